"""Galaxy models in Fourier space (sec. 3.1, 4, 6 and App. A of the paper).

A model component is a circular radial profile with a tabulated Fourier
transform ``R(rho)`` (:mod:`shearfit.engine.profiles`). Everything else is a change
of the wavevector or a factor per Fourier mode:

* ellipticity with the semi-major axis fixed: ``rho^2 = r^2 K^T C(e) K`` with
  ``C = a a^T + q^2 b b^T`` (a, b the major/minor axis directions, q = b/a);
* the exposure's local affine map (WCS Jacobian J, sec. 6): the sky wavevector
  is ``K = J^-T k`` for the pixel wavevector k;
* a sub-pixel shift d: the phase ``exp(-i k.d)``;
* the PSF (pixel response included): a product with its transform, after
  which the modes beyond Nyquist fold onto the sampled grid (App. A).

One exposure is reduced to a list of *modes* ``j`` on a fine frequency grid,
each with its sky wavevector ``K_j``, its complex transfer ``T_j`` (PSF, pixel,
shift, photometric scale) and the sampled-grid mode ``c(j)`` it folds onto:
``M_c = sum_{j -> c} T_j R(rho_j)`` is the model's DFT on the stamp. With a
native-sampled PSF the fine grid is the stamp's own (the band-limited
assumption) unless the Moffat alias correction (App. A) is switched on;
with a PSF oversampled k times, the fine grid is k times wider and the fold
is exact.
"""

from __future__ import annotations

import functools
from collections import OrderedDict

from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft
from scipy import special

from ..config import FitConfig
from ..errors import ShearfitValueError
from ..observation import Observation, is_immutable
from . import moffat as _moffat
from .moffat import fit_moffat, fit_moffats, moffat_ft, moffat_norm
from .kernel import KERNEL, USE_KERNEL

__all__ = ["ExposureModes", "prepare_exposure", "prepare_exposures", "shape_matrix", "render_object"]


def shape_matrix(e1, e2):
    """Coefficients (c11, c12, c22) of ``|K'|^2 = K^T C K`` for ellipticity e.

    The profile is stretched so that its semi-major axis keeps the circular
    profile's size and its minor axis is q = (1-|e|)/(1+|e|) times that
    (App. A); its transform is then ``R(r |K'|)`` with
    ``K' = (K.a, q K.b)``. Flux is conserved by construction.
    """
    e1 = np.asarray(e1, dtype=float)
    e2 = np.asarray(e2, dtype=float)
    e = np.hypot(e1, e2)
    q = (1.0 - e) / (1.0 + e)
    # the direction of e (1, 0 where e = 0); no division by zero to guard against
    pos = e > 0
    safe = np.where(pos, e, 1.0)
    c2 = np.where(pos, e1 / safe, 1.0)
    s2 = e2 / safe   # e2 = 0 where e = 0
    mean = 0.5 * (1.0 + q * q)
    half = 0.5 * (1.0 - q * q)
    return mean + half * c2, half * s2, mean - half * c2


def _pad_center(a, shape):
    """Crop or zero-pad ``a`` to ``shape`` keeping index (n//2) on (n//2)."""
    out = np.zeros(shape, dtype=float)
    ny, nx = a.shape
    my, mx = shape
    # source and destination windows aligned on the centres n//2
    y0s = max(0, ny // 2 - my // 2)
    x0s = max(0, nx // 2 - mx // 2)
    y0d = max(0, my // 2 - ny // 2)
    x0d = max(0, mx // 2 - nx // 2)
    hy = min(ny - y0s, my - y0d)
    hx = min(nx - x0s, mx - x0d)
    out[y0d:y0d + hy, x0d:x0d + hx] = a[y0s:y0s + hy, x0s:x0s + hx]
    return out

# --------------------------------------------------------------------------
# one exposure as a set of Fourier modes
# --------------------------------------------------------------------------

@dataclass
class ExposureModes:
    """One exposure of one object, reduced to Fourier modes (see module doc).

    Attributes
    ----------
    shape : (ny, nx) of the stamp
    kxx, kxy, kyy : sky-frame K components products (arcsec^-2) per fine mode
    kx, ky : sky-frame wavevector per fine mode (rad/arcsec)
    transfer : complex T_j (PSF, pixel, sub-pixel offset, flux scale)
    coarse : index of the sampled rfft mode each fine mode folds onto
    cweight : Hermitian weight (1 or 2) of each sampled rfft mode
    data_ft : rfft of the masked, centred stamp
    sigma2 : stationary pixel noise variance
    yy : sum of y^2 / sigma^2 over used pixels
    npix : pixels with non-zero weight
    """

    shape: tuple
    kx: np.ndarray
    ky: np.ndarray
    transfer: np.ndarray
    coarse: np.ndarray
    cweight: np.ndarray
    data_ft: np.ndarray
    sigma2: float
    yy: float
    npix: int
    pixel_scale: float


def inv2(J):
    """The inverse of a 2 x 2 matrix, by its adjugate (a tenth of np.linalg.inv's overhead)."""
    (a, b), (c, d) = np.asarray(J, float).tolist()   # Python floats: the same arithmetic, less overhead
    det = a * d - b * c
    if det == 0.0 or det != det:
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.array([[d, -b], [-c, a]]) / det   # numpy's infinities and NaNs, as before
    return np.array([[d / det, -b / det], [-c / det, a / det]])


@functools.lru_cache(maxsize=16)
def _rfft_weights(ny, nx):
    """Each rfft mode's weight in Parseval's sum over the full grid (2, or 1 for the columns that are their own
    conjugates); read-only, made once per grid."""
    w = np.full((ny, nx // 2 + 1), 2.0)
    w[:, 0] = 1.0
    if nx % 2 == 0:
        w[:, -1] = 1.0
    w.setflags(write=False)
    return w


class ContentMemo:
    """Results computed from an array (a PSF image that the objects of a CCD share, as one array or each
    object its own copy), remembered by a fingerprint of the array (its shape, type and about 256 of its values) and
    checked against a copy of its whole contents on every hit, so that an array that differs anywhere is
    computed afresh: cheaper than hashing the contents, as safe (an immutable array, ``is_immutable``, is kept
    itself, and a hit on that very array needs no comparison, nor a fingerprint: such arrays are found by their
    identity first). Least recently used entries go first beyond ``max_bytes`` (copies and results) or
    ``max_entries``."""

    def __init__(self, max_bytes, max_entries=4096):
        self._d = OrderedDict()          # (fingerprint, serial) -> (copy, result, bytes)
        self._by_fp = {}                 # fingerprint -> its keys in _d
        self._by_id = {}                 # (id of a copy that is the array itself, extra) -> its key in _d
        self._serial = 0
        self.max_bytes = max_bytes
        self.max_entries = max_entries
        self._nbytes = 0

    _MISSING = object()

    def _fingerprint(self, a, extra):
        flat = a.ravel()
        return a.shape, a.dtype.str, flat[::max(1, flat.size // 256)].tobytes(), extra

    def peek(self, a, extra, default=None):
        """The result remembered for array ``a`` and ``extra``, or ``default``."""
        a = np.asarray(a)
        # the array itself (a CCD's objects share its PSF image): found without its fingerprint, whose 256
        # scattered reads miss the cache after a fit (some 25 us; the entry holds the array, so its id is its own)
        key = self._by_id.get((id(a), extra))
        if key is not None and self._d[key][0] is a:
            self._d.move_to_end(key)
            return self._d[key][1]
        for key in self._by_fp.get(self._fingerprint(a, extra), ()):
            copy, value, _ = self._d[key]
            if copy is a or np.array_equal(copy, a):
                self._d.move_to_end(key)
                return value
        return default

    def put(self, a, extra, value):
        """Remember ``value`` for array ``a`` and ``extra`` (a copy of ``a`` is kept to check later hits)."""
        a = np.asarray(a)
        fp = self._fingerprint(a, extra)
        # an immutable array (read-only, owning its memory or a view of one that does) cannot change: kept itself,
        # so that its own later hits are recognised without comparing contents
        copy = a if is_immutable(a) else np.array(a, copy=True)
        # (an immutable view keeps its whole owner alive: counted at the owner's size)
        size = (copy.nbytes if copy.base is None else copy.base.nbytes) + sum(
            v.nbytes for v in (value if isinstance(value, tuple) else (value,)) if isinstance(v, np.ndarray))
        self._serial += 1
        key = (fp, self._serial)
        self._d[key] = (copy, value, size)
        self._by_fp.setdefault(fp, []).append(key)
        if copy is a:
            self._by_id[(id(a), extra)] = key
        self._nbytes += size
        while (self._nbytes > self.max_bytes or len(self._d) > self.max_entries) and len(self._d) > 1:
            old, (gone, _, nb) = self._d.popitem(last=False)
            self._nbytes -= nb
            keys = self._by_fp[old[0]]
            keys.remove(old)
            if not keys:
                del self._by_fp[old[0]]
            ik = (id(gone), old[0][3])   # (the fingerprint's last item is extra)
            if self._by_id.get(ik) == old:
                del self._by_id[ik]
        return value

    def get(self, a, extra, make):
        """``make()``'s result for array ``a`` and the hashable ``extra``, remembered."""
        got = self.peek(a, extra, self._MISSING)
        return self.put(a, extra, make()) if got is self._MISSING else got

    def __len__(self):
        return len(self._d)

    def values(self):
        """The remembered results, least recently used first."""
        return [v[1] for v in self._d.values()]

    def clear(self):
        self._d.clear()
        self._by_fp.clear()
        self._by_id.clear()
        self._nbytes = 0


#: _fine_modes_from_psf's results by the PSF image and the grid
_FINE_PSF = ContentMemo(64 * 2 ** 20)


def _fine_modes_from_psf(psf, s, ny, nx, tolerance=0.0):
    """Fine wavevectors (rad per stamp pixel), PSF transform, coarse index and each mode's place on the fine grid.

    The PSF array is taken on a grid s times finer than the stamp, padded or
    cropped to (s ny, s nx); its DFT gives the PSF at wavevectors up to
    s pi. Each fine mode folds onto the stamp's mode (m mod n). Only the modes
    where |T| exceeds ``tolerance`` times its largest value are kept.
    Returns (ky, kx, T, coarse, iy, ix): iy, ix the modes' rows and columns of the fine grid (numpy's FFT order),
    whose phases :func:`_offset_phases` takes one axis at a time.
    Remembered (read-only arrays, :class:`ContentMemo`): the objects of a CCD
    with one given PSF image share them (the same numbers as made afresh).
    """
    def make():
        ky, kx, T, coarse, iy, ix = _fine_modes_from_psf_made(psf, s, ny, nx)
        aT = np.abs(T)
        keep = aT > tolerance * aT.max()
        got = ky[keep], kx[keep], T[keep], coarse[keep], iy[keep], ix[keep]
        for arr in got:
            arr.setflags(write=False)
        return got
    return _FINE_PSF.get(psf, (int(s), int(ny), int(nx), float(tolerance)), make)


@functools.lru_cache(maxsize=32)
def _signed_freqs(n):
    """numpy's FFT order's signed integer frequencies of an n-point grid (read-only, shared)."""
    out = np.rint(np.fft.fftfreq(n) * n).astype(int)
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=16)
def _fine_geometry(s, ny, nx):
    """What :func:`_fine_modes_from_psf_made` takes from the grids alone (read-only, shared): the modes folding onto
    the stamp's rfft half-plane, in the fine grid's row-major order, as (ky, kx, coarse, iy, ix, at, mirror): their
    wavevectors, folded stamp mode, fine row and column (numpy's FFT order), their place in the fine grid's rfft2
    (flat index) and whether they are the conjugate of the mode there (kx < 0, by the real image's Hermitian
    symmetry)."""
    fy, fx = s * ny, s * nx
    my, mx = _signed_freqs(fy), _signed_freqs(fx)
    cols = np.nonzero(mx % nx <= nx // 2)[0]   # the columns folding onto the half-plane, in every row
    iy, ix = np.repeat(np.arange(fy), cols.size), np.tile(cols, fy)
    MY, MX = my[iy], mx[ix]
    mirror = MX < 0
    at = np.where(mirror, (-MY) % fy, MY % fy) * (fx // 2 + 1) + np.abs(MX)
    got = (2 * np.pi * MY / ny, 2 * np.pi * MX / nx, (MY % ny) * (nx // 2 + 1) + MX % nx, iy, ix, at, mirror)
    for arr in got:
        arr.setflags(write=False)
    return got


def _fine_modes_from_psf_made(psf, s, ny, nx):
    fy, fx = s * ny, s * nx
    ky, kx, coarse, iy, ix, at, mirror = _fine_geometry(int(s), int(ny), int(nx))
    # the real image's transform over the half-plane (rfft2 of the image with its centre at the origin), each kept
    # mode read there or at its mirror -k
    P = np.fft.rfft2(_ifftshift2(_pad_center(psf, (fy, fx)))).ravel()[at]
    np.conjugate(P, out=P, where=mirror)
    return ky, kx, P, coarse, iy, ix


def _offset_phases(iy, ix, fy, fx, ny, nx, dx, dy):
    """exp(-i (kx dx + ky dy)) of the fine modes (rows ``iy`` and columns ``ix`` of the (fy, fx) grid, kx = 2 pi mx /
    nx, ky = 2 pi my / ny), one axis at a time: the product of a phase per column and one per row (the same to
    rounding as the whole exponent)."""
    px = np.exp(-1j * dx * (2 * np.pi / nx) * _signed_freqs(fx))
    py = np.exp(-1j * dy * (2 * np.pi / ny) * _signed_freqs(fy))
    return px[ix] * py[iy]


def psf_moffat(psf):
    """(rs, beta), in pixels, of the circular Moffat that stands for a native PSF above Nyquist (App. A; see
    :func:`shearfit.engine.moffat.fit_moffat`).

    The paper fits one such Moffat near the field centre; ``shearfit measure`` fits one per CCD, to the PSF
    model at the CCD's centre. A user of :func:`shearfit.measure_object` with many objects per exposure does
    the same by fitting it once per CCD and passing it as ``Observation(..., psf_moffat=...)`` to each object
    there: without it every object's every PSF is fitted, with its own alias tables (``benchmarks/speed.py
    --moffat-per-exposure`` against the default: 1.87 against 2.23 times GalSim HSM's time, session 78).
    """
    ny, nx = (n + n % 2 for n in psf.shape)
    return _fit_moffat_rfft(_centred_rfft2(_pad_center(psf, (ny, nx))), ny, nx)


def psf_moffats(psfs):
    """:func:`psf_moffat` of several native PSF images, those of equal shapes fitted as one batch
    (:func:`shearfit.engine.moffat.fit_moffats`: the same numbers as one by one). Returns [(rs, beta), ...]."""
    psfs = list(psfs)
    out = [None] * len(psfs)
    for (ny, nx), idx in indices_by_shape(tuple(n + n % 2 for n in p.shape) for p in psfs).items():
        fts = [_centred_rfft2(_pad_center(psfs[i], (ny, nx))) for i in idx]
        for i, fit in zip(idx, fit_moffats(fts, 2 * np.pi * np.fft.fftfreq(ny), 2 * np.pi * np.fft.rfftfreq(nx))):
            out[i] = fit
    return out


def _fit_moffat_rfft(Ps, ny, nx):
    """fit_moffat of the rfft ``Ps`` of a PSF on a (ny, nx) grid."""
    return fit_moffat(Ps, 2 * np.pi * np.fft.fftfreq(ny), 2 * np.pi * np.fft.rfftfreq(nx))


#: Moffats fitted to observations' own PSFs (see _own_moffat)
_OWN_MOFFAT = ContentMemo(16 * 2 ** 20, max_entries=512)


def _own_moffat(psf, Ps, ny, nx):
    """fit_moffat of a PSF without a given Moffat, remembered by the PSF image (:class:`ContentMemo`):
    objects handed the same PSF image (a constant PSF per exposure, as in the GREAT challenges) fit it once
    and share its alias tables. The same fit, bit for bit, as without the memory."""
    return _OWN_MOFFAT.get(psf, (ny, nx), lambda: _fit_moffat_rfft(Ps, ny, nx))


#: aliases of the stamp's modes the Moffat is summed over, each way (beyond +-2 it is below 1e-8)
_N_ALIAS = 2
#: points of the Moffat's |k| table
_N_KTAB = 4001


@functools.lru_cache(maxsize=8)
def _alias_geometry(ny, nx, s):
    """What the alias tables of a (ny, nx) stamp share whatever the Moffat: |k| and the pixel response of
    every alias k + 2 pi n, n in [-2, 2]^2, and the wavevectors and folded mode of the s x s kept ones
    (and, for phases, their ky and kx as (the values, each mode's index in them))."""
    kyc = 2 * np.pi * np.fft.fftfreq(ny)
    kxc = 2 * np.pi * np.fft.rfftfreq(nx)
    na = _N_ALIAS
    offs = 2 * np.pi * np.arange(-na, na + 1)
    kmax = np.hypot(np.pi + offs[-1], np.pi + offs[-1]) + 1.0
    KYa = kyc[None, :] + offs[:, None]                     # (5, ny)
    KXa = kxc[None, :] + offs[:, None]                     # (5, nxh)
    sy = np.sinc(KYa / (2 * np.pi))
    sx = np.sinc(KXa / (2 * np.pi))
    kk = np.hypot(KYa[:, None, :, None], KXa[None, :, None, :])          # (5, 5, ny, nxh)
    pix = sy[:, None, :, None] * sx[None, :, None, :]
    # linear interpolation on the uniform |k| table, weights with the pixel response folded in
    ktab = np.linspace(0.0, kmax, _N_KTAB)
    u = kk * ((_N_KTAB - 1) / kmax)
    i0 = np.minimum(u.astype(np.intp), _N_KTAB - 2)
    t = u - i0
    w0, w1 = (1.0 - t) * pix, t * pix
    half = s // 2
    sel = slice(na - half, na + half + 1)
    shape = kk[sel, sel].shape
    nxh = kxc.size
    KYf = np.broadcast_to(KYa[sel][:, None, :, None], shape).ravel()
    KXf = np.broadcast_to(KXa[sel][None, :, None, :], shape).ravel()
    coarse_index = (np.arange(ny)[:, None] * nxh + np.arange(nxh)[None, :])
    cs = np.broadcast_to(coarse_index, shape).ravel()
    kyv, kxv = KYa[sel].ravel(), KXa[sel].ravel()
    iy = np.broadcast_to(np.arange(kyv.size).reshape(s, 1, ny, 1), shape).ravel()
    ix = np.broadcast_to(np.arange(kxv.size).reshape(1, s, 1, nxh), shape).ravel()
    for arr in (ktab, i0, w0, w1, KYf, KXf, cs, kyv, kxv, iy, ix):
        arr.setflags(write=False)
    return ktab, i0, w0, w1, sel, KYf, KXf, cs, (kyv, iy, kxv, ix)


@functools.lru_cache(maxsize=8)
def _alias_mirrored(ny, nx, s):
    """Whether the alias geometry of a (ny, nx) stamp is its own mirror image in ky to the bit: row ny - r's alias
    (ny_a, nx_a) has row r's (-ny_a, nx_a) table index and weights (2 pi fftfreq, hypot and sinc are odd or even
    exactly where the C library's sin is odd), so that ``KERNEL.alias_sums_mirror`` may make the tables from half
    the rows (the same numbers)."""
    _, i0, w0, w1 = _alias_geometry(ny, nx, s)[:4]
    rows = (ny - np.arange(1, (ny + 1) // 2)) % ny      # the mirrored rows ny - r, r = 1 .. ceil(ny / 2) - 1
    src = np.arange(1, (ny + 1) // 2)
    return all(np.array_equal(a[::-1, :, rows], a[:, :, src]) for a in (i0, w0, w1))


#: the alias tables' Moffat (:func:`_moffat_table`) is exact below x = k rs = 1 where beta < MOFFAT_SMOOTH_BETA (the
#: transform's cusp: x^(2 nu) with 2 nu < 3), below x = 0.05 otherwise
MOFFAT_SMOOTH_BETA = 2.5


def _moffat_table(k, rs, beta, x_exact=None, h0=0.1, grow=0.1, floor=1e-30, use_kernel=True):
    """moffat_ft on a uniform grid k, set to zero where it falls below ``floor``.

    Exact up to x = k rs = ``x_exact`` (None: 1 where beta < MOFFAT_SMOOTH_BETA, where the transform has its
    cusp, else 0.05); beyond, the quintic Hermite interpolant of its logarithm through exact nodes, with the exact
    slopes d log f / dx = -K_(nu-1)(x) / K_nu(x) and curvatures there (from Bessel's equation, K''/K = 1 +
    nu^2 / x^2 - (K'/K) / x: no more Bessel functions than the slopes). The logarithm's higher derivatives fall
    as x grows (it tends to -x + (nu - 1/2) log x), so the nodes are ``h0 + grow x`` apart. Within 2.2e-8 of the
    exact values (tests/test_model.py, beta 1.2-21 and rs 0.05-40 pixels), far below the error of the linear
    interpolation in the table (at its midpoints 6e-6 for rs = 1.7, beta 3; 1e-3 for rs = 15.8, beta 2.5).
    Until session 82 the interpolant was cubic, through nodes 0.06 + 0.03 x apart beyond x = 1 (within 1.5e-7):
    at the fitted rs of 2.4-5 pixels of ``benchmarks/speed.py``'s PSFs a table took some 250 Bessel functions, now
    about 95. The transform decreases monotonically (its derivative is -c x^nu K_(nu-1)(x)), so it is zero beyond
    the last node above the floor. The compiled kernel (``moffat_table``, with scipy's kv and gamma) makes the
    same numbers to rounding (tests/test_model.py) without the array operations' overhead, which was most of a
    table's time where every exposure of every object had its own PSF and so its own Moffat.
    """
    n = k.size
    if x_exact is None:
        x_exact = 1.0 if beta < MOFFAT_SMOOTH_BETA else 0.05
    if use_kernel and _moffat.USE_KERNEL_BESSEL:
        out = np.empty(n)
        KERNEL.moffat_table(np.ascontiguousarray(k, dtype=float), float(rs), float(beta), float(x_exact), float(h0),
                            float(grow), float(floor), out)
        return out
    dx = (k[1] - k[0]) * rs
    j = int(np.ceil(x_exact / dx))
    if n - j >= 8:
        # node i at x_i = (x_exact + h0 / grow) (1 + grow)^i - h0 / grow: x_(i+1) - x_i = h0 + grow x_i
        top = (k[-1] * rs + h0 / grow) / (x_exact + h0 / grow)
        count = int(np.ceil(np.log(top) / np.log1p(grow))) + 1
        xs = (x_exact + h0 / grow) * (1.0 + grow) ** np.arange(count) - h0 / grow
        nodes = np.clip(np.rint(xs / dx).astype(np.intp), j, n - 1)   # non-decreasing: drop the repeats
        nodes = nodes[np.concatenate(([True], nodes[1:] != nodes[:-1]))]
        nu = beta - 1.0
        xn = k[nodes] * rs
        kvn = special.kv(nu, xn)
        v = moffat_norm(nu) * xn ** nu * kvn
        m = int(np.count_nonzero(v >= floor))
        if m >= 4:
            out = np.zeros_like(k)
            out[:j] = moffat_ft(k[:j], rs, beta)
            nodes, v, xn, kvn = nodes[:m], v[:m], xn[:m], kvn[:m]
            last = nodes[-1]
            ratio = special.kv(nu - 1.0, xn) / kvn
            rho = -ratio - nu / xn                          # K_nu' / K_nu
            slope = -rs * ratio                             # d log f / dk at the nodes
            curv = rs * rs * ((1.0 + (nu * nu - nu) / (xn * xn)) - rho / xn - rho * rho)   # d^2 log f / dk^2
            lv = np.log(v)
            if USE_KERNEL:
                KERNEL.hermite_log_table(float(k[0]), float(k[1] - k[0]), nodes.astype(np.int64), lv, slope, curv,
                                         out)
            else:
                seg = np.repeat(np.arange(m - 1), np.diff(nodes))   # each point's segment, points j .. last - 1
                k0 = k[nodes[seg]]
                h = k[nodes[seg + 1]] - k0
                t = (k[j:last] - k0) / h
                t2 = t * t
                t3 = t2 * t
                t4 = t3 * t
                t5 = t4 * t
                out[j:last] = np.exp((1 - 10 * t3 + 15 * t4 - 6 * t5) * lv[seg]
                                     + (t - 6 * t3 + 8 * t4 - 3 * t5) * (h * slope[seg])
                                     + 0.5 * (t2 - 3 * t3 + 3 * t4 - t5) * (h * h * curv[seg])
                                     + (10 * t3 - 15 * t4 + 6 * t5) * lv[seg + 1]
                                     + (-4 * t3 + 7 * t4 - 3 * t5) * (h * slope[seg + 1])
                                     + 0.5 * (t3 - 2 * t4 + t5) * (h * h * curv[seg + 1]))
            out[nodes] = v
            return out
    out = moffat_ft(k, rs, beta)
    out[out < floor] = 0.0
    return out


@functools.lru_cache(maxsize=8)
def _kept_aliases(ny, nx, s):
    """The indices, among the 5 x 5 aliases of ``_alias_geometry``, of the s x s ones kept."""
    geometry = _alias_geometry(ny, nx, s)
    i0, sel = geometry[1], geometry[4]
    na = i0.shape[0]
    kept = np.arange(na * na).reshape(na, na)[sel, sel].ravel()
    kept.setflags(write=False)
    return kept


@functools.lru_cache(maxsize=64)
def _moffat_aliases(rs, beta, ny, nx, s):
    """The Moffat (times the pixel response) at every alias of the stamp's rfft modes.

    Returns the aliased sum ``A = sum_n G(k + 2 pi n)`` over n in [-2, 2]^2
    (beyond +-2 the Moffat is below 1e-8), set to 1 where |A| <= 1e-12, and
    the mask of |A| > 1e-12 (elsewhere the model's ratio P_s / A is 0); then,
    for the s x s aliases the model keeps, G (flattened) and |G| with their
    wavevectors and the sampled mode each folds onto, and each mode's largest
    |G|^2 over those aliases. Cached: one exposure's
    CCD shares one Moffat (App. A fits one near the field centre), so its
    objects reuse these tables.
    """
    ktab, i0, w0, w1, sel, KYf, KXf, cs, _ = _alias_geometry(ny, nx, s)
    # the Moffat's transform is radial: tabulate it once on |k| and interpolate linearly
    mtab = _moffat_table(ktab, rs, beta)
    if USE_KERNEL:
        # the same sums in one pass, without the (5, 5, ny, nx/2 + 1) array G, and each mode's largest |G|^2
        kept = _kept_aliases(ny, nx, s)
        A = np.empty(i0.shape[2:])
        Gs = np.empty(kept.size * A.size)
        G2max = np.empty(A.size)
        if _alias_mirrored(ny, nx, s):
            # half the rows' interpolations: the others are their mirror images (the same numbers)
            KERNEL.alias_sums_mirror(mtab, i0, w0, w1, kept, A, Gs, G2max, ny, A.shape[1], i0.shape[0])
        else:
            KERNEL.alias_sums(mtab, i0, w0, w1, kept, A, Gs, G2max)
        absG = None   # fine_modes_select squares G itself: |G|^2 = G^2
    else:
        G = mtab[i0] * w0 + mtab[i0 + 1] * w1
        A = G.sum(axis=(0, 1))
        Gs = G[sel, sel].ravel()
        absG = np.abs(Gs)
        G2max = (absG.reshape(-1, A.size) ** 2).max(axis=0)   # each mode's largest |G|^2 (fine_modes_select)
    ok = np.abs(A) > 1e-12
    A = np.where(ok, A, 1.0)   # where not ok, the ratio P_s / A is set to 0
    for arr in (A, ok, Gs, absG, G2max):
        if arr is not None:
            arr.setflags(write=False)
    return A, ok, Gs, absG, KYf, KXf, cs, G2max


def _centred_rfft2(a):
    """rfft2 of arrays (the last two axes) whose centre pixel (n//2) is the origin (scipy's FFT: the
    same numbers as numpy's, with less overhead per call on stamps this small)."""
    return sfft.rfft2(_ifftshift2(a))


def _ifftshift2(a):
    """np.fft.ifftshift over the last two axes in one copy (the quadrants swapped; ifftshift rolls one axis at a
    time, two copies): the same array."""
    a = np.asarray(a)
    ny, nx = a.shape[-2:]
    hy, hx = ny // 2, nx // 2
    out = np.empty_like(a)
    out[..., :ny - hy, :nx - hx] = a[..., hy:, hx:]
    out[..., :ny - hy, nx - hx:] = a[..., hy:, :hx]
    out[..., ny - hy:, :nx - hx] = a[..., :hy, hx:]
    out[..., ny - hy:, nx - hx:] = a[..., :hy, :hx]
    return out


def _fine_modes_moffat(psf, ny, nx, s, moffat=None, tolerance=0.0, Ps=None, offset=None):
    """Native PSF with the App. A alias correction, generalised (see fit_moffat).

    Above Nyquist the PSF is taken to be a circular Moffat times the pixel
    response, scaled mode by mode so that its aliased sum reproduces the
    sampled PSF's transform exactly inside the band: the model is
    ``sum_n (R G)(k + 2 pi n) * P_s(k) / sum_n G(k + 2 pi n)``. For a
    band-limited PSF this is the exact convolution; for a Moffat-like PSF it
    models the modes a native image cannot hold. ``moffat`` = (rs, beta)
    gives the Moffat (one per CCD, as the pipeline does); by default it is
    fitted to this PSF. ``Ps``: the PSF's rfft on the grid, if already made.
    ``offset`` = (dx, dy) pixels: the transfer times the phase exp(-i (kx dx + ky dy)) that puts the
    model's origin there (made as the product of a phase in kx and one in ky).
    """
    if Ps is None:
        Ps = _centred_rfft2(_pad_center(psf, (ny, nx)))
    if moffat is None:
        rs, beta = _own_moffat(psf, Ps, ny, nx)
    else:
        rs, beta = moffat
    A, ok, Gs, absG, KYf, KXf, cs, G2max = _moffat_aliases(float(rs), float(beta), ny, nx, int(s))
    if USE_KERNEL:
        # the same selection and products in one pass (fine_modes_select)
        kyv, _, kxv, _ = _alias_geometry(ny, nx, int(s))[-1]
        dx, dy = (0.0, 0.0) if offset is None else (float(offset[0]), float(offset[1]))
        n = Gs.size
        ky, kx, T, c = np.empty(n), np.empty(n), np.empty(n, complex), np.empty(n, np.int64)
        # (its absG argument is only squared: G itself serves where the tables were made without |G|)
        m = KERNEL.fine_modes_select(np.ascontiguousarray(Ps, complex).ravel(), A.ravel(), ok.ravel(),
                                     Gs if absG is None else absG, Gs,
                                     G2max, kyv, kxv, dx, dy, int(s), ny, nx // 2 + 1, float(tolerance), ky, kx, T, c)
        return ky[:m], kx[:m], T[:m], c[:m]
    if absG is None:
        absG = np.abs(Gs)
    ratio = np.where(ok, Ps / A, 0.0).ravel()
    # only the modes above ``tolerance`` of the largest |T| (G is real: |T| = |G| |ratio|)
    mag = (absG.reshape(-1, ratio.size) * np.abs(ratio)[None]).ravel()
    idx = np.nonzero(mag > tolerance * mag.max())[0]
    c = cs[idx]
    T = Gs[idx] * ratio[c]
    if offset is not None:
        kyv, iy, kxv, ix = _alias_geometry(ny, nx, int(s))[-1]
        T = T * (np.exp(-1j * kxv * offset[0])[ix[idx]] * np.exp(-1j * kyv * offset[1])[iy[idx]])
    return KYf[idx], KXf[idx], T, c


def noise_variance(weight, stats=None):
    """Stationary noise variance of a stamp: 1 / median of the positive weights. ``stats``: (count, least, largest,
    ...) of the positive weights where already known (:func:`_masked_stamp`'s)."""
    if stats is not None:
        count, lo, hi = stats[:3]
        if count == 0:
            raise ShearfitValueError("stamp has no pixel with positive weight")
        if lo == hi:
            return 1.0 / float(lo)
    w = weight[weight > 0]
    if w.size == 0:
        raise ShearfitValueError("stamp has no pixel with positive weight")
    lo = w.min()
    if lo == w.max():
        return 1.0 / float(lo)   # one weight throughout (the usual stamp): the median is that value
    # np.median's value, from a partition alone
    h = w.size // 2
    if w.size % 2:
        return 1.0 / float(np.partition(w, h)[h])
    p = np.partition(w, (h - 1, h))
    return 1.0 / float((p[h - 1] + p[h]) / 2)


def _masked_stamp(obs, ny, nx, stats=None, out=None):
    """The stamp where its weight is positive, 0 elsewhere, on the (ny, nx) grid (into ``out``, a (ny, nx) float64
    C-contiguous array, where given). With ``stats`` (a dict), the compiled kernel (``masked_stamp``) makes it where
    it can, the same numbers, and stores the positive weights' count, least and largest and the stamp's sum y^2
    there as ``stats["weights"]`` (for :func:`_data_modes`)."""
    im, w = obs.image, obs.weight
    if (stats is not None and USE_KERNEL and im.shape == (ny, nx) and w.shape == im.shape
            and im.dtype == np.float64 and w.dtype == np.float64):
        y = np.empty((ny, nx)) if out is None else out
        stats["weights"] = KERNEL.masked_stamp(np.ascontiguousarray(im), np.ascontiguousarray(w), y)
        return y
    y = np.where(w > 0, im, 0.0)
    y = y if y.shape == (ny, nx) else _pad_center(y, (ny, nx))
    if out is None:
        return y
    out[...] = y
    return out


def _data_modes(obs, ny, nx, y=None, data_ft=None, wstats=None):
    """The stamp's noise variance, rfft (masked, centred on the grid), sum y^2 / sigma^2 and used pixels
    (``y``, ``data_ft``: the masked stamp on the grid and its rfft, if already made; ``wstats``: the positive
    weights' count, least and largest and y's sum of squares, :func:`_masked_stamp`'s for this ``y``)."""
    sigma2 = noise_variance(obs.weight, wstats)
    if y is None:
        y = _masked_stamp(obs, ny, nx)
    if data_ft is None:
        data_ft = _centred_rfft2(y)
    if wstats is not None:
        # (the stamp's count of used pixels and sum y^2 as the compiled masked stamp made them with it)
        return sigma2, data_ft.ravel(), float(wstats[3] / sigma2), int(wstats[0])
    return sigma2, data_ft.ravel(), float(np.sum(y * y) / sigma2), int(np.count_nonzero(obs.weight > 0))


def indices_by_shape(shapes):
    """{shape: the indices of the items of that shape, in order}, for transforms batched per shape."""
    out = {}
    for i, shp in enumerate(shapes):
        out.setdefault(tuple(shp), []).append(i)
    return out


def prepare_exposures(observations, cfg: FitConfig, likes=None) -> list:
    """:func:`prepare_exposure` of each observation (``likes``: its ``like`` each, or None), the same
    numbers; the stamps' and native PSFs' transforms of equal shapes are made in one call each."""
    observations = list(observations)
    likes = [None] * len(observations) if likes is None else list(likes)
    if len(likes) != len(observations):
        raise ShearfitValueError("prepare_exposures: one like= per observation is needed")
    alias = cfg.alias_correction == "moffat"
    pre = [{} for _ in observations]
    for (ny, nx), idx in indices_by_shape(o.shape for o in observations).items():
        if len(idx) < 2:
            continue
        # (the masked stamps made in one stack: the transforms' input without a copy)
        ys = np.empty((len(idx), ny, nx))
        for i, y in zip(idx, ys):
            _masked_stamp(observations[i], ny, nx, pre[i], out=y)
        for i, y, f in zip(idx, ys, _centred_rfft2(ys)):
            pre[i]["y"], pre[i]["data_ft"] = y, f
        native = [i for i in idx if likes[i] is None and alias and observations[i].psf_oversampling == 1]
        if len(native) >= 2:
            P = _centred_rfft2(np.stack([_pad_center(observations[i].psf, (ny, nx)) for i in native]))
            for i, Ps in zip(native, P):
                pre[i]["Ps"] = Ps
            # the App. A Moffats the exposures' own PSFs need, fitted in one batch (fit_moffats)
            need = [i for i in native if observations[i].psf_moffat is None
                    and _OWN_MOFFAT.peek(observations[i].psf, (ny, nx)) is None]
            if len(need) >= 2:
                fits = fit_moffats([pre[i]["Ps"] for i in need], 2 * np.pi * np.fft.fftfreq(ny),
                                   2 * np.pi * np.fft.rfftfreq(nx))
                for i, fit in zip(need, fits):
                    # (and handed to its exposure: the memory's lookup of the same PSF, a fingerprint and a
                    # comparison of the image, cost 1 % of a fit whose every PSF is new)
                    pre[i]["moffat"] = _OWN_MOFFAT.put(observations[i].psf, (ny, nx), fit)
    return [prepare_exposure(o, cfg, like=lk, _pre=p) for o, lk, p in zip(observations, likes, pre)]


def prepare_exposure(obs: Observation, cfg: FitConfig, grid_shape=None, with_data=True, like=None,
                     _pre=None, use_kernel=True) -> ExposureModes:
    """Reduce one observation to its Fourier modes.

    ``grid_shape`` (default: the stamp's) is the periodic grid the model
    lives on; rendering pads it to avoid wrap-around. ``like``: the
    ExposureModes of an observation with the same PSF, Moffat, Jacobian,
    offset, flux scale and shape (another version of the same stamp, as
    metacalibration's): its modes are reused and only the data transformed.
    (``_pre``: transforms :func:`prepare_exposures` made for it; ``use_kernel=False``: the sky wavevectors and the
    transfer's flux scale by the numpy lines, the reference of the compiled ``sky_modes``.)
    """
    ny, nx = grid_shape if grid_shape is not None else obs.shape
    pre = _pre or {}
    if like is not None:
        if like.shape != (ny, nx):
            raise ShearfitValueError(f"prepare_exposure: like= has shape {like.shape}, the stamp {(ny, nx)}")
        sigma2, data_ft, yy, npix = _data_modes(obs, ny, nx, pre.get("y"), pre.get("data_ft"), pre.get("weights"))
        # (``replace(like, data_ft=..., ...)``, made directly: a fifth of its cost, which metacal's replays pay for
        # every version of every exposure)
        return ExposureModes(like.shape, like.kx, like.ky, like.transfer, like.coarse, like.cweight, data_ft, sigma2,
                             yy, npix, like.pixel_scale)
    s = obs.psf_oversampling
    if s == 1 and cfg.alias_correction == "moffat":
        # the modes below the tolerance are dropped as they are made; the object's nominal position sits
        # at (stamp centre + offset)
        moffat = obs.psf_moffat if obs.psf_moffat is not None else pre.get("moffat")
        ky, kx, T, coarse = _fine_modes_moffat(obs.psf, ny, nx, cfg.alias_oversampling, moffat,
                                               cfg.psf_mode_tolerance, Ps=pre.get("Ps"), offset=obs.offset)
    else:
        ky, kx, T, coarse, iy, ix = _fine_modes_from_psf(obs.psf, s, ny, nx, cfg.psf_mode_tolerance)
        # the object's nominal position sits at (stamp centre + offset)
        dx, dy = obs.offset
        T = T * _offset_phases(iy, ix, s * ny, s * nx, ny, nx, dx, dy)
    # sky wavevector K = J^-T k, and the transfer times the flux scale
    Jinv_T = inv2(obs.jacobian).T
    if USE_KERNEL and use_kernel:
        # (the compiled kernel: the same products in one pass)
        Kx, Ky, Ts = np.empty(kx.size), np.empty(kx.size), np.empty(kx.size, complex)
        KERNEL.sky_modes(np.ascontiguousarray(kx, dtype=float), np.ascontiguousarray(ky, dtype=float),
                         np.ascontiguousarray(T, dtype=complex), np.ascontiguousarray(Jinv_T, dtype=float),
                         float(obs.flux_scale), Kx, Ky, Ts)
        T = Ts
    else:
        T = T * obs.flux_scale
        Kx = Jinv_T[0, 0] * kx + Jinv_T[0, 1] * ky
        Ky = Jinv_T[1, 0] * kx + Jinv_T[1, 1] * ky
    cweight = _rfft_weights(ny, nx).ravel()
    sigma2, data_ft, yy, npix = (_data_modes(obs, ny, nx, pre.get("y"), pre.get("data_ft"), pre.get("weights"))
                                 if with_data else (1.0, None, 0.0, 0))
    return ExposureModes(shape=(ny, nx), kx=Kx, ky=Ky, transfer=T, coarse=coarse, cweight=cweight,
                         data_ft=data_ft, sigma2=sigma2, yy=yy, npix=npix, pixel_scale=obs.pixel_scale)


def complex_bincount(index, values, n, use_kernel=True):
    """The sum of complex ``values`` into ``n`` bins by ``index`` (numpy's bincount takes real weights); each bin's
    sum in the order of ``values``, as ``np.add.at`` makes it. (The compiled ``complex_bincount`` where the index is
    int64 and the values complex128, the same numbers in one pass; these lines stay as its reference.)"""
    if (use_kernel and USE_KERNEL and isinstance(index, np.ndarray) and index.dtype == np.int64
            and isinstance(values, np.ndarray) and values.dtype == np.complex128 and index.ndim == values.ndim == 1
            and index.size == values.size):
        out = np.empty(int(n), complex)
        if KERNEL.complex_bincount(np.ascontiguousarray(index), np.ascontiguousarray(values), out):
            return out
    return np.bincount(index, values.real, n) + 1j * np.bincount(index, values.imag, n)


def model_ft(modes: ExposureModes, profile, e1, e2, r):
    """Model DFT on the rfft grid of ``modes.shape`` for unit flux of one component."""
    c11, c12, c22 = shape_matrix(e1, e2)
    rho2 = r * r * (c11 * modes.kx ** 2 + 2 * c12 * modes.kx * modes.ky + c22 * modes.ky ** 2)
    vals = modes.transfer * profile.ft_rho2(rho2)
    ny, nx = modes.shape
    return complex_bincount(modes.coarse, vals, ny * (nx // 2 + 1)).reshape(ny, nx // 2 + 1)


def render_object(obs: Observation, e1, e2, scalelength, bulge_fraction, flux, config=None):
    """The PSF-convolved, pixelised model of a bulge+disk galaxy on ``obs``'s stamp.

    The model is computed on a grid padded so that the truncated profile and
    the PSF do not wrap around, then cut to the stamp. Returns counts: total
    ``flux * obs.flux_scale`` (before the cut).
    """
    from .profiles import de_vaucouleurs, exponential_disk

    from ..config import as_config

    cfg = as_config(config)
    ny, nx = obs.shape
    pix = obs.pixel_scale
    extent = cfg.truncation * scalelength * max(1.0, cfg.bulge_size_ratio) / pix
    psf_half = max(obs.psf.shape) / obs.psf_oversampling / 2
    need = int(np.ceil(2 * (extent + psf_half + np.abs(obs.offset).max()) + 4))
    n = max(ny, nx, need)
    n += n % 2
    modes = prepare_exposure(obs, cfg, grid_shape=(n, n), with_data=False)
    disk = exponential_disk(cfg.truncation)
    bulge = de_vaucouleurs(cfg.truncation)
    M = (1.0 - bulge_fraction) * model_ft(modes, disk, e1, e2, scalelength)
    if bulge_fraction != 0:
        M = M + bulge_fraction * model_ft(modes, bulge, e1, e2, scalelength * cfg.bulge_size_ratio)
    img = np.fft.fftshift(np.fft.irfft2(M, s=(n, n))) * flux
    return _pad_center(img, (ny, nx))

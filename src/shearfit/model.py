"""Galaxy models in Fourier space (sec. 3.1, 4, 6 and App. A of the paper).

A model component is a circular radial profile with a tabulated Fourier
transform ``R(rho)`` (:mod:`shearfit.profiles`). Everything else is a change
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
assumption) unless the elliptical-Moffat alias correction is switched on;
with a PSF oversampled k times, the fine grid is k times wider and the fold
is exact.
"""

from __future__ import annotations

import functools

from dataclasses import dataclass, replace

import numpy as np
from scipy import special

from .config import FitConfig
from .errors import ShearfitValueError
from .observation import Observation

__all__ = ["ExposureModes", "prepare_exposure", "shape_matrix", "render_object", "fit_moffat"]


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
    with np.errstate(invalid="ignore", divide="ignore"):
        c2 = np.where(e > 0, e1 / np.where(e > 0, e, 1.0), 1.0)
        s2 = np.where(e > 0, e2 / np.where(e > 0, e, 1.0), 0.0)
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
# elliptical Moffat, used only to model a native PSF above Nyquist (App. A)
# --------------------------------------------------------------------------

def _moffat_ft(k, rs, beta):
    """Transform of a unit-flux circular Moffat (1+(r/rs)^2)^-beta at |k| (beta > 1)."""
    nu = beta - 1.0
    x = np.asarray(k, dtype=float) * rs
    out = np.ones_like(x)
    pos = x > 1e-8
    xp = x[pos]
    out[pos] = (2.0 ** (1.0 - nu) / special.gamma(nu)) * xp ** nu * special.kv(nu, xp)
    return out


def fit_moffat(psf_ft_coarse, ky, kx):
    """Fit a circular Moffat (times the pixel response) to a native PSF's transform.

    Only modes well inside the band (|k| < 0.7 pi) enter, where aliasing is
    negligible, so the fitted profile can stand for the PSF above Nyquist. The
    paper fits a circular Moffat near the field centre (App. A); here one is
    fitted per exposure.

    Returns (rs, beta) in pixels.
    """
    from scipy.optimize import least_squares

    kk = np.hypot(ky[:, None], kx[None, :])
    pix = np.sinc(ky[:, None] / (2 * np.pi)) * np.sinc(kx[None, :] / (2 * np.pi))
    sel = (kk > 0) & (kk < 0.7 * np.pi)
    # azimuthal average in narrow rings keeps the fit cheap and makes it circular
    edges = np.linspace(0, 0.7 * np.pi, 15)
    idx = np.digitize(kk[sel], edges)
    val = (np.abs(psf_ft_coarse)[sel] / pix[sel])
    kr = np.array([kk[sel][idx == i].mean() for i in range(1, len(edges)) if np.any(idx == i)])
    vr = np.array([val[idx == i].mean() for i in range(1, len(edges)) if np.any(idx == i)])

    def resid(p):
        return _moffat_ft(kr, np.exp(p[0]), 1.0 + np.exp(p[1])) - vr

    # starting size from the half-power wavenumber of a Gaussian of similar width
    khalf = kr[np.argmin(np.abs(vr - 0.5))] if np.any(vr < 0.5) else 0.5
    # unbounded Levenberg-Marquardt (the log parameters keep rs > 0, beta > 1), then clipped to a
    # sane range: a few times cheaper than a bounded solver for these two parameters
    sol = least_squares(resid, x0=[np.log(1.2 / khalf), np.log(2.0)], method="lm")
    lrs = float(np.clip(sol.x[0], np.log(0.05), np.log(50.0)))
    lb = float(np.clip(sol.x[1], np.log(0.2), np.log(20.0)))
    return float(np.exp(lrs)), float(1.0 + np.exp(lb))


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


def _rfft_weights(ny, nx):
    w = np.full((ny, nx // 2 + 1), 2.0)
    w[:, 0] = 1.0
    if nx % 2 == 0:
        w[:, -1] = 1.0
    return w


def _fine_modes_from_psf(psf, s, ny, nx):
    """Fine wavevectors (rad per stamp pixel), PSF transform and coarse index.

    The PSF array is taken on a grid s times finer than the stamp, padded or
    cropped to (s ny, s nx); its DFT gives the PSF at wavevectors up to
    s pi. Each fine mode folds onto the stamp's mode (m mod n).
    """
    fy, fx = s * ny, s * nx
    p = _pad_center(psf, (fy, fx))
    P = np.fft.fft2(np.fft.ifftshift(p))
    my = np.rint(np.fft.fftfreq(fy) * fy).astype(int)   # signed integer frequencies
    mx = np.rint(np.fft.fftfreq(fx) * fx).astype(int)
    MY, MX = np.meshgrid(my, mx, indexing="ij")
    cy = MY % ny
    cx = MX % nx
    keep = cx <= nx // 2   # only modes folding onto the rfft half-plane
    ky = 2 * np.pi * MY[keep] / ny
    kx = 2 * np.pi * MX[keep] / nx
    coarse = cy[keep] * (nx // 2 + 1) + cx[keep]
    return ky, kx, P[keep], coarse


def psf_moffat(psf):
    """(rs, beta) of the circular Moffat that stands for a native PSF above Nyquist (see fit_moffat)."""
    ny, nx = psf.shape
    Ps = np.fft.rfft2(np.fft.ifftshift(_pad_center(psf, (ny + ny % 2, nx + nx % 2))))
    ny, nx = ny + ny % 2, nx + nx % 2
    return fit_moffat(Ps, 2 * np.pi * np.fft.fftfreq(ny), 2 * np.pi * np.fft.rfftfreq(nx))


@functools.lru_cache(maxsize=64)
def _moffat_aliases(rs, beta, ny, nx, s):
    """The Moffat (times the pixel response) at every alias of the stamp's rfft modes.

    Returns the aliased sum ``A = sum_n G(k + 2 pi n)`` over n in [-2, 2]^2
    (beyond +-2 the Moffat is below 1e-8) and, for the s x s aliases the
    model keeps, G with their wavevectors and the sampled mode each folds
    onto. Cached: one exposure's CCD shares one Moffat (App. A fits one
    near the field centre), so its objects reuse these tables.
    """
    kyc = 2 * np.pi * np.fft.fftfreq(ny)
    kxc = 2 * np.pi * np.fft.rfftfreq(nx)
    # the Moffat's transform is radial: tabulate it once on |k| and interpolate; the pixel response is
    # separable
    na = 2
    offs = 2 * np.pi * np.arange(-na, na + 1)
    kmax = np.hypot(np.pi + offs[-1], np.pi + offs[-1]) + 1.0
    ktab = np.linspace(0.0, kmax, 4001)
    mtab = _moffat_ft(ktab, rs, beta)
    KYa = kyc[None, :] + offs[:, None]                     # (5, ny)
    KXa = kxc[None, :] + offs[:, None]                     # (5, nxh)
    sy = np.sinc(KYa / (2 * np.pi))
    sx = np.sinc(KXa / (2 * np.pi))
    kk = np.hypot(KYa[:, None, :, None], KXa[None, :, None, :])          # (5, 5, ny, nxh)
    G = np.interp(kk, ktab, mtab, right=0.0) * sy[:, None, :, None] * sx[None, :, None, :]
    A = G.sum(axis=(0, 1))
    half = s // 2
    sel = slice(na - half, na + half + 1)
    Gs = G[sel, sel]
    nxh = kxc.size
    KYf = np.broadcast_to(KYa[sel][:, None, :, None], Gs.shape).ravel()
    KXf = np.broadcast_to(KXa[sel][None, :, None, :], Gs.shape).ravel()
    coarse_index = (np.arange(ny)[:, None] * nxh + np.arange(nxh)[None, :])
    cs = np.broadcast_to(coarse_index, Gs.shape).ravel()
    for a in (A, Gs, KYf, KXf, cs):
        a.setflags(write=False)
    return A, Gs, KYf, KXf, cs


def _fine_modes_moffat(psf, ny, nx, s, moffat=None, tolerance=0.0):
    """Native PSF with the App. A alias correction, generalised (see fit_moffat).

    Above Nyquist the PSF is taken to be a circular Moffat times the pixel
    response, scaled mode by mode so that its aliased sum reproduces the
    sampled PSF's transform exactly inside the band: the model is
    ``sum_n (R G)(k + 2 pi n) * P_s(k) / sum_n G(k + 2 pi n)``. For a
    band-limited PSF this is the exact convolution; for a Moffat-like PSF it
    models the modes a native image cannot hold. ``moffat`` = (rs, beta)
    gives the Moffat (one per CCD, as the pipeline does); by default it is
    fitted to this PSF.
    """
    p = _pad_center(psf, (ny, nx))
    Ps = np.fft.rfft2(np.fft.ifftshift(p))
    if moffat is None:
        rs, beta = fit_moffat(Ps, 2 * np.pi * np.fft.fftfreq(ny), 2 * np.pi * np.fft.rfftfreq(nx))
    else:
        rs, beta = moffat
    A, Gs, KYf, KXf, cs = _moffat_aliases(float(rs), float(beta), ny, nx, int(s))
    ratio = np.where(np.abs(A) > 1e-12, Ps / np.where(np.abs(A) > 1e-12, A, 1.0), 0.0)
    # only the modes above ``tolerance`` of the largest |T| (G is real: |T| = |G| |ratio|)
    mag = (np.abs(Gs) * np.abs(ratio)[None, None]).ravel()
    idx = np.nonzero(mag > tolerance * mag.max())[0]
    return KYf[idx], KXf[idx], Gs.ravel()[idx] * ratio.ravel()[cs[idx]], cs[idx]


def noise_variance(weight):
    """Stationary noise variance of a stamp: 1 / median of the positive weights."""
    good = weight > 0
    if not np.any(good):
        raise ShearfitValueError("stamp has no pixel with positive weight")
    return 1.0 / float(np.median(weight[good]))


def _data_modes(obs, ny, nx):
    """The stamp's noise variance, rfft (masked, centred on the grid), sum y^2 / sigma^2 and used pixels."""
    sigma2 = noise_variance(obs.weight)
    y = np.where(obs.weight > 0, obs.image, 0.0)
    if y.shape != (ny, nx):
        y = _pad_center(y, (ny, nx))
    data_ft = np.fft.rfft2(np.fft.ifftshift(y)).ravel()
    return sigma2, data_ft, float(np.sum(y * y) / sigma2), int(np.count_nonzero(obs.weight > 0))


def prepare_exposure(obs: Observation, cfg: FitConfig, grid_shape=None, with_data=True, like=None) -> ExposureModes:
    """Reduce one observation to its Fourier modes.

    ``grid_shape`` (default: the stamp's) is the periodic grid the model
    lives on; rendering pads it to avoid wrap-around. ``like``: the
    ExposureModes of an observation with the same PSF, Moffat, Jacobian,
    offset, flux scale and shape (another version of the same stamp, as
    metacalibration's): its modes are reused and only the data transformed.
    """
    ny, nx = grid_shape if grid_shape is not None else obs.shape
    if like is not None:
        if like.shape != (ny, nx):
            raise ShearfitValueError(f"prepare_exposure: like= has shape {like.shape}, the stamp {(ny, nx)}")
        sigma2, data_ft, yy, npix = _data_modes(obs, ny, nx)
        return replace(like, data_ft=data_ft, sigma2=sigma2, yy=yy, npix=npix)
    s = obs.psf_oversampling
    if s == 1 and cfg.alias_correction == "moffat":
        # the modes below the tolerance are dropped as they are made
        ky, kx, T, coarse = _fine_modes_moffat(obs.psf, ny, nx, cfg.alias_oversampling, obs.psf_moffat,
                                               cfg.psf_mode_tolerance)
    else:
        ky, kx, T, coarse = _fine_modes_from_psf(obs.psf, s, ny, nx)
        aT = np.abs(T)
        keep = aT > cfg.psf_mode_tolerance * aT.max()
        ky, kx, T, coarse = ky[keep], kx[keep], T[keep], coarse[keep]
    # the object's nominal position sits at (stamp centre + offset)
    dx, dy = obs.offset
    T = T * np.exp(-1j * (kx * dx + ky * dy)) * obs.flux_scale
    # sky wavevector K = J^-T k
    Jinv_T = np.linalg.inv(obs.jacobian).T
    Kx = Jinv_T[0, 0] * kx + Jinv_T[0, 1] * ky
    Ky = Jinv_T[1, 0] * kx + Jinv_T[1, 1] * ky
    cweight = _rfft_weights(ny, nx).ravel()
    sigma2, data_ft, yy, npix = _data_modes(obs, ny, nx) if with_data else (1.0, None, 0.0, 0)
    return ExposureModes(shape=(ny, nx), kx=Kx, ky=Ky, transfer=T, coarse=coarse, cweight=cweight,
                         data_ft=data_ft, sigma2=sigma2, yy=yy, npix=npix, pixel_scale=obs.pixel_scale)


def model_ft(modes: ExposureModes, profile, e1, e2, r):
    """Model DFT on the rfft grid of ``modes.shape`` for unit flux of one component."""
    c11, c12, c22 = shape_matrix(e1, e2)
    rho2 = r * r * (c11 * modes.kx ** 2 + 2 * c12 * modes.kx * modes.ky + c22 * modes.ky ** 2)
    vals = modes.transfer * profile.ft_rho2(rho2)
    ny, nx = modes.shape
    M = np.zeros(ny * (nx // 2 + 1), dtype=complex)
    np.add.at(M, modes.coarse, vals)
    return M.reshape(ny, nx // 2 + 1)


def render_object(obs: Observation, e1, e2, scalelength, bulge_fraction, flux, config=None):
    """The PSF-convolved, pixelised model of a bulge+disk galaxy on ``obs``'s stamp.

    The model is computed on a grid padded so that the truncated profile and
    the PSF do not wrap around, then cut to the stamp. Returns counts: total
    ``flux * obs.flux_scale`` (before the cut).
    """
    from .profiles import de_vaucouleurs, exponential_disk

    from .measure import as_config

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

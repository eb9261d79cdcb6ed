"""Metacalibration on the lensfit likelihood: a shear response from the data themselves.

Huff & Mandelbaum (2017), Sheldon & Huff (2017). For each exposure of an
object, the stamp is taken as an interpolated image (GalSim's
``InterpolatedImage``: Lanczos-15 in x, quintic in k), that exposure's PSF
(which includes the pixel) is divided out, the result is sheared by +-delta
in each component in the sky frame (the stamp's WCS is the exposure's
Jacobian, so the shear acts on the catalogue's (u, v) axes), and convolved
with the PSF dilated by 1 + 2 delta, which is wider than the sheared
original in every direction. The same without the shear gives the
``noshear`` version. All five versions carry the same new PSF. With
``psf='round'`` (the pipeline's ``metacal_psf: round``) the new PSF is
instead the round envelope below the dilated PSF in every direction
(:func:`round_psf`): the response is multiplicative, so PSF anisotropy that
the estimator leaks into the ellipticities would pass through it; on round
versions there is none to leak.

These operations are shearfit's own (:func:`own_kspace_images`,
:mod:`shearfit.calib.kspace`): the transforms of the stamp, its noise and
the PSF are taken once per exposure and every version interpolates them at
its sheared wavevectors with one set of quintic weights (for a PSF given on
the stamp's pixels, the usual case, in one compiled loop for the version
without shear and one for the four sheared ones, point by point:
``quintic_band``; for an
oversampled PSF, whose transform is interpolated at its own pixels'
wavevectors and remembered per PSF image, in another, which for a PSF image k
times the stamp's size, whose padded grid is then k times the stamp's, reads
both transforms in rows at the same taps with the same weights, the four
sheared versions in one pass over them: ``quintic_band_rows``, the same images to rounding); the deconvolution
stops at the PSF's band (where its transform falls below 1e-3 of its flux,
and at most the PSF pixels' Nyquist disc). With other interpolants
(``K_INTERPOLANT``, ``PSF_K_INTERPOLANT``) or GalSim's own FFT grid
(``WRAP_STAMPS = 0``), GalSim's objects do them (``galsim.Deconvolve``,
``.shear``, ``.dilate``, :func:`_galsim_images`); set ``OWN_KSPACE = False``
for GalSim's objects always. Given the same band, the two give the same
noise-free images to 1e-6 of the peak for a native PSF and 2e-6 for one
oversampled 3 times (``tests/test_kspace.py``; with noise, where GalSim
leaves out some of the band's edge, 2e-5 and 5e-3) and the same noise-free
metacal m (``benchmarks/metacal_noise_free.py``); the own operations take a
fifth of the time (a third for an oversampled PSF).

The deconvolution and the shear correlate the noise anisotropically, which
would itself respond to the shear. The standard cure: a new noise field with
the stamp's variance, rotated by 90 degrees, is put through the same
operations, rotated back and added; the sum's noise correlation is then
symmetric under 90-degree rotation, so it carries no preferred ellipticity
(square stamps only: a non-square stamp is processed with a warning and its
noise left unsymmetrised).
The weight maps of the versions are the original ones scaled to the variance
of the processed noise; pixels near masked ones (whose contents were set to
zero before interpolation) and near the stamp's edge are masked.

The lensfit engine then measures each version jointly over the exposures.
The ``noshear`` fit makes its choices from its data as any fit does (the
Fourier modes kept, the position, the size nodes, the ellipticity samples);
the sheared versions replay them (:func:`shearfit.engine.measure.measure_versions`),
so that their estimates differ only through their pixels, and evaluate only
the samples within ``replay_margin`` nats of the posterior cut (those above the
noshear fit's cut first, then of the rest only those that the version's change of
the posterior, fitted over the first and smooth in e, could lift to within
``REPLAY_FIRST_MARGIN`` of its own cut: the same estimates). The four replays are
evaluated together, each ellipticity's mode bins placed once for all of them
(:class:`shearfit.engine.sampling.VersionLikelihoods`): each version's own
numbers, to rounding. The replays' R is the response at fixed choices; the noshear fit's choices move with
a true shear too, and at low SNR the response through them need not vanish: versions each fitted on their own
(``measure_metacal(..., replay=False)``, the pipeline's ``metacal_replay: false``) include it, at the price of
their choices' jumps (noise-free responses a true shear's to a few 1e-3 instead of 1e-4). On the outside-model
galaxies they raise m by +0.011 +- 0.007 at SNR 10-14 (5500 galaxies, of the replays' -0.028 there) and +0.0024 +-
0.0016 at 14-20 (``benchmarks/README.md``, sessions 44 and 48).
``R_ij = (e_i[j+] - e_i[j-]) / (2 delta)`` per galaxy, and an ensemble
shear is ``<R>^-1 <e>`` with the lensfit weights of the ``noshear`` fit.
Cuts and weights computed from measured quantities respond to the shear too
(selection response): :func:`ensemble_response` recomputes them from each
sheared version's own measurement and adds ``R_S``.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, field

import galsim
import numpy as np
from scipy import fft as sfft

from ..errors import FITCLASS_GALAXY, ShearfitIOError, ShearfitValueError
from ..engine.model import ContentMemo, inv2, psf_moffat, psf_moffats
from . import kspace
from ..observation import Observation

log = logging.getLogger(__name__)

__all__ = ["VERSIONS", "SHEARED", "metacal_observations", "measure_metacal", "MetacalResult",
           "ensemble_response", "catalogue_response", "metacal_shear"]

#: The versions and the shear (g1, g2) in units of delta that each applies.
VERSIONS = {"noshear": (0, 0), "1p": (1, 0), "1m": (-1, 0), "2p": (0, 1), "2m": (0, -1)}
SHEARED = ("1p", "1m", "2p", "2m")

#: The versions' new PSF (:func:`metacal_observations`' ``psf``): the exposure's PSF dilated by 1 + 2 delta, or
#: the round envelope below it (:func:`round_psf`).
RECONVOLUTION_PSFS = ("dilated", "round")
#: Pixels masked around a masked pixel and along the stamp's edge in the processed stamps.
_MASK_GROW = 2
_EDGE = 3
#: The versions' FFT grid in stamp widths (:class:`_Drawer`): a third of a stamp width between the stamp
#: and its periodic copies (0: the grid GalSim's drawImage would choose).
WRAP_STAMPS = 4 / 3
#: GalSim's k-interpolants of the interpolated stamp (and its noise) and of the PSF. Its default quintic for
#: both: the cubic's interpolation errors are anisotropic enough to bias the response to shears along the
#: pixel diagonals (m2 = +2.6e-3 with a cubic stamp, about 2e-4 with a cubic PSF alone, on noise-free galaxies:
#: ``benchmarks/metacal_noise_free.py --variants``).
K_INTERPOLANT = "quintic"
PSF_K_INTERPOLANT = "quintic"
#: The x-interpolant of the interpolated stamps and PSFs.
_LANCZOS = galsim.Lanczos(15)
#: The versions made by shearfit's own k-space operations (:func:`own_kspace_images`; False: by GalSim's objects,
#: :func:`_galsim_images`).
OWN_KSPACE = True
#: The symmetrising noise turned by 90 degrees before the operations and back after them, so that its correlation
#: is the processed noise's sheared the other way (False: processed as it is, so that the versions' whole noise
#: is sheared with the galaxy; for benchmarks that measure what the turn does, ``ring_test.py
#: --metacal-unsymmetrised``: at SNR 10-14 the fits' <R> falls from 0.71 to 0.19, benchmarks/README.md, session 51).
SYMMETRISE_NOISE = True


def _wcs(J, k=1):
    J = np.asarray(J, float) / k
    return galsim.JacobianWCS(J[0, 0], J[0, 1], J[1, 0], J[1, 1])


def _interpolated(array, wcs, calculate_maxk=False, k_interpolant="quintic", maxk=None):
    # use_true_center=False: the profile's origin is pixel (ny // 2, nx // 2), the convention of the stamps.
    # The PSF's own maxk (calculate_maxk, or ``maxk`` given: the own operations' band) bounds the k-space grids of
    # every convolution with it: about 13 times faster than the interpolant's maxk, and the same images to 1e-4 of
    # the peak.
    return galsim.InterpolatedImage(galsim.Image(np.ascontiguousarray(array, dtype=np.float64), wcs=wcs),
                                    x_interpolant="lanczos15", k_interpolant=k_interpolant, use_true_center=False,
                                    calculate_stepk=False, calculate_maxk=calculate_maxk and maxk is None,
                                    _force_maxk=0.0 if maxk is None else float(maxk))


_PIXEL = galsim.PixelScale(1.0)


@functools.lru_cache(maxsize=16)
def _dilation_matrix(n, dilation):
    """L[i, p] = X((i - c) / d - (p - c)) / d, X the Lanczos-15 interpolant (GalSim's), c = n // 2: the
    interpolated image of n pixels along one axis, dilated by d about pixel c, at its pixel centres."""
    c = n // 2
    u = ((np.arange(n) - c) / dilation)[:, None] - (np.arange(n) - c)[None, :]
    m = _LANCZOS.xval(u.ravel()).reshape(u.shape) / dilation
    m.setflags(write=False)
    return m


@functools.lru_cache(maxsize=16)
def _dilation_band(n, dilation):
    """:func:`_dilation_matrix` as a banded matrix (``KERNEL.banded_rows``' values and start): each row's values from
    its first non-zero one, as many as the widest row holds (the Lanczos kernel's support, 30 of an oversampled PSF
    image's 144), so that every value left out is zero (read-only)."""
    m = _dilation_matrix(n, dilation)
    nz = m != 0
    first = np.where(nz.any(axis=1), nz.argmax(axis=1), 0)
    last = np.where(nz.any(axis=1), n - 1 - nz[:, ::-1].argmax(axis=1), 0)
    w = int(max(1, (last - first).max() + 1))
    start = np.minimum(first, n - w).astype(np.int64)
    values = np.ascontiguousarray(m[np.arange(n)[:, None], start[:, None] + np.arange(w)[None, :]])
    for a in (start, values):
        a.setflags(write=False)
    return values, start


def dilated_image(image, dilation):
    """The image as an interpolated image (Lanczos-15) dilated by ``dilation`` about its pixel
    (ny // 2, nx // 2), at its pixel centres: what GalSim's ``drawImage(method='no_pixel')`` of
    ``InterpolatedImage(image).dilate(dilation)`` draws on the same pixels, as two matrix products (the
    interpolant is separable). For an image four times as wide as the band of the matrices or more (a PSF image
    oversampled 3 times, 144 pixels wide), compiled, each product over its matrix's band alone (``banded_rows``:
    the same numbers to rounding, the dense products' order of summation aside, in half their time; on narrower
    images the dense products are the faster)."""
    ny, nx = image.shape
    vy, sy = _dilation_band(ny, float(dilation))
    vx, sx = _dilation_band(nx, float(dilation))
    if not (kspace.USE_KERNEL and image.dtype == np.float64 and min(ny, nx) >= 4 * max(vy.shape[1], vx.shape[1])):
        return _dilation_matrix(ny, float(dilation)) @ image @ _dilation_matrix(nx, float(dilation)).T
    rows = np.empty((ny, nx))
    kspace.KERNEL.banded_rows(vy, sy, np.ascontiguousarray(image), rows)   # L_y image
    out = np.empty((nx, ny))
    kspace.KERNEL.banded_rows(vx, sx, np.ascontiguousarray(rows.T), out)   # L_x (L_y image)^T
    return np.ascontiguousarray(out.T)


#: the versions' new PSF images (the exposures' PSFs dilated), remembered by the PSF image's contents: the objects
#: of a CCD given one PSF image share it
_DILATED = ContentMemo(16 * 2 ** 20, max_entries=64)
#: PSF images up to this many pixels a side are dilated afresh, not looked up: their two matrix products (6 us at 25
#: pixels) cost less than the memory's lookup and entry (some 25 us an exposure where each object has a PSF image of
#: its own, as a PSF model fitted from the stars gives, session 98)
DILATE_DIRECT_MAX = 40


def _dilated_psf(psf, dilation):
    """:func:`dilated_image` of a PSF image, normalised to unit sum (read-only; remembered, :data:`_DILATED`, for
    images wider than :data:`DILATE_DIRECT_MAX`)."""
    def make():
        img = dilated_image(psf, dilation)
        img /= img.sum()
        img.setflags(write=False)
        return img
    if max(psf.shape) <= DILATE_DIRECT_MAX:
        return make()
    return _DILATED.get(psf, float(dilation), make)


def _draw(prof, shape, wcs):
    ny, nx = shape
    return prof.drawImage(nx=nx, ny=ny, wcs=wcs, method="no_pixel", use_true_center=False).array


class _Drawer:
    """The pixels of one stamp's k-space products, drawn as GalSim's ``drawImage`` draws a convolution.

    ``draw(products, bands)`` takes a list of products (each a list of GSObjects in the sky frame, the
    factors of a ``galsim.Convolution``) and the band of each (the world wavenumber beyond which the
    product is zero: the sheared deconvolution's maxk), and returns their images on the stamp's pixel
    grid, the profiles' origin at pixel (ny // 2, nx // 2) (``use_true_center=False``), as
    ``galsim.Convolution(product).drawImage(nx=nx, ny=ny, wcs=wcs, method="no_pixel",
    use_true_center=False)`` would on GalSim's own FFT grid (``fft_size=0``; the default grid is smaller,
    see below), with three shortcuts that leave the images the same to rounding:

    - GalSim's own pieces of that draw (``profileToImage``, ``drawFFT_makeKImage``, each factor's
      ``_drawKImage`` with the image-frame Jacobian) are called once per stamp where they are the same
      for every product, not once per image.
    - Band limit: the factors are evaluated only on the smallest part of the k grid that holds the band
      (a disc of radius ``band``, seen through the Jacobian); the rest of the grid is zero. GalSim
      evaluates every factor on the whole grid, out to the pixels' Nyquist frequency.
    - Shared factors (the same object in several products, such as the sheared inverse PSF and the new
      PSF of a version and of its noise) are evaluated once per k grid; the inverse transforms of all
      the products are batched (``scipy.fft``) and evaluated only at the stamp's rows and columns.

    A band that reaches the grid's Nyquist row or column is folded onto the grid by GalSim's
    ``Image.wrap`` (Hermitian in x), as ``drawFFT`` folds its k image before the transform.

    ``fft_size``: the largest FFT grid used (pixels; default :data:`WRAP_STAMPS` stamp widths, rounded up
    to a fast size: 64 for a 48-pixel stamp). GalSim sizes its grid from the product's stepk, which for an
    interpolated 48-pixel stamp is 128 pixels; the images are periodic on the grid, and for a galaxy inside
    the stamp a third of a stamp width between the stamp and its periodic copies is enough: a noise-free
    galaxy's versions are GalSim's own to 5e-5 of their peak away from the masked edge, and the metacal
    response of noise-free galaxies matches their true shear response as closely as on GalSim's grid
    (``benchmarks/metacal_noise_free.py``: |m| <= 1e-4 on either grid, for the paper's population and
    for one unlike it), with a quarter of the k values. The deconvolution's hard band edge gives the
    kernel a long ringing reach (a few per cent of its power lies beyond 16 pixels), so a noisy stamp's
    processed noise does depend on the grid, by a few per cent of its amplitude; on either grid it is the
    stamp's noise through one linear operator that is periodic on a square grid, so the 90-degree
    symmetrisation holds as before and the weights follow the processed noise's variance
    (``tests/test_metacal.py``).
    ``fft_size=0`` keeps GalSim's own grid, and the images are then those of GalSim's ``drawImage``.
    """

    def __init__(self, shape, wcs, fft_size=None):
        self.shape = tuple(shape)
        self.wcs = wcs
        ny, nx = self.shape
        if fft_size is None:
            fft_size = sfft.next_fast_len(int(np.ceil(WRAP_STAMPS * max(ny, nx)))) if WRAP_STAMPS else 0
        self.fft_size = int(fft_size)
        # drawImage's image, shifted so that its integer centre (the profile's origin) is (0, 0)
        self.bounds = galsim.BoundsI(-(nx // 2), nx - 1 - nx // 2, -(ny // 2), ny - 1 - ny // 2)
        frame = wcs.profileToImage(galsim.Gaussian(sigma=1.0))
        if frame.offset.x != 0 or frame.offset.y != 0:
            raise ValueError("metacal: a stamp WCS with an origin offset")
        self.jac = np.asarray(frame.jac, float)
        # the k-space values' scaling of GalSim's Transformation: surface brightness per pixel
        self.flux_scaling = abs(float(np.linalg.det(self.jac))) * float(frame.flux_ratio)
        # image k pixel (i, j) is the world wavenumber dk * jac^T (i, j): at least dk sigma_min |(i, j)| long
        self.sigma_min = float(np.linalg.svd(self.jac, compute_uv=False)[-1])
        self._grids = {}

    def _grid(self, product):
        """The FFT size for this product (GalSim's drawFFT's, from its stepk and maxk, or ``fft_size`` where
        that is smaller), the k image's size before folding, and dk; asked of GalSim once per distinct
        (stepk, maxk)."""
        conv = galsim.Convolution(product)
        key = (conv.stepk, conv.maxk)   # the sky frame's: the image frame's follow from them through the WCS
        if key not in self._grids:
            prof = self.wcs.profileToImage(conv)
            kimage, n = prof.drawFFT_makeKImage(galsim.Image(self.bounds, scale=1.0))
            nk, dk = kimage.bounds.xmax * 2, kimage.scale
            if 0 < self.fft_size < n:
                # a smaller periodic grid (see the class doc): dk = 2 pi / n on the image's unit pixels,
                # the k image as wide as GalSim's (its maxk), folded onto the grid where it reaches beyond
                dk_small = 2.0 * np.pi / self.fft_size
                n, nk, dk = self.fft_size, max(self.fft_size, 2 * int(np.ceil(nk * dk / (2.0 * dk_small)))), dk_small
            self._grids[key] = (n, nk, dk)
        return self._grids[key]

    def draw(self, products, bands):
        out = [None] * len(products)
        batches = {}
        cache = {}
        for i, (product, band) in enumerate(zip(products, bands)):
            n, nk, dk = self._grid(product)
            r = min(int(np.ceil(band / (dk * self.sigma_min))) + 1, nk // 2)
            sub = galsim.BoundsI(0, r, -r, r)
            grid = (r, dk)
            arr = None
            for obj in product:
                key = (id(obj),) + grid
                hit = cache.get(key)
                # the cache holds the object too: an id is unique only while its object lives
                if hit is None or hit[0] is not obj:
                    part = galsim.Image(sub, dtype=np.complex128, scale=dk)
                    obj._drawKImage(part, self.jac)
                    hit = cache[key] = (obj, part.array)
                arr = hit[1] if arr is None else arr * hit[1]   # a new array: the cached factors stay
            if abs(self.flux_scaling - 1.0) > galsim.GSParams().kvalue_accuracy:
                arr = arr * self.flux_scaling
            batches.setdefault(n, []).append((i, r, arr))
        for n, items in batches.items():
            for (i, _, _), im in zip(items, band_images(self.shape, n, [(r, arr) for _, r, arr in items])):
                out[i] = im
        return out


def fold_band(arr, n):
    """Bands (``arr``: (bands, 2 r + 1, r + 1), the values F(i, j) at i = 0 .. r, rows j = -r .. r, Hermitian
    in x) folded onto the n x n grid's rfft layout ((bands, n, n // 2 + 1): rows ky, columns kx), periodic in
    n: each value lands at (i mod n, j mod n) where that column is stored, and for i > 0 its mirror conj
    F(i, j) = F(-i, -j) at ((-i) mod n, (-j) mod n) where that one is. For even n this is GalSim's
    ``Image.wrap(..., hermitian='x')`` onto rows -n/2 .. n/2 - 1 (``tests/test_kspace.py``)."""
    nb, rows2, r1 = arr.shape
    r, half = r1 - 1, n // 2
    out = np.zeros((nb, n, half + 1), complex)
    if r < n:
        # rows j = 0 .. r, then j = -r .. -1 at n - r .. n - 1; columns i <= n / 2 where they are, and the
        # mirrors of i = n - n // 2 .. r (the others are not stored) at n - i, rows -j, conjugated
        rows = np.zeros((nb, n, r1), complex)
        rows[:, :r + 1] = arr[:, r:]
        rows[:, n - r:] += arr[:, :r]
        m = min(r, half) + 1
        out[:, :, :m] = rows[:, :, :m]
        lo = max(n - half, 1)
        if lo <= r:
            sub = rows[:, :, lo:]
            mirror = np.concatenate([sub[:, :1], sub[:, :0:-1]], axis=1).conj()   # rows -j mod n
            out[:, :, n - r:n - lo + 1] += mirror[:, :, ::-1]
        return out
    rows = np.zeros((nb, n, r1), complex)
    j = np.arange(-r, r + 1) % n
    for s in range(0, rows2, n):   # n consecutive rows land on distinct rows
        rows[:, j[s:s + n]] += arr[:, s:s + n]
    i = np.arange(r1)
    mirror = rows[:, (-np.arange(n)) % n].conj()
    for s in range(0, r1, n):      # n consecutive columns land on distinct columns
        cols = i[s:s + n]
        x = cols % n
        keep = x <= half
        out[:, :, x[keep]] += rows[:, :, cols[keep]]
        xm = (-cols) % n
        keep = (xm <= half) & (cols > 0)
        out[:, :, xm[keep]] += mirror[:, :, cols[keep]]
    return out


def band_images(shape, n, items):
    """The images on a stamp of ``shape`` of k images given on bands: ``items`` is a list of (r, arr), arr the
    transform (an image's, as GalSim's drawFFT makes its k image: surface brightness per pixel, origin at
    pixel (ny // 2, nx // 2)) at the wavevectors 2 pi (i, j) / n of the pixel frame, i = 0 .. r, j = -r .. r
    (rows j), zero beyond; the images are periodic on the n x n grid. A band that reaches the grid's Nyquist
    row or column is folded onto the grid as GalSim's ``Image.wrap`` (Hermitian in x) folds it (:func:`fold_band`),
    as ``drawFFT`` folds its k image before the transform."""
    ny, nx = shape
    half = n // 2
    cols = min(max(r for r, _ in items), half) + 1
    spec = np.zeros((len(items), n, cols), np.complex128)
    wide = {}
    edge = []
    for b, (r, arr) in enumerate(items):
        if r < half:
            # rows j = 0 .. r, then -r .. -1 at the grid's end
            spec[b, :r + 1, :r + 1] = arr[r:]
            if r:
                spec[b, n - r:, :r + 1] = arr[:r]
        elif r == half and n % 2 == 0:
            # the band reaching the Nyquist row and column exactly (the usual wide case, its radius capped at
            # the new PSF's band): fold_band's folding done in place, rows j = -r + 1 .. r where they are, row
            # -r added onto row r, and the Nyquist column's mirrors conj F(r, -j) added onto it
            spec[b, :r + 1] = arr[r:]
            spec[b, n - r + 1:] = arr[1:r]
            spec[b, half, :] += arr[0]
            edge.append(b)
        else:
            wide.setdefault(r, []).append(b)
    if edge:
        col = spec[edge, :, half]
        spec[edge, :, half] = col + np.conj(col[:, (-np.arange(n)) % n])
    for bands in wide.values():
        spec[bands] = fold_band(np.stack([items[b][1] for b in bands]), n)
    # f(x) = (1 / 4 pi^2) sum_k F(k) exp(i k.x) dk^2 with dk = 2 pi / n, irfft2's own normalisation,
    # evaluated only at the stamp's rows and columns: the transform over ky of the band's columns,
    # the stamp's rows of it, then the real transform over kx
    # (the stamp's rows y = -ny // 2 .. ny - 1 - ny // 2 and columns likewise, taken as two slices each: the images
    # returned are read-only views of a read-only stack, so that an Observation keeps them without a copy)
    lo_y, lo_x = ny // 2, nx // 2
    col = sfft.ifft(spec, axis=1, workers=1, overwrite_x=True)
    wraps = ny > n or nx > n   # a stamp wider than the period: its rows and columns wrap
    rows = np.zeros((len(items), ny, half + 1), np.complex128)
    if wraps:
        rows[:, :, :cols] = col[:, (np.arange(ny) - lo_y) % n, :]
    else:
        rows[:, :lo_y, :cols] = col[:, n - lo_y:, :]
        rows[:, lo_y:, :cols] = col[:, :ny - lo_y, :]
    full = sfft.irfft(rows, n=n, axis=2, workers=1, overwrite_x=True)
    if wraps:
        return list(full[:, :, (np.arange(nx) - lo_x) % n])
    # (one read-only stack of the images, each image a view of it: immutable, :func:`shearfit.observation.is_immutable`)
    out = np.empty((len(items), ny, nx))
    out[:, :, :lo_x] = full[:, :, n - lo_x:]
    out[:, :, lo_x:] = full[:, :, :nx - lo_x]
    out.setflags(write=False)
    return list(out)


def _galsim_images(image, noise, psf_image, wcs, psf_wcs, delta, names, new_psf_image=None):
    """The images of :func:`metacal_observations`' products, [version, its noise] per name of ``names``, from
    GalSim's objects (interpolated images, ``Deconvolve``, ``shear``, ``dilate``) drawn by :class:`_Drawer`:
    the reference for :func:`own_kspace_images`, and the path for oversampled PSFs. ``new_psf_image``: the new
    PSF's image on the PSF's pixels (:func:`round_psf`'s), as an interpolated image, instead of the dilated
    PSF."""
    gal = _interpolated(image, wcs, k_interpolant=K_INTERPOLANT)
    nint = _interpolated(noise, wcs, k_interpolant=K_INTERPOLANT)
    # the PSF's band: the own operations' (:func:`shearfit.calib.kspace.band_edge`, on their padded grid: the
    # stamp's and the PSF's for a native PSF, the PSF's own for an oversampled one), its maxk
    n = kspace.padded_size(image.shape, psf_image.shape) if psf_wcs == wcs else kspace.padded_size(psf_image.shape)
    maxk = kspace.band_maxk(kspace.padded_transforms([psf_image], n)[0], _LANCZOS.kval,
                            psf_wcs.jacobian().getMatrix())
    psf = _interpolated(psf_image, psf_wcs, k_interpolant=PSF_K_INTERPOLANT, maxk=maxk)
    inv_psf = galsim.Deconvolve(psf)
    new_psf = (psf.dilate(1.0 + 2.0 * abs(delta)) if new_psf_image is None else
               _interpolated(new_psf_image, psf_wcs, calculate_maxk=True, k_interpolant=PSF_K_INTERPOLANT))
    products, bands = [], []
    for name in names:
        s1, s2 = VERSIONS[name]
        g1, g2 = s1 * delta, s2 * delta
        # the shear of (stamp / PSF) is the product of the sheared factors (a shear keeps areas)
        gal_g, noise_g, inv = [(p.shear(g1=g1, g2=g2) if (g1 or g2) else p) for p in (gal, nint, inv_psf)]
        # the same operations on the rotated noise; rotated back, its correlation is the processed
        # noise's turned by 90 degrees (as if sheared by -g), so the sum's is symmetric
        products += [[gal_g, inv, new_psf], [noise_g, inv, new_psf]]
        bands += [inv.maxk, inv.maxk]
    return _Drawer(image.shape, wcs).draw(products, bands)


@functools.lru_cache(maxsize=64)
def _shear_matrix(g1, g2):
    """GalSim's matrix of the shear (g1, g2), which acts on sky positions (read-only, shared)."""
    m = galsim.Shear(g1=g1, g2=g2).getMatrix()
    m.setflags(write=False)
    return m


def turned_band(arr, n, size):
    """The band of an image turned back by 90 degrees (``np.rot90(image, -1)`` of a square stamp of ``size``
    pixels, origin at pixel (size // 2, size // 2)), from the band ``arr`` ((2 r + 1, r + 1): rows j = -r .. r,
    columns i = 0 .. r, Hermitian in x, as :func:`band_images` takes it) of the image on the n x n periodic grid:
    the turned image is g(c - x, y) with c = size - 1 - 2 (size // 2) (-1 for an even stamp: the array turns about
    the pixel corner, not about the origin pixel), whose transform is exp(-i c kx) G(-kx, ky); the band's square
    is its own image under the turn, so the turned band is exact and folds as the original does."""
    r = arr.shape[1] - 1
    out = np.empty_like(arr)
    out[r:] = arr[r::-1].T                      # j >= 0: G(-i, j)
    out[:r] = np.conj(arr[r:, r:0:-1]).T        # j < 0: G(-i, j) = conj G(i, -j)
    c = size - 1 - 2 * (size // 2)
    if c:
        out *= np.exp(-1j * c * (2 * np.pi / n) * np.arange(r + 1))[None, :]
    return out


#: an oversampled PSF image's padded transform and what is made from it alone (its band for a Jacobian, the new
#: PSF's transform at a band's points), remembered by the image's contents: the objects of a CCD given one PSF image
#: make its transform once
_PSF_TABLES = ContentMemo(64 * 2 ** 20, max_entries=64)


@functools.lru_cache(maxsize=16)
def _shear_stack(names, delta):
    """:func:`_shear_matrix` of each version of ``names`` (on sky positions, unit determinant): (versions, 2, 2),
    read-only, shared."""
    out = np.stack([_shear_matrix(VERSIONS[v][0] * delta, VERSIONS[v][1] * delta) for v in names])
    out.setflags(write=False)
    return out


def _version_matrices(names, delta, jit, maxk, dk, dilation, smax_j):
    """Per version of ``names``: A = S J^-T, which takes a band's point kappa to the deconvolved profile's sky
    wavevector S^T K (S symmetric), and the band's half-width r in grid steps: the band's disc seen in the pixel frame
    (maxk over A's smaller singular value), and no wider than the new PSF's band (beyond it the product is below the
    threshold). The versions at once, each the same numbers as ``S @ jit`` and
    :func:`shearfit.calib.kspace.singular_values2`'s arithmetic on its own. Returns (A per version, r per version)."""
    A = _shear_stack(tuple(names), float(delta)) @ jit
    a, b, c, d = A[:, 0, 0], A[:, 0, 1], A[:, 1, 0], A[:, 1, 1]
    p = a * a + b * b + c * c + d * d
    q = np.hypot(a * a + b * b - c * c - d * d, 2 * (a * c + b * d))
    smin = np.sqrt(np.maximum(0.5 * (p - q), 0.0))
    cap = int(np.ceil(maxk / dilation * smax_j / dk))
    r = [min(int(x) + 1, cap) for x in np.ceil(maxk / (smin * dk))]
    return list(A), r


def _psf_table(psf, n, columns):
    """(table, memo): the padded transform of a PSF image (one plane, read-only) made at its first ``columns`` columns
    at least (:func:`shearfit.calib.kspace.padded_transform_within`: every column beyond, proven below the band's
    threshold, left unmade; memo["columns"] of them made), and a dict for what is made from it alone, remembered by
    its contents (:data:`_PSF_TABLES`). :func:`_psf_columns` makes the table whole, in place, where a read needs
    more."""
    def make():
        t, m = kspace.padded_transform_within(psf, n, columns, _LANCZOS.kval)
        t.setflags(write=False)
        return t, {"table": t, "columns": m}
    return _PSF_TABLES.get(psf, ("table", n), make)


def _psf_columns(psf, n, memo, need):
    """:func:`_psf_table`'s table with at least its first ``need`` columns made: made whole in place where it lacks
    them (:func:`shearfit.calib.kspace.padded_transform_rest`: the columns made before untouched)."""
    if memo["columns"] < need:
        t = memo["table"]
        t.setflags(write=True)
        kspace.padded_transform_rest(psf, t, memo["columns"])
        t.setflags(write=False)
        memo["columns"] = t.shape[1]
    return memo["table"]


def _add_band(items, first, r, arr, n_small, size, turn_noise):
    """A version's bands (``arr``: the stamp's and its noise's) into ``items`` for :func:`band_images`: the two, or
    with ``turn_noise`` their sum with the noise turned back (:func:`turned_band`); returns the first version's
    turned noise (``first``, or this one's if it is None)."""
    if not turn_noise:
        items += [(r, arr[0]), (r, arr[1])]
        return first
    back = turned_band(arr[1], n_small, size)
    items.append((r, arr[0] + back))
    return (r, back) if first is None else first


def _add_compiled_band(items, first, r, arr, turn_noise):
    """:func:`_add_band` for a compiled loop's bands (``arr``: the stamp's and the noise's, or with ``turn_noise``
    their sum and the noise turned back, already made)."""
    if not turn_noise:
        items += [(r, arr[0]), (r, arr[1])]
        return first
    items.append((r, arr[0]))
    return (r, arr[2]) if first is None else first


def _psf_rows(ptab, memo, n_s):
    """The PSF's padded table (``ptab``, its grid n_p = k n_s) at the stamp's grid's wavevectors within half the
    stamp's period, in rows as :func:`shearfit.calib.kspace.padded_transforms_rows` gives the stamp's ((n_s, n_s / 2 +
    1): ky = 0 .. n_s / 2 - 1, -n_s / 2 .. -1, then kx = 0 .. n_s / 2; read-only, remembered in the PSF's ``memo``):
    the compiled band (``quintic_band_rows``) reads the stamp and the PSF at the same taps with the same weights."""
    key = ("rows", n_s)
    got = memo.get(key)
    if got is None:
        h, n_p = n_s // 2, ptab.shape[2]
        got = np.ascontiguousarray(np.concatenate([ptab[0, :h + 1, :h], ptab[0, :h + 1, n_p - h:]], axis=1).T)
        got.setflags(write=False)
        memo[key] = got
    return got


def _oversampled_kspace_images(image, noise, psf, J, k, delta, names, n_small, new_psf, turn_noise):
    """:func:`own_kspace_images` for a PSF image oversampled k times (its pixels J / k): the stamp's and its noise's
    transforms as interpolated images on the stamp's pixels, the PSF's (and the new PSF's) on its own, each the
    padded table's quintic interpolation times the x-interpolant's transform at the wavevector in its own pixels
    (kappa for the stamp, kappa / k for the PSF), which no longer cancel. In numpy, with the compiled
    interpolation; the PSF's table, band and new PSF's transform remembered per PSF image (:func:`_psf_table`)."""
    shape = image.shape
    n_s = kspace.padded_size(shape)
    n_p = kspace.padded_size(psf.shape)
    to_s, to_p = n_s / (2 * np.pi), n_p / (2 * np.pi)
    # the PSF's table made at the columns the bands read where the band lies within the stamp's Nyquist square (its
    # wavevectors up to pi / k in the PSF's pixels, a tenth more for the shears and dilation, and the taps): a third
    # of the columns at k = 3 (the band's reads are checked below, and the table made whole where they need more)
    made = int(1.1 * np.pi / k * to_p) + 4
    ptab, memo = _psf_table(psf, n_p, made)
    # a PSF grid k times the stamp's (a PSF image k times the stamp's size): the compiled band reads both at the same
    # taps, from the tables' rows (quintic_band_rows)
    psf_rows = _psf_rows(ptab, memo, n_s) if kspace.USE_KERNEL and n_p == k * n_s else None
    table = (kspace.padded_transforms_rows([image, noise], n_s) if psf_rows is not None
             else kspace.padded_transforms([image, noise], n_s))
    gtab, gmemo = (ptab, memo) if new_psf is None else _psf_table(new_psf, n_p, made)
    J = np.asarray(J, float)
    jit = inv2(J).T
    xk = _LANCZOS.kval
    # the PSF's band for this Jacobian, from its edge in the image's own frame, found once per PSF image (the
    # columns made: those beyond lie below the threshold, the same edge)
    edge = memo.get("edge")
    if edge is None:
        edge = memo["edge"] = kspace.band_edge(ptab[0, :memo["columns"]], xk)
    maxk = kspace.maxk_of_edge(edge, J / k)
    dk = 2 * np.pi / n_small
    dilation = 1.0 + 2.0 * abs(delta)
    smax_j = kspace.singular_values2(J)[0]
    scale = (1.0 if new_psf is not None else dilation) / k   # kappa -> the new PSF's wavevector in its pixels
    mats, radii = _version_matrices(names, delta, jit, maxk, dk, dilation, smax_j)
    # the columns read: the bands' taps at the sheared wavevectors q / k (in the PSF's pixels) within the band, |q| at
    # most smax_j maxk; the new PSF's at the band's points kappa scale, kx up to r dk (the taps reach 3 beyond)
    need = int(smax_j * maxk / k * to_p * (1 + 1e-9)) + 4
    gneed = int(max(radii) * dk * scale * to_p * (1 + 1e-9)) + 4
    if new_psf is None:   # (one table for both)
        ptab = gtab = _psf_columns(psf, n_p, memo, max(need, gneed))
    else:
        ptab, gtab = _psf_columns(psf, n_p, memo, need), _psf_columns(new_psf, n_p, gmemo, gneed)
    items = []
    first = None
    if kspace.USE_KERNEL:   # (the same for every version)
        jt = np.ascontiguousarray(J.T)
        xtab, xh = _x_table(int(np.ceil(maxk * smax_j / np.pi)) + 1)
    lim = maxk * maxk * (1 + 1e-12)
    plans = []
    for name, A, r in zip(names, mats, radii):
        s1, s2 = VERSIONS[name]
        gkey = ("gamma", r, dk, scale, to_p)
        got = gmemo.get(gkey)
        if got is None:
            kap = _band_kappa(r, dk)
            d = kap * scale
            gamma = kspace.kvalues(gtab, d[0] * to_p, d[1] * to_p)[:, 0] * xk(d[0]) * xk(d[1])
            gamma.setflags(write=False)
            got = gmemo[gkey] = (kap, gamma)
        plans.append((name, s1, s2, A, r) + got)
    if kspace.USE_KERNEL:
        # the lines of the numpy branch below in one compiled loop over the band, the x-interpolant's transform from
        # a table (within 3e-10 of GalSim's, :func:`_x_table`)
        nb = 3 if turn_noise else 2
        bands, together = {}, {}
        for name, s1, s2, A, r, kap, gamma in plans:
            # the version without shear, whose wavevectors are the tables' own where the stamp's grid is a multiple
            # of the band's, reads them there; the others of one band radius go together: one loop over the band
            # reads the tables for all of them, each point's versions at neighbouring taps (the tables are larger
            # than a core's L2 cache: version after version, each fetched them again, a third of the loop's time
            # where they had left the cache, a few per cent where the transforms just made them)
            step = n_s // n_small if (s1 == s2 == 0 and n_s % n_small == 0 and (n_s // n_small) * r < n_s // 2) else 0
            if psf_rows is not None and not step:
                together.setdefault(r, (kap, gamma, []))[2].append((name, A))
                continue
            arr = np.empty((nb, kap.shape[1]), complex)
            phase = _turn_phase(r, n_small, shape[0]) if turn_noise else _NO_PHASE
            if psf_rows is not None:
                kspace.KERNEL.quintic_band_rows(table, n_s, psf_rows, ptab, n_p, k, r, dk, A, jt, lim, gamma, xtab,
                                                xh, step, phase, arr)
            else:
                kspace.KERNEL.quintic_band_os(table, n_s, ptab, n_p, k, r, dk, A, jt, lim, gamma, xtab, xh, phase,
                                              arr)
            bands[name] = arr
        for r, (kap, gamma, group) in together.items():
            arr = np.empty((len(group), nb, kap.shape[1]), complex)
            phase = _turn_phase(r, n_small, shape[0]) if turn_noise else _NO_PHASE
            kspace.KERNEL.quintic_band_rows(table, n_s, psf_rows, ptab, n_p, k, r, dk,
                                            np.ascontiguousarray([A for _, A in group]), jt, lim, gamma, xtab, xh, 0,
                                            phase, arr)
            bands.update((name, a) for (name, _), a in zip(group, arr))
        for name, _, _, _, r, _, _ in plans:
            first = _add_compiled_band(items, first, r, bands[name].reshape(-1, 2 * r + 1, r + 1), turn_noise)
    for name, s1, s2, A, r, kap, gamma in (() if kspace.USE_KERNEL else plans):
        sky = A @ kap
        inside = np.nonzero(np.sum(sky * sky, axis=0) <= lim)[0]
        q = J.T @ sky[:, inside]   # the sheared wavevectors in the stamp's pixels
        m = inside.size
        x = xk(np.concatenate([q.ravel(), q.ravel() / k]))   # X at the stamp's q and at the PSF's q / k
        v = kspace.kvalues(table, q[0] * to_s, q[1] * to_s)
        p = kspace.kvalues(ptab, q[0] * (to_p / k), q[1] * (to_p / k))[:, 0]
        f = gamma[inside] * ((x[:m] * x[m:2 * m]) / (p * (x[2 * m:3 * m] * x[3 * m:])))
        arr = np.zeros((2, kap.shape[1]), complex)
        arr[:, inside] = v.T * f
        arr = arr.reshape(2, 2 * r + 1, r + 1)
        first = _add_band(items, first, r, arr, n_small, shape[0], turn_noise)
    return band_images(shape, n_small, items + ([first] if turn_noise else []))


def own_kspace_images(image, noise, psf, J, delta, names, fft_size=None, new_psf=None, turn_noise=False, k=1):
    """The images of :func:`metacal_observations`' products, [version, its noise] per name of ``names``, from
    shearfit's own k-space operations (:mod:`shearfit.calib.kspace`) instead of GalSim's objects, for a PSF
    image on the stamp's pixels (``k`` = 1; one oversampled k times: :func:`_oversampled_kspace_images`): the
    stamp's, its noise's and the PSF's discrete transforms once, each
    version's sheared wavevectors interpolated with one set of quintic weights for the three; drawn on the
    same periodic grid of :data:`WRAP_STAMPS` stamp widths (``fft_size``) as :class:`_Drawer`. ``new_psf``: the
    new PSF's image on the stamp's pixels (:func:`round_psf`'s) instead of the dilated PSF: its transform as an
    interpolated image, as :func:`_galsim_images` takes it. ``turn_noise`` (a square stamp whose ``noise`` was
    turned by ``np.rot90(noise, 1)``): instead, per name the version plus its noise turned back
    (``np.rot90(..., -1)``), then the first name's noise turned back, the turns made on the bands
    (:func:`turned_band`), so that one inverse transform serves each sum."""
    shape = image.shape
    n_small = int(fft_size) if fft_size else sfft.next_fast_len(int(np.ceil(WRAP_STAMPS * max(shape))))
    if turn_noise and shape[0] != shape[1]:
        raise ValueError("own_kspace_images: turn_noise needs a square stamp")
    if k != 1:
        return _oversampled_kspace_images(image, noise, psf, J, int(k), delta, names, n_small, new_psf, turn_noise)
    n = kspace.padded_size(shape, psf.shape)
    table = kspace.padded_transforms([image, noise, psf] + ([] if new_psf is None else [new_psf]), n)
    psf_table = table[2:3] if new_psf is None else table[3:4]
    table = table[:3]
    J = np.asarray(J, float)
    jit = inv2(J).T
    smax_j = kspace.singular_values2(J)[0]
    maxk = kspace.band_maxk(table[2], _LANCZOS.kval, J, smax=smax_j)
    dk = 2 * np.pi / n_small
    dilation = 1.0 + 2.0 * abs(delta)
    to_table = n / (2 * np.pi)
    grids = {}
    items = []
    first = None
    # the band's edge: maxk may be the norm of one of the padded grid's wavevectors (a ring's radius over the
    # Jacobian's singular value), which for the noshear version may be one of these too, so it is inside however
    # rounding computes the two norms
    lim = maxk * maxk * (1 + 1e-12)
    plans = []
    for name, A, r in zip(names, *_version_matrices(names, delta, jit, maxk, dk, dilation, smax_j)):
        if r not in grids:
            kap, tx, ty, x0, x1 = _band_points(r, dk, None if new_psf is not None else dilation, to_table)
            grids[r] = (kap, kspace.kvalues(psf_table, tx, ty)[:, 0] * x0 * x1)
        plans.append((name, A, r) + grids[r])
    if kspace.USE_KERNEL:
        # the lines of the numpy branch below in one compiled loop over the band (the same values to rounding); the
        # version without shear, whose wavevectors are the padded table's own where its grid is a multiple of the
        # stamp's, reads them there; the others of one band radius go together, point by point, so that the table
        # (larger than a core's L2 cache) is read once for all of them instead of once each
        nb = 3 if turn_noise else 2
        jt = np.ascontiguousarray(J.T)
        bands, together = {}, {}
        for name, A, r, kap, gamma in plans:
            s1, s2 = VERSIONS[name]
            step = n // n_small if (s1 == s2 == 0 and n % n_small == 0 and (n // n_small) * r <= n // 2) else 0
            if not step:
                together.setdefault(r, (gamma, []))[1].append((name, A))
                continue
            arr = np.empty((nb, kap.shape[1]), complex)
            phase = _turn_phase(r, n_small, shape[0]) if turn_noise else _NO_PHASE
            kspace.KERNEL.quintic_band(table, n, r, dk, np.ascontiguousarray(A), jt, to_table, lim, gamma, step, phase,
                                       arr)
            bands[name] = arr
        for r, (gamma, group) in together.items():
            arr = np.empty((len(group), nb, gamma.size), complex)
            phase = _turn_phase(r, n_small, shape[0]) if turn_noise else _NO_PHASE
            kspace.KERNEL.quintic_band(table, n, r, dk, np.ascontiguousarray([A for _, A in group]), jt, to_table, lim,
                                       gamma, 0, phase, arr)
            bands.update((name, a) for (name, _), a in zip(group, arr))
        for name, _, r, _, _ in plans:
            first = _add_compiled_band(items, first, r, bands[name].reshape(-1, 2 * r + 1, r + 1), turn_noise)
    for name, A, r, kap, gamma in (() if kspace.USE_KERNEL else plans):
        arr = np.zeros((2, kap.shape[1]), complex)
        sky = A @ kap
        inside = np.nonzero(np.sum(sky * sky, axis=0) <= lim)[0]
        kp = (J.T @ sky[:, inside]) * to_table   # the sheared wavevectors in the pixel frame: M kappa, M = J^T S J^-T
        v = kspace.kvalues(table, kp[0], kp[1])
        arr[:, inside] = v[:, :2].T * (gamma[inside] / v[:, 2])
        arr = arr.reshape(2, 2 * r + 1, r + 1)
        first = _add_band(items, first, r, arr, n_small, shape[0], turn_noise)
    return band_images(shape, n_small, items + ([first] if turn_noise else []))


_NO_PHASE = np.zeros(1, complex)

#: the step of :func:`_x_table` (its Catmull-Rom interpolation: within 3e-10 of the transform, whose third
#: derivative stays below 110)
_X_STEP = 5e-4


@functools.lru_cache(maxsize=8)
def _x_table(periods):
    """The x-interpolant's transform at 0, h, 2 h, ... up to ``periods`` pi (beyond it the compiled band takes
    it as 0; read-only): what ``quintic_band_os`` interpolates at the stamp's and the PSF's wavevectors."""
    u = _X_STEP * np.arange(int(np.ceil(periods * np.pi / _X_STEP)) + 3)
    out = np.ascontiguousarray(_LANCZOS.kval(u), dtype=float)
    out.setflags(write=False)
    return out, _X_STEP


@functools.lru_cache(maxsize=32)
def _turn_phase(r, n, size):
    """:func:`turned_band`'s phase exp(-i c kx) at the columns i = 0 .. r (read-only, shared)."""
    c = size - 1 - 2 * (size // 2)
    out = np.exp(-1j * c * (2 * np.pi / n) * np.arange(r + 1)) if c else np.ones(r + 1, complex)
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=32)
def _band_kappa(r, dk):
    """A band's points kappa = dk (i, j), rows j = -r .. r, columns i = 0 .. r: (2, points) (read-only, shared)."""
    j, i = np.mgrid[-r:r + 1, 0:r + 1]
    kap = dk * np.stack([i.ravel(), j.ravel()]).astype(float)
    kap.setflags(write=False)
    return kap


@functools.lru_cache(maxsize=32)
def _band_points(r, dk, dilation, to_table):
    """A band's points kappa = dk (i, j) (rows j = -r .. r, columns i = 0 .. r; (2, points)), the new PSF's
    points d = dilation kappa (kappa where ``dilation`` is None) in the padded table's units (d * to_table), and
    the x-interpolant's transform at d's two components (read-only, shared by the exposures of one stamp size)."""
    kap = _band_kappa(r, dk)
    d = kap if dilation is None else dilation * kap
    xk = _LANCZOS.kval
    out = (kap, d[0] * to_table, d[1] * to_table, xk(d[0]), xk(d[1]))
    for a in out:
        a.setflags(write=False)
    return out


def round_psf(psf, J, delta, shape, fft_size=None):
    """The round new PSF of ``psf='round'``: the image, on the pixels of the PSF image ``psf`` (whose Jacobian is
    ``J``: the stamp's divided by the oversampling) and normalised to unit sum, of the round envelope below the
    PSF dilated by 1 + 2 delta in every direction (:func:`shearfit.calib.kspace.round_envelope`, a function of
    the sky's \\|K\\| alone), drawn from it on a periodic grid of :data:`WRAP_STAMPS` times ``shape`` (the stamp's,
    or the oversampled PSF's own) as :func:`own_kspace_images` draws the stamps. The versions are then
    convolved with this image as an interpolated image (its transform is round to the PSF image's sampling and
    size: GalSim's adaptive moments give \\|e\\| < 1e-3, ``tests/test_kspace.py``), so that the fits' PSF is
    exactly the versions'."""
    n_small = int(fft_size) if fft_size else sfft.next_fast_len(int(np.ceil(WRAP_STAMPS * max(shape))))
    n = kspace.padded_size(psf.shape)
    column = kspace.padded_transforms([psf], n)[0]
    J = np.asarray(J, float)
    xk = _LANCZOS.kval
    maxk = kspace.band_maxk(column, xk, J)
    knots, values = kspace.round_envelope(column, xk, J, 1.0 + 2.0 * abs(delta), maxk)
    dk = 2 * np.pi / n_small
    r = int(np.ceil(knots[-1] * kspace.singular_values2(J)[0] / dk)) + 1
    kap = _band_kappa(r, dk)
    # linear in |K|^2 between the knots: smooth at K = 0, as a PSF's transform is (1 - c K^2)
    k2 = np.sum((inv2(J).T @ kap) ** 2, axis=0)
    arr = np.interp(k2, knots ** 2, values, right=0.0).astype(complex)
    image = band_images(psf.shape, n_small, [(r, arr.reshape(2 * r + 1, r + 1))])[0]
    return image / image.sum()


def _grown(mask, steps):
    """``ndimage.binary_dilation(mask, iterations=steps)`` (its cross of four neighbours, nothing beyond the edge)
    as shifted ORs: the same pixels, without scipy's setup, which cost four times the work on a stamp."""
    for _ in range(steps):
        out = mask.copy()
        out[1:] |= mask[:-1]
        out[:-1] |= mask[1:]
        out[:, 1:] |= mask[:, :-1]
        out[:, :-1] |= mask[:, 1:]
        mask = out
    return mask


def _mean_square(x):
    """``float(np.mean(x ** 2))`` of a 1D array made for it (squared in place: the same numbers)."""
    np.multiply(x, x, out=x)
    return float(x.mean())


@functools.lru_cache(maxsize=16)
def _edge_mask(shape):
    """The pixels within ``_EDGE`` of a stamp's edge (read-only, shared): a stamp's mask without masked pixels."""
    mask = np.zeros(shape, bool)
    mask[:_EDGE, :] = mask[-_EDGE:, :] = True
    mask[:, :_EDGE] = mask[:, -_EDGE:] = True
    mask.setflags(write=False)
    return mask


def _noise_numpy(w, image, noise):
    """The stamp's pixels with weight > 0 (0 elsewhere), the symmetrising noise (unit normals, scaled in place) times
    sigma = 1 / sqrt(w) there (0 elsewhere), the mask (the pixels of weight 0 grown by ``_MASK_GROW``, and those within
    ``_EDGE`` of the edge) and var_in, the mean of sigma^2 off the mask (1 where all is masked): (image, mask,
    var_in). The reference of :func:`_noise_compiled`."""
    good = w > 0
    # (a stamp without a masked pixel, the usual one, needs none of the masked pixels' handling below: the same
    # arrays with fewer operations)
    whole = bool(good.all())
    image = image if whole else np.where(good, image, 0.0)
    sigma = np.sqrt(w)
    if whole:
        np.divide(1.0, sigma, out=sigma)
    else:
        np.divide(1.0, sigma, out=sigma, where=good)
        sigma[~good] = 0.0
    noise *= sigma
    mask = _edge_mask(w.shape) if whole else _grown(~good, _MASK_GROW) | _edge_mask(w.shape)
    inner = ~mask
    return image, mask, (_mean_square(sigma[inner]) if inner.any() else 1.0)


def _noise_compiled(w, image, noise):
    """:func:`_noise_numpy` in one compiled pass (``metacal_noise``: the same numbers; ``noise`` C-contiguous)."""
    out, mask = np.empty(w.shape), np.empty(w.shape, np.uint8)
    var_in = kspace.KERNEL.metacal_noise(np.ascontiguousarray(w), np.ascontiguousarray(image), noise, w.shape[0],
                                         w.shape[1], _EDGE, _MASK_GROW, out, mask)
    return out, mask.view(bool), var_in


def _weight_numpy(noise0, mask, w, var_in):
    """The versions' weights: ``w`` times var_in / (2 var_out), var_out the mean of the processed noise's square
    (``noise0``, the noshear version's) off the mask (var_in where all is masked), 0 on the mask. The reference of
    :func:`_weight_compiled`."""
    inner = ~mask
    var_out = _mean_square(noise0[inner]) if inner.any() else var_in
    weight = w * (var_in / max(2.0 * var_out, 1e-300))
    weight[mask] = 0.0
    return weight


def _weight_compiled(noise0, mask, w, var_in):
    """:func:`_weight_numpy` in one compiled pass (``metacal_weight``: the same numbers)."""
    weight = np.empty(w.shape)
    kspace.KERNEL.metacal_weight(np.ascontiguousarray(noise0), np.ascontiguousarray(mask), np.ascontiguousarray(w),
                                 float(var_in), weight)
    return weight


def metacal_observations(obs: Observation, delta=0.01, rng=None, versions=tuple(VERSIONS),
                         fit_moffat=True, psf="dilated") -> dict:
    """The metacal versions of one exposure's stamp: ``{version: Observation}`` (see the module doc).

    ``rng`` (numpy Generator) draws the symmetrising noise field. ``fit_moffat=False``: where the
    observation gives no App. A Moffat, the versions carry none either (:func:`measure_metacal` fits those
    of all the exposures as one batch, the same numbers). ``psf``: the versions' new PSF, 'dilated' (the
    exposure's PSF dilated by 1 + 2 delta) or 'round' (:func:`round_psf`: the round envelope below it, whose
    images carry no PSF anisotropy into the ellipticities).
    """
    if psf not in RECONVOLUTION_PSFS:
        raise ShearfitValueError(f"metacal: psf={psf!r} must be one of {', '.join(RECONVOLUTION_PSFS)}")
    rng = np.random.default_rng() if rng is None else rng
    J = obs.jacobian
    k = obs.psf_oversampling
    w = obs.weight
    dilation = 1.0 + 2.0 * abs(delta)
    own = OWN_KSPACE and WRAP_STAMPS and K_INTERPOLANT == PSF_K_INTERPOLANT == "quintic"
    if psf == "round":
        # on the PSF's pixels (J / k), drawn on the stamp's periodic grid (the oversampled PSF's own for k > 1:
        # the same width on the sky)
        psf_img = round_psf(obs.psf, J / k, delta, obs.image.shape if k == 1 else obs.psf.shape)
    else:
        # its image: a dilation commutes with the Jacobian, so it is drawn in the PSF's own pixel frame, where the
        # interpolation is separable (GalSim's drawImage of the dilated interpolated PSF to 1e-7 of the peak)
        psf_img = _dilated_psf(obs.psf, dilation)
    # the App. A Moffat of the new PSF: the exposure's own, dilated the same way (so objects sharing an
    # exposure's Moffat share its alias tables); fitted to the new PSF only when none was given (and always to
    # the round PSF)
    if k != 1:
        moffat = None
    elif psf == "round":
        moffat = psf_moffat(psf_img) if fit_moffat else None
    elif obs.psf_moffat is not None:
        moffat = (float(obs.psf_moffat[0]) * dilation, float(obs.psf_moffat[1]))
    else:
        moffat = psf_moffat(psf_img) if fit_moffat else None
    # the symmetrising noise: the stamp's variance, rotated by 90 degrees before the operations (none at the
    # masked pixels)
    noise = rng.normal(0.0, 1.0, w.shape)
    compiled = kspace.USE_KERNEL and w.dtype == obs.image.dtype == np.float64
    image, mask, var_in = (_noise_compiled if compiled else _noise_numpy)(w, obs.image, noise)
    square = w.shape[0] == w.shape[1]
    if not square:
        # a 90-degree rotation of a non-square stamp is another shape: the added noise is then not rotated,
        # and its correlation doubles the processed noise's instead of symmetrising it
        log.warning("metacal: a %d x %d stamp is not square; its noise is not symmetrised", *w.shape)
    turn = square and SYMMETRISE_NOISE
    nrot = noise[:, ::-1].T if turn else noise   # np.rot90(noise, 1)
    names = ("noshear",) + tuple(v for v in versions if v != "noshear")
    new_psf = psf_img if psf == "round" else None
    if own and turn:
        # each version's sum and the noshear noise, the noise turned back on its band (the same images to rounding)
        images = own_kspace_images(image, nrot, obs.psf, J, delta, names, new_psf=new_psf, turn_noise=True, k=k)
        sums, noise0 = images[:-1], images[-1]
    else:
        if own:
            images = own_kspace_images(image, nrot, obs.psf, J, delta, names, new_psf=new_psf, k=k)
        else:
            images = _galsim_images(image, nrot, obs.psf, _wcs(J), _wcs(J, k), delta, names, new_psf_image=new_psf)
        images = np.asarray(images)
        nims = np.rot90(images[1::2], -1, axes=(1, 2)) if turn else images[1::2]
        sums, noise0 = images[0::2] + nims, nims[0]
    # the versions' noise: the original, processed, plus the added field: twice the added field's variance,
    # measured on the noshear version and used for all, so that every version is fitted with the same weights
    # (and the same Fourier modes)
    # (GalSim's drawImage path gives float32 images, whose variance numpy takes in float32)
    weight = (_weight_compiled if compiled and noise0.dtype == np.float64 else _weight_numpy)(noise0, mask, w, var_in)
    weight.setflags(write=False)
    out = {}
    first = None
    for v, name in enumerate(names):
        if name in versions:
            if first is None:
                first = out[name] = obs.derived(sums[v], weight, psf_img, moffat)
            else:   # the versions share the first one's weight, PSF and geometry
                out[name] = first.with_image(sums[v])
    return out


@dataclass
class MetacalResult:
    """The fits of every version of one object, and its shear response."""

    results: dict = field(default_factory=dict)     # version -> FitResult
    R: np.ndarray = field(default_factory=lambda: np.full((2, 2), np.nan))
    delta: float = 0.01

    @property
    def noshear(self):
        return self.results.get("noshear")


#: Finest ellipticity step of the metacal fits. R compares estimates 2 delta apart, so the estimate must
#: follow the data smoothly: the paper's 0.02 leaves likelihoods narrower than the step (bright
#: galaxies) sampled by a handful of points, whose mean jumps by up to a step. The adaptive grid only
#: goes below 0.02 where fewer than 30 samples lie above 5 % of the peak, so broad likelihoods cost
#: nothing more.
E_GRID_MIN = 0.005
#: The sheared versions' replays evaluate the samples above the noshear fit's posterior cut first, then of those
#: within ``replay_margin`` only the ones whose log posterior, predicted from the version's change of it over the
#: first samples, lies within this many nats (plus the prediction's error) of the version's cut
#: (:func:`shearfit.engine.sampling.replay_samples`): the same estimates as the whole margin's, to rounding, with
#: 61 % of its samples on the small field's galaxies (0.5: 64 %, 1.0: 70 %; session 88's rule at 1.0: 72 %).
REPLAY_FIRST_MARGIN = 0.25


def _fit_new_moffats(per_exp):
    """The App. A Moffats of the versions' new PSFs where none was given (native PSFs), as
    :func:`metacal_observations` fits them one by one, but as one batch (``psf_moffats``: the same numbers)."""
    need = [v for v in per_exp if v["noshear"].psf_oversampling == 1 and v["noshear"].psf_moffat is None]
    for v, fit in zip(need, psf_moffats([v["noshear"].psf for v in need])):
        for o in v.values():
            o.psf_moffat = fit


def measure_metacal(observations, mag, config=None, delta=0.01, rng=None, replay_margin=10.0,
                    replay_first_margin=REPLAY_FIRST_MARGIN, psf="dilated", replay=True,
                    own_position=False, own_samples=False, own_sizes=False) -> MetacalResult:
    """Measure the five metacal versions of one object jointly over its exposures (see the module doc); ``psf``:
    the versions' new PSF, 'dilated' or 'round' (:func:`metacal_observations`). ``replay=False``: every version
    is fitted on its own, with its own choices (modes, position, sizes, samples), as the ``noshear`` fit is: R
    then also holds the estimator's response through its choices, at the price of their jumps' noise and of 1.6-1.8
    times the metacal fits' time (``benchmarks/README.md``, session 44). ``own_position``: the sheared
    versions replay every choice but the position, which each finds for itself from the noshear fit's
    (:func:`shearfit.engine.measure.measure_versions`), so that R holds the estimate's response through its
    position (measured on paired runs in ``benchmarks/README.md``, session 45). ``own_samples``: each sheared
    version runs the adaptive ellipticity grid on its own likelihood, the noshear fit's samples evaluated for
    all four together (:func:`shearfit.engine.sampling.adaptive_versions`), so that R holds the estimate's
    response through its grid (session 46). ``own_sizes``: each sheared version places its own size nodes and
    centres from its own round model's size posterior, so that R holds the estimate's response through the size
    integral's quadrature (session 52)."""
    from dataclasses import replace

    from ..config import as_config
    from ..engine.measure import measure_object, measure_versions, paused_gc

    rng = np.random.default_rng() if rng is None else rng
    config = as_config(config)
    if config.e_grid_min > E_GRID_MIN:
        config = replace(config, e_grid_min=E_GRID_MIN)
    # Python's cyclic garbage collector paused for the object's images and fits (a few per cent of them)
    with paused_gc():
        per_exp = [metacal_observations(o, delta, rng, fit_moffat=False, psf=psf) for o in observations]
        _fit_new_moffats(per_exp)
        # the sheared versions replay the noshear fit's choices (modes, position, size nodes, ellipticity
        # samples): their estimates then differ only through their pixels (measure_versions)
        if replay:
            results = measure_versions([[v[name] for v in per_exp] for name in VERSIONS], mag, config,
                                       margin=replay_margin, first_margin=replay_first_margin,
                                       own_position=own_position, own_samples=own_samples, own_sizes=own_sizes)
        else:
            results = [measure_object([v[name] for v in per_exp], mag, config) for name in VERSIONS]
    out = MetacalResult(delta=float(delta))
    out.results = dict(zip(VERSIONS, results))
    R = np.full((2, 2), np.nan)
    for j, (p, m) in enumerate((("1p", "1m"), ("2p", "2m"))):
        rp, rm = out.results[p], out.results[m]
        R[0, j] = (rp.e1 - rm.e1) / (2 * delta)
        R[1, j] = (rp.e2 - rm.e2) / (2 * delta)
    out.R = R
    return out


def _col(tab, name):
    return np.asarray(tab[name], float)


def _selected(tab, suffix, select):
    """Weights of the galaxies a version selects: its own fitclass, weight and optional cuts."""
    sfx = f"_{suffix}" if suffix else ""
    w = np.where(np.asarray(tab[f"fitclass{sfx}"]) == FITCLASS_GALAXY, _col(tab, f"weight{sfx}"), 0.0)
    w = np.where(np.isfinite(w), w, 0.0)
    if select is not None:
        w = w * np.asarray(select(tab, sfx), bool)
    return w


def ensemble_response(tab, select=None, delta=None):
    """Mean shear response of a metacal catalogue: (R_total, R_gamma, R_S), each 2x2.

    ``R_gamma`` is the weighted mean of the per-galaxy R (the noshear fit's
    lensfit weights and selection). ``R_S`` is the selection response: the
    noshear ellipticities averaged with the weights and selection recomputed
    from each sheared version (``fitclass``, ``weight`` and ``select``, a
    function ``select(table, suffix) -> bool array`` that reads columns
    ``name + suffix``, e.g. ``snr_1p``), differenced over +-delta.
    """
    delta = float(tab.meta.get("MCDELTA", 0.01)) if delta is None else float(delta)
    w0 = _selected(tab, "", select)
    R = np.array([[_col(tab, "R11"), _col(tab, "R12")], [_col(tab, "R21"), _col(tab, "R22")]])
    ok = (w0 > 0) & np.all(np.isfinite(R.reshape(4, -1)), axis=0)
    R_gamma = np.einsum("n,ijn->ij", w0[ok], R[..., ok]) / w0[ok].sum()
    e = np.stack([_col(tab, "e1"), _col(tab, "e2")])
    e = np.where(np.isfinite(e), e, 0.0)
    R_S = np.zeros((2, 2))
    for j, (p, m) in enumerate((("1p", "1m"), ("2p", "2m"))):
        wp, wm = _selected(tab, p, select), _selected(tab, m, select)
        R_S[:, j] = (e @ wp / wp.sum() - e @ wm / wm.sum()) / (2 * delta)
    return R_gamma + R_S, R_gamma, R_S


def catalogue_response(tab, source):
    """:func:`ensemble_response` of a metacal catalogue read from ``source``: R, with a missing column
    named as a one-line error."""
    try:
        R, _, _ = ensemble_response(tab)
    except KeyError as exc:
        raise ShearfitIOError(f"{source}: metacal catalogue has no column {exc.args[0]!r}") from None
    return R


def metacal_shear(tab, select=None, delta=None):
    """The ensemble shear <R>^-1 <e> of a metacal catalogue (noshear weights and selection)."""
    R, _, _ = ensemble_response(tab, select, delta)
    w0 = _selected(tab, "", select)
    e = np.stack([_col(tab, "e1"), _col(tab, "e2")])
    e = np.where(np.isfinite(e), e, 0.0)
    return np.linalg.solve(R, e @ w0 / w0.sum())

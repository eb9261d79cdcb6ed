"""PSF models given with a field instead of fitted (docs/interface.rst, ``psf:``).

Two forms are read:

* a FITS image per CCD (:func:`read_psf_fits`): the PSF including the pixel
  response, summing to one, centred on array index ``(ny // 2, nx // 2)``,
  sampled every ``1/k`` image pixel where ``k`` is the header's ``OVERSAMP``
  (default 1); floats or scaled integers (``BSCALE``/``BZERO``), plain or
  tile-compressed (``.fits.fz``: :func:`psf_image_hdus` finds the HDUs);
* a PSFEx ``.psf`` file (:class:`PSFExModel`): a pixel basis whose every
  pixel is a polynomial in the position on the CCD.

Both give arrays in the convention the engine's :class:`~shearfit.Observation`
takes: pixel response included, sum 1, centre at ``(ny // 2, nx // 2)``, and
an integer oversampling factor.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import NamedTuple

import numpy as np
from astropy.io import fits

from ..errors import ShearfitIOError, ShearfitKeyError, ShearfitValueError

__all__ = ["PSFImage", "read_psf_fits", "psf_image_hdus", "PSFExModel", "is_psfex_file", "resample_matrix", "INTERPOLANTS"]


class PSFImage(NamedTuple):
    """A PSF image in the contract's convention and its oversampling."""

    image: np.ndarray
    """2D float64 array, sums to 1, centred on ``(ny // 2, nx // 2)``."""
    oversampling: int
    """PSF array pixels per image pixel (k: one sample every 1/k pixel)."""


def _one_line(exc):
    return " ".join(str(exc).split())


def _open_fits(path, what):
    """Open a FITS file, turning every failure into a one-line ShearfitIOError."""
    path = Path(path)
    if not path.exists():
        raise ShearfitIOError(f"{what} file '{path}' does not exist")
    if path.is_dir():
        raise ShearfitIOError(f"{what} file '{path}' is a directory")
    try:
        hdul = fits.open(path, memmap=False)
        # fits.open is lazy: read every header now so a truncated or non-FITS
        # file fails here, with the file's name, and not at first use.
        hdul.readall()
    except (OSError, ValueError, TypeError) as exc:
        raise ShearfitIOError(f"cannot read {what} file '{path}': not a valid FITS file ({_one_line(exc)})") from exc
    if len(hdul) == 0:
        hdul.close()
        raise ShearfitIOError(f"cannot read {what} file '{path}': no HDUs")
    return hdul


def _hdu_list_text(hdul):
    return ", ".join(f"{i} {h.name or '(no name)'}" for i, h in enumerate(hdul))


def _select_hdu(hdul, path, hdu, what):
    try:
        if isinstance(hdu, (int, np.integer)) and not isinstance(hdu, bool):
            if hdu < 0:
                raise IndexError(hdu)
            return hdul[int(hdu)]
        return hdul[hdu]
    except (KeyError, IndexError, TypeError):
        raise ShearfitKeyError(
            f"{what} file '{path}' has no HDU {hdu!r} (it has: {_hdu_list_text(hdul)})") from None


def psf_image_hdus(path):
    """Indices of the PSF image HDUs of a given-PSF FITS file: every HDU holding a 2D image, in file order.

    An empty primary HDU (as in a multi-extension or a tile-compressed file)
    and table HDUs are not PSF images. Only headers are read.

    Raises
    ------
    ShearfitIOError
        The file is missing or is not FITS.
    """
    with _open_fits(path, "PSF") as hdul:
        return [i for i, h in enumerate(hdul)
                if getattr(h, "is_image", False) and h.header.get("NAXIS", 0) == 2
                and all(h.header.get(f"NAXIS{j}", 0) > 0 for j in (1, 2))]


def read_psf_fits(path, hdu=0):
    """Read one PSF image from a FITS file, validate it and normalise it to sum 1.

    The pixels may be floats or scaled integers (``BSCALE``/``BZERO``, scaled
    to float here), in a plain or a tile-compressed (``CompImageHDU``) HDU.

    Parameters
    ----------
    path : str or Path
        The FITS file.
    hdu : int or str
        HDU index (0-based) or name (``EXTNAME``).

    Returns
    -------
    PSFImage
        ``(image, oversampling)``: the image as float64 divided by its sum and
        ``k`` from the header keyword ``OVERSAMP`` (1 when absent).

    Raises
    ------
    ShearfitIOError
        The file is missing or is not FITS.
    ShearfitKeyError
        The HDU does not exist.
    ShearfitValueError
        The HDU is not a 2D image, holds non-finite values, does not have a
        positive sum, or ``OVERSAMP`` is not a positive integer.

    Notes
    -----
    The centring convention (PSF centre on ``(ny // 2, nx // 2)``) cannot be
    checked without knowing the PSF, so it is taken on trust: an off-centre
    PSF shifts every model on that CCD and shows up as centroid offsets.
    """
    with _open_fits(path, "PSF") as hdul:
        h = _select_hdu(hdul, path, hdu, "PSF")
        where = f"PSF file '{path}' HDU {hdu!r}"
        if not isinstance(h, (fits.PrimaryHDU, fits.ImageHDU, fits.CompImageHDU)):
            raise ShearfitValueError(f"{where} is a {type(h).__name__}, not an image")
        data = h.data
        header = h.header
        if data is None:
            raise ShearfitValueError(f"{where} holds no data")
        img = np.array(data, dtype=np.float64)
    if img.ndim != 2:
        raise ShearfitValueError(f"{where} must be a 2D image, got shape {img.shape}")
    if not np.all(np.isfinite(img)):
        raise ShearfitValueError(f"{where} has {int(np.sum(~np.isfinite(img)))} non-finite pixels")
    total = float(img.sum())
    if not total > 0:
        raise ShearfitValueError(f"{where} must have a positive sum to be normalised, got {total:.6g}")
    k_raw = header.get("OVERSAMP", 1)
    try:
        k = int(round(float(k_raw)))
        ok = k >= 1 and abs(float(k_raw) - k) < 1e-6
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ShearfitValueError(f"{where}: OVERSAMP must be a positive integer, got {k_raw!r}")
    img /= total
    img.setflags(write=False)
    return PSFImage(img, k)


def is_psfex_file(path):
    """True if ``path`` is a FITS file with a PSFEx ``PSF_DATA`` table, False otherwise."""
    try:
        with fits.open(path, memmap=False) as hdul:
            return any(h.name == "PSF_DATA" and isinstance(h, fits.BinTableHDU) for h in hdul)
    except (OSError, ValueError, TypeError):
        return False


def _lanczos3(t):
    # sinc(t) sinc(t/3) on |t| < 3: the kernel PSFEx uses to move its model
    # between the PSF and image grids (INTERPFAC = 3 in its vignet code), and
    # the x_interpolant of galsim.des.DES_PSFEx.
    t = np.asarray(t, dtype=np.float64)
    return np.where(np.abs(t) < 3.0, np.sinc(t) * np.sinc(t / 3.0), 0.0)


INTERPOLANTS = ("sinc", "lanczos3")


def resample_matrix(n_in, step_in, n_out, step_out, interpolant="sinc"):
    """Matrix W (n_out, n_in) taking samples on one centred grid to another.

    Input sample i sits at ``(i - n_in // 2) * step_in`` and output sample j
    at ``(j - n_out // 2) * step_out`` (same units): both grids are centred on
    index ``n // 2``, the convention of the contract and of PSFEx. Outside the input
    array the function is zero (PSFEx's model is zero there). A 2D image
    ``A`` resamples as ``W_y @ A @ W_x.T``.

    Parameters
    ----------
    n_in, step_in : int, float
        Number and spacing of the input samples.
    n_out, step_out : int, float
        Number and spacing of the output samples.
    interpolant : {"sinc", "lanczos3"}
        ``"sinc"``: Whittaker-Shannon interpolation, exact for a function
        band-limited below the input Nyquist frequency and vanishing beyond
        the array (what a PSF tabulated at or above its Nyquist rate is).
        ``"lanczos3"``: the windowed sinc PSFEx and GalSim use; each row is
        divided by the kernel's full sum at its phase so that a constant
        resamples to the same constant (plain Lanczos-3 has a DC gain that
        ripples by ~1e-3 with the sub-sample phase, which would print a grid
        pattern on the PSF). Lanczos-3 also attenuates frequencies well below
        Nyquist, so it broadens a PSF slightly, by an amount that depends on
        the sub-sample phase: up to ~2e-3 of the peak in 1D (~4e-3 in 2D)
        for a Gaussian with sigma = 2.5 samples.

    Returns
    -------
    W : ndarray, shape (n_out, n_in)
    """
    if interpolant not in INTERPOLANTS:
        raise ShearfitValueError(f"unknown PSF interpolant {interpolant!r}; valid: {', '.join(INTERPOLANTS)}")
    s_in = (np.arange(n_in) - n_in // 2) * float(step_in)
    t_out = (np.arange(n_out) - n_out // 2) * float(step_out)
    arg = (t_out[:, None] - s_in[None, :]) / float(step_in)
    if interpolant == "sinc":
        # No row normalisation here: the infinite sinc sum is exactly 1, and
        # dividing by the truncated one would add a phase-dependent error of
        # ~1/(pi n) where the PSF is actually zero.
        return np.sinc(arg)
    W = _lanczos3(arg)
    # The DC normalisation uses the full (untruncated) kernel sum, so rows
    # near the array edge are not inflated by the missing input samples.
    frac = t_out / float(step_in)
    taps = np.floor(frac)[:, None] + np.arange(-2, 4)[None, :]
    dc = _lanczos3(frac[:, None] - taps).sum(axis=1)
    return W / dc[:, None]


def _context_axis(name):
    """'x' or 'y' for a PSFEx context parameter naming an image coordinate, else None."""
    # SExtractor image coordinates: X_IMAGE, XWIN_IMAGE, XPSF_IMAGE, XMODEL_IMAGE, ...
    m = re.fullmatch(r"([XY])[A-Z]*_IMAGE", str(name).strip().upper())
    return m.group(1).lower() if m else None


class PSFExModel:
    """A PSFEx ``.psf`` model: a pixel basis whose pixels are polynomials in CCD position.

    The file holds, in its ``PSF_DATA`` table, one cell ``PSF_MASK`` of shape
    ``(n_terms, ny, nx)``. The PSF at image position (X, Y) (PSFEx's 1-based
    ``X_IMAGE``, ``Y_IMAGE``) is

    .. math::

        P(X, Y) = \\sum_{j=0}^{d} \\sum_{i=0}^{d-j} M_{t(i,j)}\\, \\xi^i \\eta^j, \\qquad
        \\xi = \\frac{X - X_0}{s_X},\\ \\eta = \\frac{Y - Y_0}{s_Y},

    with ``X_0, Y_0 = POLZERO1, POLZERO2``, ``s_X, s_Y = POLSCAL1, POLSCAL2``,
    ``d = POLDEG1`` and terms stored with the power of x running fastest:
    ``t(i, j) = j (d + 1) - j (j - 1) / 2 + i``, i.e. 1, x, ..., x^d, y,
    xy, ..., x^(d-1) y, ..., y^d (PSFEx's ``poly_func`` ordering). Only the
    single-group, two-parameter (image X, image Y) form is supported, plus
    the constant model (``POLNAXIS = 0``).

    Each PSFEx sample is ``PSF_SAMP`` image pixels wide, and the vignette's
    centre is sample ``(ny // 2, nx // 2)`` (PSFEx places it at ``size / 2``
    in integer arithmetic: index 12 of 25), which is the contract's
    convention. PSFEx builds its model from the stars as observed, so the
    pixel response is included.

    Parameters
    ----------
    path : str or Path
        The ``.psf`` file.
    interpolant : {"sinc", "lanczos3"}
        How :meth:`image_at` resamples a model whose ``PSF_SAMP`` is not
        ``1/k`` (see there and :func:`resample_matrix`).

    Notes
    -----
    The API takes 0-based numpy pixel positions (x along columns); the
    conversion to PSFEx's 1-based FITS positions (X = x + 1) is made here.
    """

    def __init__(self, path, interpolant="sinc"):
        if interpolant not in INTERPOLANTS:
            raise ShearfitValueError(
                f"unknown PSF interpolant {interpolant!r}; valid: {', '.join(INTERPOLANTS)}")
        self.interpolant = interpolant
        self.path = Path(path)
        with _open_fits(self.path, "PSFEx") as hdul:
            if "PSF_DATA" not in [h.name for h in hdul]:
                raise ShearfitKeyError(
                    f"PSFEx file '{self.path}' has no PSF_DATA table (it has: {_hdu_list_text(hdul)})")
            h = hdul["PSF_DATA"]
            hdr = h.header
            try:
                mask = np.array(h.data["PSF_MASK"][0], dtype=np.float64)
            except (KeyError, IndexError, TypeError) as exc:
                raise ShearfitValueError(
                    f"PSFEx file '{self.path}': cannot read column PSF_MASK ({_one_line(exc)})") from None
        where = f"PSFEx file '{self.path}'"
        if mask.ndim == 2:
            mask = mask[None]
        if mask.ndim != 3:
            raise ShearfitValueError(f"{where}: PSF_MASK must be (n_terms, ny, nx), got shape {mask.shape}")
        if not np.all(np.isfinite(mask)):
            raise ShearfitValueError(f"{where}: PSF_MASK has non-finite values")

        naxis = int(hdr.get("POLNAXIS", 0))
        if naxis == 0:
            self.degree = 0
            self.polzero = (0.0, 0.0)
            self.polscal = (1.0, 1.0)
        elif naxis == 2:
            if int(hdr.get("POLNGRP", 1)) != 1 or int(hdr.get("POLGRP1", 1)) != 1 or int(hdr.get("POLGRP2", 1)) != 1:
                raise ShearfitValueError(f"{where}: only one polynomial group is supported (POLNGRP = 1)")
            axes = (_context_axis(hdr.get("POLNAME1")), _context_axis(hdr.get("POLNAME2")))
            if axes != ("x", "y"):
                raise ShearfitValueError(
                    f"{where}: the polynomial must be in (X_IMAGE, Y_IMAGE), got "
                    f"({hdr.get('POLNAME1')!r}, {hdr.get('POLNAME2')!r})")
            try:
                self.degree = int(hdr["POLDEG1"])
                self.polzero = (float(hdr["POLZERO1"]), float(hdr["POLZERO2"]))
                self.polscal = (float(hdr["POLSCAL1"]), float(hdr["POLSCAL2"]))
            except KeyError as exc:
                raise ShearfitKeyError(f"{where}: missing header keyword {exc.args[0]}") from None
            if not (self.polscal[0] != 0 and self.polscal[1] != 0):
                raise ShearfitValueError(f"{where}: POLSCAL1/2 must be non-zero, got {self.polscal}")
        else:
            raise ShearfitValueError(
                f"{where}: only models in image position (POLNAXIS = 2) or constant ones (0) are "
                f"supported, got POLNAXIS = {naxis}")
        d = self.degree
        self._terms = [(i, j) for j in range(d + 1) for i in range(d + 1 - j)]
        if mask.shape[0] != len(self._terms):
            raise ShearfitValueError(
                f"{where}: PSF_MASK has {mask.shape[0]} planes but degree {d} needs {len(self._terms)}")
        self.basis = mask
        self.basis.setflags(write=False)

        samp = float(hdr.get("PSF_SAMP", 1.0))
        if not (np.isfinite(samp) and samp > 0):
            raise ShearfitValueError(f"{where}: PSF_SAMP must be positive, got {samp!r}")
        self.psf_samp = samp
        # PSF_SAMP = 1/k exactly (0.5, 0.3333333...) means the model already
        # is on a 1/k grid of the image; the header stores 8 digits, hence
        # the tolerance. Otherwise resample onto the nearest 1/k grid (never
        # coarser than the image pixels).
        inv = 1.0 / samp
        k = max(1, int(round(inv)))
        self.oversampling = k
        self.needs_resampling = abs(inv - k) > 1e-5 * k
        ny, nx = mask.shape[1:]
        if self.needs_resampling:
            self._Wy = resample_matrix(ny, samp, _inner_size(ny, samp, k), 1.0 / k, interpolant)
            self._Wx = resample_matrix(nx, samp, _inner_size(nx, samp, k), 1.0 / k, interpolant)

    @property
    def shape(self):
        """Shape (ny, nx) of the arrays :meth:`image_at` returns."""
        if self.needs_resampling:
            return (self._Wy.shape[0], self._Wx.shape[0])
        return self.basis.shape[1:]

    def _coefficients(self, x, y):
        X = float(x) + 1.0     # PSFEx positions are 1-based FITS pixels
        Y = float(y) + 1.0
        xi = (X - self.polzero[0]) / self.polscal[0]
        eta = (Y - self.polzero[1]) / self.polscal[1]
        return np.array([xi**i * eta**j for i, j in self._terms])

    def native_image_at(self, x, y):
        """The model at 0-based pixel position (x, y) on PSFEx's own sample grid.

        Returns
        -------
        image : ndarray
            ``(ny, nx)`` float64, normalised to sum 1; sample spacing
            :attr:`psf_samp` image pixels; centre at ``(ny // 2, nx // 2)``.
        """
        img = np.tensordot(self._coefficients(x, y), self.basis, axes=1)
        return _normalised(img, f"PSFEx model '{self.path}' at (x, y) = ({x}, {y})")

    def image_at(self, x, y):
        """The PSF at 0-based pixel position (x, y), in the contract's convention.

        When ``PSF_SAMP = 1/k`` for an integer k the PSFEx samples are
        returned as they are, with ``oversampling = k``. Otherwise they are
        resampled onto the grid of spacing ``1/k`` image pixels, k the
        nearest integer to ``1/PSF_SAMP`` (at least 1), by separable
        interpolation. The default, band-limited (sinc) interpolation treats
        the samples as those of a function band-limited below the PSF
        grid's Nyquist frequency, which is what PSFEx's automatic sampling
        aims at; it is exact for such a function and does not broaden it.
        ``interpolant="lanczos3"`` reproduces instead what PSFEx and
        ``galsim.des.DES_PSFEx`` do (Lanczos-3). The two differ by ~6e-3 of
        the peak on a DECam model of FWHM 4.6 pixels (Lanczos-3 broader by
        0.3 % in size, PSF ellipticity different by up to 1e-3). Which is
        closer to the truth depends on how PSFEx built the model: with its
        default PIXEL_AUTO basis and FWHM > 3 pixels the samples are
        averages of stars already resampled once with Lanczos-3, and sinc
        adds no second smoothing; where PSFEx refined the samples through
        Lanczos-3 (small FWHM), ``"lanczos3"`` is the self-consistent
        choice. The output grid is centred on
        the same point and spans the largest odd size that fits inside the
        PSFEx vignette.

        Returns
        -------
        PSFImage
            ``(image, oversampling)``, image float64 summing to 1.
        """
        img = self.native_image_at(x, y)
        if self.needs_resampling:
            img = self._Wy @ img @ self._Wx.T
            img = _normalised(img, f"PSFEx model '{self.path}' at (x, y) = ({x}, {y})")
        return PSFImage(img, self.oversampling)

    def __repr__(self):
        return (f"PSFExModel('{self.path}', degree={self.degree}, psf_samp={self.psf_samp:.6g}, "
                f"oversampling={self.oversampling}, shape={self.shape}, interpolant={self.interpolant!r})")


def _inner_size(n, samp, k):
    """Odd size of the largest grid of step 1/k, centred like an n-sample grid of step samp, inside it."""
    # Half-extent of the input in output steps, on the shorter side of the
    # centre (n // 2 for odd n, n // 2 - 1 on one side for even n).
    half = int(np.floor(min(n // 2, n - 1 - n // 2) * samp * k + 1e-9))
    return 2 * half + 1


def _normalised(img, where):
    total = float(img.sum())
    if not (np.isfinite(total) and total > 0):
        raise ShearfitValueError(f"{where}: the PSF sums to {total:.6g}, cannot normalise")
    out = img / total
    out.setflags(write=False)
    return out

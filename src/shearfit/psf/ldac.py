"""Stars from a SExtractor FITS_LDAC catalogue with vignettes (the input PSFEx reads).

A user of PSFEx already has, per CCD, a catalogue whose ``VIGNET`` column
holds a small image of every PSF star (masked pixels set to about -1e30),
with windowed positions ``XWIN_IMAGE``/``YWIN_IMAGE`` and the image header
in the ``LDAC_IMHEAD`` HDU. :func:`read_ldac_stars` turns it into a
:class:`StarSet` for :func:`fit_pixel_psf`, so that shearfit's pixel model
can be fitted to the same stars PSFEx uses.

The vignette is centred on the pixel nearest the isophotal position
``X_IMAGE``/``Y_IMAGE`` (1-based FITS pixels), so a star's offset from the
vignette's centre pixel is ``XWIN_IMAGE - round(X_IMAGE)``. The per-pixel
variance is the sky's (``SKYSIGMA`` of the image header, or the robust
scatter of the vignettes' outer pixels) plus the star's own Poisson noise
(``GAIN`` or ``SEXGAIN``, e-/ADU).
"""

from __future__ import annotations

import numpy as np
from astropy.io import fits

from ..errors import ShearfitIOError, ShearfitValueError
from .build import APERTURE_RADIUS
from .pixelmodel import StarSet

__all__ = ["read_ldac_stars", "ldac_image_header"]

MASKED = -1e29          # SExtractor writes -BIG (about -1e30) into vignette pixels it has no data for


def ldac_image_header(hdul, path) -> fits.Header:
    """The image header stored, one card per row, in the LDAC_IMHEAD table."""
    if "LDAC_IMHEAD" not in hdul:
        raise ShearfitIOError(f"{path}: no LDAC_IMHEAD HDU (not a FITS_LDAC catalogue)")
    data = hdul["LDAC_IMHEAD"].data
    if data is None or len(data) == 0 or len(data.columns) == 0:
        raise ShearfitIOError(f"{path}: HDU LDAC_IMHEAD is empty")
    cards = np.atleast_1d(data[0][0])
    # one row of 80-character cards (TDIM (80, n)), or the cards as one string
    text = "".join(str(c).ljust(80)[:80] for c in cards) if cards.size > 1 else str(cards[0])
    return fits.Header.fromstring(text)


def read_ldac_stars(path, size: int = 25, gain=None, sky_sigma=None, hdu: str = "LDAC_OBJECTS"):
    """Read the stars of one CCD's FITS_LDAC catalogue.

    Parameters
    ----------
    path : str
        The catalogue.
    size : int
        Odd side of the stamps cut from the vignettes' centres.
    gain, sky_sigma : float, optional
        e-/ADU and the sky noise (ADU); by default from the image header
        (``GAIN`` or ``SEXGAIN``; ``SKYSIGMA``), the sky noise otherwise from
        the vignettes' outer pixels.

    Returns
    -------
    (StarSet, dict)
        Every star with a complete stamp (``ccd`` 0; ``u``, ``v`` the CCD
        position scaled to [-1, 1]; ``x``, ``y`` 0-based pixels), and
        ``info``: ``n_rows``, ``masked`` (index of the rows dropped for a masked
        pixel in the stamp), ``rows`` (the catalogue row of each star),
        ``shape`` (ny, nx of the CCD), ``gain``, ``sky_sigma``, ``header``.
    """
    size = int(size)
    if size < 3 or size % 2 == 0:
        raise ShearfitValueError(f"stamp size must be odd and at least 3, got {size}")
    try:
        hdul = fits.open(path)
    except OSError as exc:
        raise ShearfitIOError(f"{path}: cannot open: {exc}") from None
    with hdul:
        header = ldac_image_header(hdul, path)
        if hdu not in hdul:
            raise ShearfitIOError(f"{path}: no {hdu} HDU")
        tab = hdul[hdu].data
        names = set(tab.columns.names) if tab is not None else set()
        for col in ("VIGNET", "XWIN_IMAGE", "YWIN_IMAGE", "X_IMAGE", "Y_IMAGE"):
            if col not in names:
                raise ShearfitIOError(f"{path}: HDU {hdu} has no column {col}")
        vig = np.asarray(tab["VIGNET"], float)
        xw = np.asarray(tab["XWIN_IMAGE"], float)
        yw = np.asarray(tab["YWIN_IMAGE"], float)
        xi = np.asarray(tab["X_IMAGE"], float)
        yi = np.asarray(tab["Y_IMAGE"], float)
    if vig.ndim != 3 or vig.shape[1] < size or vig.shape[2] < size:
        raise ShearfitValueError(f"{path}: VIGNET of shape {vig.shape[1:]} is smaller than the stamp size {size}")
    if gain is None:
        gain = header.get("GAIN", header.get("SEXGAIN"))
    if gain is None or not float(gain) > 0:
        raise ShearfitIOError(f"{path}: LDAC_IMHEAD has no positive GAIN or SEXGAIN; pass gain=")
    gain = float(gain)
    ny_v, nx_v = vig.shape[1:]
    cy, cx = ny_v // 2, nx_v // 2
    h = size // 2
    stamp = vig[:, cy - h:cy + h + 1, cx - h:cx + h + 1]
    bad = stamp < MASKED
    if sky_sigma is None:
        sky_sigma = header.get("SKYSIGMA")
    if sky_sigma is None:
        ring = vig[:, [0, -1], :].reshape(-1)
        ring = ring[ring > MASKED]
        if ring.size < 10:
            raise ShearfitValueError(f"{path}: no SKYSIGMA in LDAC_IMHEAD and too few vignette pixels to estimate it")
        sky_sigma = 1.4826 * np.median(np.abs(ring - np.median(ring)))
    sky_sigma = float(sky_sigma)
    complete = ~np.any(bad, axis=(1, 2))
    rows = np.nonzero(complete)[0]
    img = stamp[complete]
    var = sky_sigma ** 2 + np.clip(img, 0.0, None) / gain
    ivar = 1.0 / var
    # FITS pixels are 1-based; the vignette's centre pixel is the one nearest (X_IMAGE, Y_IMAGE)
    delta = np.stack([xw[rows] - np.rint(xi[rows]), yw[rows] - np.rint(yi[rows])], axis=1)
    nx = int(header.get("NAXIS1", 0)) or int(np.ceil(xw.max()))
    ny = int(header.get("NAXIS2", 0)) or int(np.ceil(yw.max()))
    x0, y0 = xw[rows] - 1.0, yw[rows] - 1.0
    c = np.arange(size) - h
    ap = (c[:, None] ** 2 + c[None, :] ** 2) <= APERTURE_RADIUS ** 2
    snr = np.sum(img * ap, axis=(1, 2)) / np.sqrt(np.sum(var * ap, axis=(1, 2)))
    stars = StarSet(image=img, ivar=ivar, delta=delta, ccd=np.zeros(rows.size, int),
                    u=2.0 * x0 / nx - 1.0, v=2.0 * y0 / ny - 1.0, x=x0, y=y0, snr=snr)
    info = dict(n_rows=int(vig.shape[0]), masked=np.nonzero(~complete)[0], rows=rows, shape=(ny, nx),
                gain=gain, sky_sigma=sky_sigma, header=header)
    return stars, info

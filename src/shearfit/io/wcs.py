"""The local affine distortion of an exposure, from its WCS (sec. 6 of the paper).

lensfit corrects camera distortion by forward modelling: the galaxy model is
mapped through the *local linearised* pixel-to-sky transformation before it
is convolved with the PSF (whose stars were never distortion-corrected). This
module supplies that linear map, the Jacobian

.. math::

    J = \\begin{pmatrix} \\partial u/\\partial x & \\partial u/\\partial y \\\\
                         \\partial v/\\partial x & \\partial v/\\partial y \\end{pmatrix}
    \\quad [\\mathrm{arcsec\\ pixel^{-1}}],

where (x, y) are 0-based numpy pixel coordinates (x along columns, FITS
axis 1) and (u, v) is the gnomonic tangent plane centred on the object, +u
west, +v north (docs/interface.rst; GalSim's ``CelestialCoord.project`` and
TreeCorr). Because the tangent plane is centred on each object, ellipticities
measured through J are relative to the local east-west and north-south axes,
as the paper requires.

Every WCS goes through :class:`astropy.wcs.WCS`: TAN, TAN-SIP and TPV
(SCAMP's polynomial ``PVi_j`` distortion, which wcslib applies itself) are
all handled there. All functions are vectorised over positions.
"""

from __future__ import annotations

import warnings

import numpy as np
from astropy.io import fits
from astropy.wcs import WCS, FITSFixedWarning, NoConvergence

from ..errors import ShearfitValueError

__all__ = ["as_wcs", "header_from_ldac", "pixel_to_sky", "sky_to_pixel",
           "tangent_plane_offsets", "local_jacobian", "DEFAULT_STEP"]

# 1 radian in arcsec.
_RAD_TO_ARCSEC = 180.0 / np.pi * 3600.0

# Finite-difference step (pixels) of local_jacobian; see its docstring for
# the truncation-versus-rounding argument behind 0.5.
DEFAULT_STEP = 0.5


def as_wcs(wcs_or_header):
    """An :class:`astropy.wcs.WCS` with two celestial axes (RA, Dec) in that order.

    Parameters
    ----------
    wcs_or_header : astropy.wcs.WCS or astropy.io.fits.Header
        A WCS is returned unchanged (after the checks); a header is parsed.
        Real headers routinely carry deprecated keywords (``RADECSYS``) or
        declare fewer data axes than WCS axes (a header-only primary HDU);
        astropy's :class:`~astropy.wcs.FITSFixedWarning` about them is
        silenced because the fix it applies is the intended reading.

    Raises
    ------
    ShearfitValueError
        If there is no celestial WCS, or its axes are not (longitude, latitude).
    """
    if isinstance(wcs_or_header, WCS):
        w = wcs_or_header
    elif isinstance(wcs_or_header, fits.Header):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FITSFixedWarning)
            try:
                w = WCS(wcs_or_header, naxis=2)
            except Exception as exc:  # astropy raises several types for bad headers
                raise ShearfitValueError(f"cannot read a WCS from the header: {exc}") from exc
    else:
        raise ShearfitValueError(
            f"expected an astropy.wcs.WCS or astropy.io.fits.Header, got {type(wcs_or_header).__name__}")
    if not w.has_celestial or w.naxis != 2:
        raise ShearfitValueError(f"the WCS is not a 2D celestial WCS (CTYPE = {list(w.wcs.ctype)})")
    if (w.wcs.lng, w.wcs.lat) != (0, 1):
        # Pixel axis 1 must be the longitude: the rest of the package assumes
        # (ra, dec) = f(x, y) in that order.
        raise ShearfitValueError(
            f"the WCS axes must be (RA, Dec) in that order, got CTYPE = {list(w.wcs.ctype)}")
    return w


def header_from_ldac(hdu):
    """The image header stored in an LDAC ``LDAC_IMHEAD`` table (SExtractor/PSFEx catalogues).

    Parameters
    ----------
    hdu : astropy.io.fits.BinTableHDU
        The ``LDAC_IMHEAD`` extension: one row, one column ("Field Header
        Card") holding the header as an array of 80-character cards.

    Returns
    -------
    astropy.io.fits.Header
    """
    try:
        cards = hdu.data[hdu.columns.names[0]][0]
    except (AttributeError, IndexError, TypeError) as exc:
        raise ShearfitValueError(f"not an LDAC_IMHEAD table: {exc}") from exc
    # FITS strips the trailing blanks of each card; join with a separator so
    # that Header.fromstring does not rely on the 80-character padding.
    lines = [c.decode("ascii") if isinstance(c, bytes) else str(c) for c in np.atleast_1d(cards)]
    return fits.Header.fromstring("\n".join(lines), sep="\n")


def _broadcast(*arrays):
    arrs = np.broadcast_arrays(*[np.asarray(a, dtype=np.float64) for a in arrays])
    scalar = arrs[0].ndim == 0
    return arrs, scalar


def _finish(a, scalar):
    return float(a) if scalar else a


def pixel_to_sky(wcs, x, y):
    """Sky position (ra, dec) in degrees of 0-based pixel position(s) (x, y).

    A thin wrapper of ``all_pix2world(x, y, 0)``, so every distortion (SIP,
    TPV, lookup tables) is included. Arrays broadcast; scalars give floats.
    """
    w = as_wcs(wcs)
    (x, y), scalar = _broadcast(x, y)
    ra, dec = w.all_pix2world(x.ravel(), y.ravel(), 0)
    return _finish(ra.reshape(x.shape), scalar), _finish(dec.reshape(x.shape), scalar)


def sky_to_pixel(wcs, ra, dec, tolerance=1e-8):
    """0-based pixel position(s) (x, y) of sky position(s) (ra, dec) in degrees.

    A thin wrapper of ``all_world2pix(ra, dec, 0)``. The inverse of a distorted
    WCS is iterative; ``tolerance`` (pixels) is far below astropy's default of
    1e-4 pixel because stamp positions feed sub-pixel centroid offsets.
    Positions where the iteration fails (far outside a distorted CCD) come
    back as NaN rather than raising, so one bad object does not stop a field.
    """
    w = as_wcs(wcs)
    (ra, dec), scalar = _broadcast(ra, dec)
    try:
        x, y = w.all_world2pix(ra.ravel(), dec.ravel(), 0, tolerance=tolerance, maxiter=50)
    except NoConvergence as exc:
        best = np.array(exc.best_solution, dtype=np.float64).reshape(-1, 2)
        bad = np.zeros(best.shape[0], dtype=bool)
        for idx in (exc.divergent, exc.slow_conv):
            if idx is not None:
                bad[np.asarray(idx, dtype=int)] = True
        best[bad] = np.nan
        x, y = best[:, 0], best[:, 1]
    return _finish(np.asarray(x).reshape(ra.shape), scalar), _finish(np.asarray(y).reshape(ra.shape), scalar)


def tangent_plane_offsets(ra, dec, ra0, dec0):
    """Gnomonic projection of (ra, dec) about (ra0, dec0): (u, v) in arcsec, +u west, +v north.

    .. math::

        \\cos c &= \\sin\\delta_0 \\sin\\delta + \\cos\\delta_0 \\cos\\delta \\cos\\Delta\\alpha \\\\
        u &= -\\cos\\delta \\sin\\Delta\\alpha / \\cos c \\\\
        v &= (\\cos\\delta_0 \\sin\\delta - \\sin\\delta_0 \\cos\\delta \\cos\\Delta\\alpha) / \\cos c

    with :math:`\\Delta\\alpha = \\alpha - \\alpha_0` wrapped to (-180, 180]
    degrees. This is GalSim's ``CelestialCoord.project(..., projection='gnomonic')``
    convention (+u points to decreasing RA). The numerators are rewritten with
    :math:`1 - \\cos\\Delta\\alpha = 2 \\sin^2(\\Delta\\alpha / 2)` and
    :math:`\\sin(\\delta - \\delta_0)` so that sub-arcsecond offsets do not lose
    digits to cancellation. Points 90 degrees or more from the centre have no
    gnomonic image and give NaN.

    Parameters
    ----------
    ra, dec, ra0, dec0 : float or array
        Degrees; all broadcast together.
    """
    (ra, dec, ra0, dec0), scalar = _broadcast(ra, dec, ra0, dec0)
    dra = np.radians((ra - ra0 + 180.0) % 360.0 - 180.0)
    d = np.radians(dec)
    d0 = np.radians(dec0)
    ddec = np.radians(dec - dec0)
    cosd = np.cos(d)
    hav = 2.0 * np.sin(0.5 * dra) ** 2          # 1 - cos(dra), without cancellation
    cosc = np.cos(ddec) - np.cos(d0) * cosd * hav
    with np.errstate(divide="ignore", invalid="ignore"):
        u = -cosd * np.sin(dra) / cosc
        v = (np.sin(ddec) + np.sin(d0) * cosd * hav) / cosc
    far = ~(cosc > 0)
    u = np.where(far, np.nan, u) * _RAD_TO_ARCSEC
    v = np.where(far, np.nan, v) * _RAD_TO_ARCSEC
    return _finish(u, scalar), _finish(v, scalar)


def local_jacobian(wcs, x, y, ra0=None, dec0=None, h=DEFAULT_STEP):
    """Local Jacobian ``d(u, v)/d(x, y)`` in arcsec per pixel at pixel position(s) (x, y).

    (u, v) is the gnomonic tangent plane about the object (+u west, +v north),
    x, y are 0-based numpy pixel coordinates, x along columns. The derivatives
    are centred finite differences of the WCS's full pixel-to-sky mapping
    (``all_pix2world``, distortions included) projected onto that plane:
    ``du/dx = [u(x+h, y) - u(x-h, y)] / 2h`` and so on.

    Why ``h = 0.5`` pixel: a centred difference has truncation error
    ``h^2 f''' / 6``. The third derivative comes from the distortion
    polynomial (cubic TPV/SIP terms, coefficients ~0.1 deg^-2 across a CCD)
    and from the gnomonic projection (``(pixel/radian)^2 ~ 1e-12``); on the
    DECam TPV header of the tests the truncation error measures ~5e-10 h^2
    of the pixel scale. Rounding enters through the sky positions: doubles
    in degrees carry ~1e-14 deg of rounding at RA ~ 100 deg, which divided
    by ``2h`` and by the pixel size (~1e-4 deg) gives ~2e-10 / h (measured:
    2e-8 at h = 0.01). The sum is smallest near h ~ 0.7 pixel; at 0.5 it is
    ~6e-10 of the pixel scale, far below what shear needs (1e-4) and the
    1e-6 the tests ask for. Much smaller steps lose digits to rounding;
    steps of tens of pixels feel the distortion's curvature (2e-7 at h = 20).

    Parameters
    ----------
    wcs : astropy.wcs.WCS or astropy.io.fits.Header
    x, y : float or array
        0-based pixel coordinates; broadcast together.
    ra0, dec0 : float or array, optional
        Centre of the tangent plane (degrees). By default the object's own sky
        position at (x, y), which is what the catalogue convention needs.
        Giving another centre (e.g. a field centre) rotates the frame by the
        convergence of meridians between the two points.
    h : float
        Finite-difference step in pixels.

    Returns
    -------
    J : ndarray, shape ``(2, 2)`` for scalar x, y, else ``x.shape + (2, 2)``
        ``[[du/dx, du/dy], [dv/dx, dv/dy]]``.
    """
    if not (np.isfinite(h) and h > 0):
        raise ShearfitValueError(f"finite-difference step h must be positive, got {h!r}")
    w = as_wcs(wcs)
    (x, y), scalar = _broadcast(x, y)
    shape = x.shape
    xf, yf = x.ravel(), y.ravel()
    n = xf.size
    # One all_pix2world call for the centre and the four offset points of
    # every position: the WCS overhead is per call, not per point.
    xs = np.concatenate([xf, xf + h, xf - h, xf, xf])
    ys = np.concatenate([yf, yf, yf, yf + h, yf - h])
    ra, dec = w.all_pix2world(xs, ys, 0)
    if ra0 is None or dec0 is None:
        if (ra0 is None) != (dec0 is None):
            raise ShearfitValueError("give both ra0 and dec0, or neither")
        c_ra, c_dec = ra[:n], dec[:n]
    else:
        c_ra = np.broadcast_to(np.asarray(ra0, dtype=np.float64), shape).ravel()
        c_dec = np.broadcast_to(np.asarray(dec0, dtype=np.float64), shape).ravel()
    u, v = tangent_plane_offsets(ra[n:], dec[n:], np.tile(c_ra, 4), np.tile(c_dec, 4))
    u = u.reshape(4, n)
    v = v.reshape(4, n)
    J = np.empty((n, 2, 2))
    J[:, 0, 0] = (u[0] - u[1]) / (2.0 * h)
    J[:, 0, 1] = (u[2] - u[3]) / (2.0 * h)
    J[:, 1, 0] = (v[0] - v[1]) / (2.0 * h)
    J[:, 1, 1] = (v[2] - v[3]) / (2.0 * h)
    J = J.reshape(shape + (2, 2))
    return J.reshape(2, 2) if scalar else J

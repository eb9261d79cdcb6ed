"""Shared helpers of the tests that simulate small fields with GalSim (not a test module)."""

import numpy as np
from astropy.io import fits

#: pixel scale (arcsec) and tangent point (deg) of the simulated fields
PIX = 0.187
RA0, DEC0 = 150.0, 2.0


def sky_header(n, crpix_shift, angle_deg):
    """A TAN header of an n x n exposure at (RA0, DEC0), north up and east left (CD1_1 < 0) then rotated by
    ``angle_deg``, its reference pixel shifted by ``crpix_shift`` (a dither), with the zero point, gain and
    saturation the pipeline reads."""
    th = np.radians(angle_deg)
    cd = PIX / 3600.0 * np.array([[-np.cos(th), np.sin(th)], [np.sin(th), np.cos(th)]])
    h = fits.Header()
    h["CTYPE1"], h["CTYPE2"] = "RA---TAN", "DEC--TAN"
    h["CRVAL1"], h["CRVAL2"] = RA0, DEC0
    h["CRPIX1"], h["CRPIX2"] = n / 2 + crpix_shift[0], n / 2 + crpix_shift[1]
    h["CD1_1"], h["CD1_2"], h["CD2_1"], h["CD2_2"] = cd[0, 0], cd[0, 1], cd[1, 0], cd[1, 1]
    h["MAGZP"], h["GAIN"], h["SATURATE"] = 30.0, 1.0, 1e6
    return h


def write_dithered_exposure(d, name, n, crpix_shift, angle_deg, sources, psf, rng, sigma=0.5, stamp=160):
    """Draw ``sources`` ((ra, dec, GalSim profile) each) convolved with the GalSim ``psf`` on an n x n exposure
    (:func:`sky_header`), add Gaussian noise ``sigma``, and write ``name``.fits, its weight and its PSF image
    (48 pixels, unit sum) to directory ``d``. Returns the exposure's entry of a field config and the PSF image."""
    import galsim

    h = sky_header(n, crpix_shift, angle_deg)
    wcs = galsim.GSFitsWCS(header=h)
    img = galsim.ImageD(n, n, wcs=wcs)
    for ra, dec, prof in sources:
        pos = wcs.toImage(galsim.CelestialCoord(ra * galsim.degrees, dec * galsim.degrees))
        drawn = galsim.Convolve(prof, psf).drawImage(wcs=wcs.local(pos), nx=stamp, ny=stamp, center=pos)
        b = drawn.bounds & img.bounds
        img[b] += drawn[b]
    fits.PrimaryHDU(img.array + rng.normal(0, sigma, img.array.shape), header=h).writeto(d / f"{name}.fits")
    fits.PrimaryHDU(np.full((n, n), 1 / sigma ** 2), header=h).writeto(d / f"{name}.weight.fits")
    pim = psf.drawImage(wcs=wcs.local(galsim.PositionD(n / 2, n / 2)), nx=48, ny=48, use_true_center=False).array
    pim = pim / pim.sum()
    fits.PrimaryHDU(pim).writeto(d / f"{name}.psf.fits")
    return {"image": f"{name}.fits", "weight": f"{name}.weight.fits", "psf": f"{name}.psf.fits"}, pim

"""PSF star selection on a CCD (shearfit.psf.build.select_stars): the cuts and their counts."""

import numpy as np
from astropy.wcs import WCS

from shearfit.io.fieldconfig import PipelineConfig
from shearfit.io.fits import ExposureCCD
from shearfit.io.wcs import pixel_to_sky
from shearfit.psf.build import FieldFrame, select_stars
from skyfield import sky_header

N = 240


def _ccd(stars, sigma=1.0, rng=None):
    rng = np.random.default_rng(1) if rng is None else rng
    y, x = np.mgrid[0:N, 0:N]
    img = rng.normal(0.0, sigma, (N, N))
    for sx, sy, flux in stars:
        img += flux * np.exp(-((x - sx) ** 2 + (y - sy) ** 2) / (2 * 1.5 ** 2)) / (2 * np.pi * 1.5 ** 2)
    w = np.full((N, N), 1.0 / sigma ** 2)
    return ExposureCCD(image=img, weight=w, wcs=WCS(sky_header(N, (0.0, 0.0), 0.0)), magzp=30.0, gain=1.0,
                       saturate=1e6, path="ccd.fits", hdu=0, dims=(N, N))


def test_select_stars_counts_each_cut_once_in_order():
    """A star with another catalogue object within psf_isolation_radius (8 px) is rejected as crowded; its own
    catalogue entry (0.3 px away) and objects farther than the radius are not neighbours; a star too faint or
    too near the edge is counted under its own cut, the edge before the neighbour."""
    pc = PipelineConfig()
    stars = [(60.0, 60.0, 3000.0), (120.0, 60.0, 3000.0), (60.0, 150.0, 3000.0), (150.0, 150.0, 3000.0),
             (180.0, 60.0, 20.0),        # too faint for psf_min_snr
             (5.0, 120.0, 3000.0)]       # its stamp runs off the CCD
    ccd = _ccd(stars)
    sx = np.array([s[0] for s in stars])
    sy = np.array([s[1] for s in stars])
    ra, dec = pixel_to_sky(ccd.wcs, sx, sy)
    # other catalogue objects: each star itself (0.3 px off), one 5 px from star 1, one 12 px from star 2, one
    # 4 px from the edge star (which the edge cut takes first)
    ox = np.concatenate([sx + 0.3, [120.0 + 5.0, 60.0, 5.0 + 4.0]])
    oy = np.concatenate([sy, [60.0, 150.0 + 12.0, 120.0]])
    ora, odec = pixel_to_sky(ccd.wcs, ox, oy)
    got, index, cand, usable, rejected = select_stars([ccd], ra, dec, ora, odec, pc, FieldFrame.of_exposure([ccd]))
    assert list(index) == [0, 2, 3]
    assert cand.tolist() == [6] and usable.tolist() == [3]
    assert rejected == {"off CCD edge or unusable pixel": 1, "SNR below minimum": 1, "saturated": 0, "neighbour": 1}
    assert got.image.shape == (3, pc.psf_size, pc.psf_size)

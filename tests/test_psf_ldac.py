"""Stars read from a SExtractor FITS_LDAC catalogue with vignettes, and the pixel model fitted to them."""

from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

from shearfit.errors import ShearfitIOError
from shearfit.psf.ldac import read_ldac_stars
from shearfit.psf.pixelmodel import fit_pixel_psf, gaussian_centroid, residual_images

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "decam_00241238_01_stars.fits"


def _real():
    if not REAL.exists():
        pytest.skip(f"real data not available: {REAL}")
    return REAL


def _ldac(path, n=3, size=31, header=("GAIN = 4.0", "SKYSIGMA = 2.0", "NAXIS1 = 200", "NAXIS2 = 100"),
          drop=None, seed=0):
    """A small FITS_LDAC file of Gaussian stars whose vignettes are centred on round(X_IMAGE)."""
    rng = np.random.default_rng(seed)
    xw = rng.uniform(20, 180, n)
    yw = rng.uniform(20, 80, n)
    c = np.arange(size) - size // 2
    vig = []
    for x, y in zip(xw, yw):
        dx, dy = x - np.rint(x + 0.05), y - np.rint(y - 0.05)
        g = np.exp(-0.5 * ((c[None, :] - dx) ** 2 + (c[:, None] - dy) ** 2) / 2.0 ** 2)
        vig.append(1000.0 * g / g.sum() + rng.normal(0, 0.2, (size, size)))
    vig = np.array(vig, np.float32)
    vig[0, 0, 0] = -1e30          # masked corner pixel, outside a small stamp
    cards = [f"{k.split('=')[0].strip():8s}= {k.split('=')[1].strip():>20s}" for k in header]
    head = fits.BinTableHDU.from_columns([fits.Column("Field Header Card", f"{80 * len(cards)}A",
                                                      array=np.array(["".join(c.ljust(80) for c in cards)]))],
                                         name="LDAC_IMHEAD")
    cols = {"VIGNET": fits.Column("VIGNET", f"{size * size}E", dim=f"({size}, {size})", array=vig),
            "XWIN_IMAGE": fits.Column("XWIN_IMAGE", "D", array=xw),
            "YWIN_IMAGE": fits.Column("YWIN_IMAGE", "D", array=yw),
            "X_IMAGE": fits.Column("X_IMAGE", "E", array=xw + 0.05),
            "Y_IMAGE": fits.Column("Y_IMAGE", "E", array=yw - 0.05)}
    if drop:
        cols.pop(drop)
    obj = fits.BinTableHDU.from_columns(list(cols.values()), name="LDAC_OBJECTS")
    fits.HDUList([fits.PrimaryHDU(), head, obj]).writeto(path, overwrite=True)
    return xw, yw


def test_synthetic_catalogue_offsets_noise_and_mask(tmp_path):
    path = tmp_path / "cat.fits"
    xw, yw = _ldac(path)
    stars, info = read_ldac_stars(path, size=15)
    assert len(stars) == 3 and info["gain"] == 4.0 and info["sky_sigma"] == 2.0 and info["shape"] == (100, 200)
    np.testing.assert_allclose(stars.delta[:, 0], xw - np.rint(xw + 0.05))
    np.testing.assert_allclose(stars.x, xw - 1.0)
    cx, cy = gaussian_centroid(stars.image, 1.0, 2.0)
    np.testing.assert_allclose(cx, stars.delta[:, 0], atol=0.05)
    np.testing.assert_allclose(cy, stars.delta[:, 1], atol=0.05)
    # sky variance plus the star's Poisson term
    np.testing.assert_allclose(1 / stars.ivar[:, 0, 0], 4.0 + np.clip(stars.image[:, 0, 0], 0, None) / 4.0)
    # the whole 31-pixel vignette holds the masked pixel of the first star
    full, info = read_ldac_stars(path, size=31)
    assert len(full) == 2 and list(info["masked"]) == [0]


@pytest.mark.parametrize("drop", ["VIGNET", "XWIN_IMAGE", "X_IMAGE"])
def test_missing_column_is_named(tmp_path, drop):
    path = tmp_path / "cat.fits"
    _ldac(path, drop=drop)
    with pytest.raises(ShearfitIOError, match=f"{path}.*LDAC_OBJECTS.*{drop}"):
        read_ldac_stars(path, size=15)


def test_missing_gain_is_named(tmp_path):
    path = tmp_path / "cat.fits"
    _ldac(path, header=("SKYSIGMA = 2.0",))
    with pytest.raises(ShearfitIOError, match="GAIN"):
        read_ldac_stars(path, size=15)
    stars, info = read_ldac_stars(path, size=15, gain=2.0)
    assert info["gain"] == 2.0 and info["shape"] == (int(np.ceil(stars.y.max() + 1)), int(np.ceil(stars.x.max() + 1)))


def test_not_ldac_is_named(tmp_path):
    path = tmp_path / "plain.fits"
    fits.HDUList([fits.PrimaryHDU(np.zeros((3, 3)))]).writeto(path)
    with pytest.raises(ShearfitIOError, match="LDAC_IMHEAD"):
        read_ldac_stars(path)


def test_real_decam_stars_model_reaches_the_noise():
    """The 117 DECam stars: vignette centring convention and a pixel model whose residuals are near the noise."""
    stars, info = read_ldac_stars(_real(), size=21)
    assert info["n_rows"] == 117 and len(stars) == 95
    assert info["gain"] == pytest.approx(4.039) and info["sky_sigma"] == pytest.approx(8.31, abs=0.01)
    cx, cy = gaussian_centroid(stars.image, 1.0, 2.0)
    # XWIN_IMAGE - round(X_IMAGE) is the offset from the vignette's centre pixel (centroid scatter 0.02 px)
    assert abs(np.mean(cx - stars.delta[:, 0])) < 0.01 and abs(np.mean(cy - stars.delta[:, 1])) < 0.01
    assert np.std(cx - stars.delta[:, 0]) < 0.05
    model, used, res = fit_pixel_psf(stars, 1, order=1, iterations=3)
    r, flux = residual_images(model, used)
    chi2 = np.mean(r ** 2 * flux[:, None, None] ** 2 * used.ivar, axis=(1, 2))
    # residuals of stars in the fit (so slightly below the noise): median reduced chi^2 near 1
    assert 0.8 < np.median(chi2) < 1.3
    assert np.isclose(model.image(0, 0.0, 0.0).sum(), 1.0)

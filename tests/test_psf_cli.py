"""``shearfit psf`` on a small GalSim field: model file, diagnostics, and automatic star selection."""

import numpy as np
import pytest
import yaml
from astropy.io import fits
from astropy.table import Table

galsim = pytest.importorskip("galsim")

from shearfit.app.cli import main  # noqa: E402
from shearfit.psf.build import read_psf_model  # noqa: E402

PIX = 0.187
RA0, DEC0 = 150.0, 2.0
N = 320
PSF = galsim.Moffat(beta=3.0, fwhm=0.7).shear(e1=0.04, e2=-0.03)


def _header():
    cd = PIX / 3600.0
    h = fits.Header()
    h["CTYPE1"], h["CTYPE2"] = "RA---TAN", "DEC--TAN"
    h["CRVAL1"], h["CRVAL2"] = RA0, DEC0
    h["CRPIX1"], h["CRPIX2"] = N / 2, N / 2
    h["CD1_1"], h["CD1_2"], h["CD2_1"], h["CD2_2"] = -cd, 0.0, 0.0, cd
    h["MAGZP"], h["GAIN"], h["SATURATE"] = 30.0, 1.0, 1e7
    return h


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    """One exposure, one CCD: 7 x 7 stars (SNR 100-400) and 16 galaxies between them."""
    d = tmp_path_factory.mktemp("psffield")
    rng = np.random.default_rng(3)
    h = _header()
    wcs = galsim.GSFitsWCS(header=h)
    img = galsim.ImageD(N, N, wcs=wcs)
    sigma = 1.0
    stars, gals = [], []
    for i in range(7):
        for j in range(7):
            x, y = 40 + 40 * i + rng.uniform(-2, 2), 40 + 40 * j + rng.uniform(-2, 2)
            flux = rng.uniform(100, 400) * sigma * 2 * np.sqrt(np.pi) * (0.7 / 2.355 / PIX)
            stars.append((x, y, flux))
            PSF.withFlux(flux).drawImage(image=img, wcs=wcs.local(galsim.PositionD(x, y)),
                                         center=galsim.PositionD(x, y), add_to_image=True)
    for i in range(4):
        for j in range(4):
            x, y = 60 + 60 * i, 60 + 60 * j
            gal = galsim.Convolve(galsim.Exponential(scale_radius=0.4, flux=3000).shear(e1=0.2, e2=0.1), PSF)
            gals.append((x, y))
            gal.drawImage(image=img, wcs=wcs.local(galsim.PositionD(x, y)), center=galsim.PositionD(x, y),
                          add_to_image=True)
    data = img.array + rng.normal(0, sigma, img.array.shape)
    fits.PrimaryHDU(data, header=h).writeto(d / "exp0.fits")
    fits.PrimaryHDU(np.full(data.shape, 1 / sigma ** 2), header=h).writeto(d / "exp0.weight.fits")

    def radec(xy):
        sky = [wcs.toWorld(galsim.PositionD(x, y)) for x, y in xy]
        return np.array([s.ra.deg for s in sky]), np.array([s.dec.deg for s in sky])

    sra, sdec = radec([(x, y) for x, y, _ in stars])
    gra, gdec = radec(gals)
    smag = 30 - 2.5 * np.log10([f for *_, f in stars])
    Table({"id": np.arange(len(stars)), "ra": sra, "dec": sdec, "mag": smag}).write(d / "stars.fits")
    Table({"id": 1000 + np.arange(len(gals)), "ra": gra, "dec": gdec, "mag": np.full(len(gals), 21.3)}).write(
        d / "objects.fits")
    # the catalogue of every object (stars included), for the automatic selection
    Table({"id": np.arange(len(stars) + len(gals)), "ra": np.concatenate([sra, gra]),
           "dec": np.concatenate([sdec, gdec]), "mag": np.concatenate([smag, np.full(len(gals), 21.3)])}).write(
        d / "all.fits")
    base = {"exposures": [{"image": "exp0.fits", "weight": "exp0.weight.fits"}], "psf_min_stars": 20,
            "psf_order": 1}
    (d / "stars.yaml").write_text(yaml.safe_dump(dict(base, catalog="objects.fits", stars="stars.fits")))
    (d / "auto.yaml").write_text(yaml.safe_dump(dict(base, catalog="all.fits")))
    return d, len(stars)


def _true_psf(n=25):
    return galsim.Convolve(PSF, galsim.Pixel(PIX)).drawImage(nx=n, ny=n, scale=PIX, method="no_pixel").array


def _check_model(path):
    model = read_psf_model(path)
    img = model.image(0, 0.0, 0.0)
    true = _true_psf(img.shape[0])
    return float(np.sqrt(np.mean((img - true / true.sum()) ** 2)))


def test_psf_command_with_star_catalogue(field, capsys):
    d, n_stars = field
    out = d / "out_stars"
    assert main(["psf", str(d / "stars.yaml"), "--out", str(out), "--no-bootstrap"]) == 0
    models = list(out.glob("*.psfmodel.fits"))
    assert len(models) == 1
    assert list(out.glob("*.png")), "diagnostic plots are written"
    summary = fits.getdata(out / "psf_summary.fits")
    assert summary["n_stars"][0] >= n_stars - 4
    # per-pixel error of the model against GalSim's PSF, relative to the total flux
    assert _check_model(models[0]) < 5e-4


def test_psf_command_selects_stars_from_the_locus(field):
    d, n_stars = field
    out = d / "out_auto"
    assert main(["psf", str(d / "auto.yaml"), "--out", str(out), "--no-bootstrap"]) == 0
    summary = fits.getdata(out / "psf_summary.fits")
    # the stars of the catalogue, and none of the 16 galaxies (a galaxy would spoil the model)
    assert n_stars - 6 <= summary["n_stars"][0] <= n_stars
    assert _check_model(next(out.glob("*.psfmodel.fits"))) < 5e-4


def test_psf_command_holds_blas_to_one_thread(field, monkeypatch, tmp_path):
    """shearfit psf fits its star models with one BLAS thread (no wall time to gain from more) and restores it."""
    from blasthreads import threads_set_to

    from shearfit.workers import thread_controls

    from shearfit.pipeline import driver

    libs = thread_controls()
    if not libs:
        pytest.skip("no BLAS or OpenMP thread control found through /proc/self/maps (not Linux)")
    seen = []
    real = driver.fit_exposure_psf

    def fit(*args, **kwargs):
        seen.append([get() for get, _ in libs])
        return real(*args, **kwargs)

    monkeypatch.setattr(driver, "fit_exposure_psf", fit)
    d, _ = field
    with threads_set_to(libs, 2):
        assert main(["psf", str(d / "stars.yaml"), "--out", str(tmp_path / "psf"), "--no-bootstrap", "--quiet"]) == 0
        after = [get() for get, _ in libs]
    assert seen == [[1] * len(libs)]
    assert after == [2] * len(libs)

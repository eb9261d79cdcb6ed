"""Piff ``.piff`` PSF models as a given PSF (shearfit.io.piffpsf and the ``psf:`` hook of the field pipeline).

The models are made here: Piff fits its Moffat model (``GSObjectModel``, pixel
response included, parameters linear over the chip) to GalSim-drawn stars on a
TAN WCS rotated against the sky, and writes it with ``PSF.write``. The reader
is checked against Piff's own ``PSF.draw`` (like with like: both normalised),
against the true PSF the stars were drawn with, for its centring convention,
the CCD -> chipnum mapping and its errors; then a tiny simulated field is
measured with Piff models fitted to its own stars, against the same field
measured with the true PSF images.
"""

import pickle
import sys
import types

import numpy as np
import pytest
import yaml
from astropy.io import fits
from astropy.table import Table

piff = pytest.importorskip("piff")
galsim = pytest.importorskip("galsim")

from shearfit.errors import ShearfitIOError, ShearfitValueError  # noqa: E402
from shearfit.io.piffpsf import PiffModel, is_piff_path  # noqa: E402
from shearfit.pipeline.driver import _load_psf  # noqa: E402

PIX = 0.187
N = 200                      # chip side, pixels
RA0, DEC0 = 35.0, -4.0
STAMP = 25

# image_at(x, y) is Piff's draw at FITS (x + 1, y + 1), centred on pixel (n // 2, n // 2) and divided by its
# sum: the two differ only by the local WCS (taken at (x + 1, y + 1) here, at the nearest pixel centre by
# Piff), measured <= 3e-9 of the peak. The model varies fast enough that a 0-/1-based slip (drawing at (x, y))
# changes the image by ~2e-3 of the peak, which the tests check is detectable at this tolerance.
DRAW_TOL = 1e-4
# Against the true PSF the stars were drawn with: Piff's fit of the same (Moffat) family to 40 stars at
# SNR ~1000, linear over the chip, as the truth is: measured <= 1.2e-4 of the peak. A 0-/1-based slip would
# be ~2e-3, so this check also catches one without relying on Piff's own draw.
TRUTH_TOL = 1e-3


def _header(angle_deg=20.0, crpix=(N / 2 + 0.5, N / 2 + 0.5)):
    th = np.radians(angle_deg)
    cd = PIX / 3600.0 * np.array([[-np.cos(th), np.sin(th)], [np.sin(th), np.cos(th)]])
    h = fits.Header()
    h["CTYPE1"], h["CTYPE2"] = "RA---TAN", "DEC--TAN"
    h["CRVAL1"], h["CRVAL2"] = RA0, DEC0
    h["CRPIX1"], h["CRPIX2"] = crpix
    h["CD1_1"], h["CD1_2"], h["CD2_1"], h["CD2_2"] = cd[0, 0], cd[0, 1], cd[1, 0], cd[1, 1]
    return h


def true_psf(X, Y):
    """The sky-frame PSF at FITS image position (X, Y): a Moffat whose size and shape vary fast over the chip."""
    t, s = (X - N / 2) / N, (Y - N / 2) / N
    return galsim.Moffat(beta=3.0, fwhm=0.75 * (1 + 0.2 * s)).shear(g1=0.04 + 0.12 * t, g2=-0.03 + 0.08 * s)


def _fit_model(path, wcs, n_star=40, seed=1, chipnum=0):
    """Fit Piff's Moffat model, linear over the chip, to stars drawn with ``true_psf`` through ``wcs``; write it."""
    rng = np.random.default_rng(seed)
    pointing = galsim.CelestialCoord(RA0 * galsim.degrees, DEC0 * galsim.degrees)
    stars = []
    for _ in range(n_star):
        X, Y = rng.uniform(15, N - 15, 2)
        pos = galsim.PositionD(X, Y)
        c = galsim.PositionI(int(round(X)), int(round(Y)))
        im = galsim.ImageD(galsim.BoundsI(c.x - STAMP // 2, c.x + STAMP // 2, c.y - STAMP // 2, c.y + STAMP // 2), wcs=wcs)
        true_psf(X, Y).withFlux(1e6).drawImage(im, center=pos, method="auto")
        sigma = 10.0
        im.array[:] += rng.normal(0, sigma, im.array.shape)
        w = galsim.ImageD(im.bounds, init_value=1 / sigma ** 2, wcs=wcs)
        stars.append(piff.Star(piff.StarData(im, pos, weight=w, pointing=pointing,
                                             properties={"chipnum": chipnum}), None))
    psf = piff.SimplePSF(piff.GSObjectModel(galsim.Moffat(beta=3.0, fwhm=0.8), fastfit=True),
                         piff.Polynomial(order=1))
    psf.set_context({chipnum: wcs}, pointing)
    psf.fit(stars)
    psf.write(str(path))
    return psf


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    d = tmp_path_factory.mktemp("piff")
    h = _header()
    wcs = galsim.GSFitsWCS(header=h)
    path = d / "exp0.piff"
    _fit_model(path, wcs)
    return path, wcs, d


POSITIONS = [(99.5, 99.5), (10.0, 20.0), (180.3, 25.7), (37.25, 170.8), (150.6, 120.1)]   # 0-based (x, y)


def _piff_draw(psf, x, y, n=STAMP, chipnum=0):
    """Piff's own drawing at 0-based (x, y): FITS (x + 1, y + 1), centred on the stamp's central pixel."""
    im = psf.draw(x + 1.0, y + 1.0, chipnum=chipnum, stamp_size=n, center=True).array
    return im / im.sum()


def test_image_at_matches_piff_draw(model):
    """image_at(x, y) is Piff's draw at (x + 1, y + 1) to 1e-4 of the peak, and a 0/1-based slip is not."""
    path, _, _ = model
    m = PiffModel(path, n_ccd=1)
    ccd = m.for_ccd(0)
    ref_psf = piff.read(str(path))
    worst = 0.0
    for x, y in POSITIONS:
        img, k = ccd.image_at(x, y)
        assert k == 1 and img.shape == (STAMP, STAMP) and img.dtype == np.float64
        assert not img.flags.writeable
        ref = _piff_draw(ref_psf, x, y)
        diff = np.abs(img - ref).max() / ref.max()
        worst = max(worst, diff)
        assert diff < DRAW_TOL, (x, y, diff)
        # the same position read 0-based by mistake: detectable at DRAW_TOL
        slip = np.abs(img - _piff_draw(ref_psf, x - 1.0, y - 1.0)).max() / ref.max()
        assert slip > 10 * DRAW_TOL, (x, y, slip)
    print(f"max |image_at - Piff draw| / peak = {worst:.2e}")


def test_image_at_is_the_true_psf_in_the_pixel_frame(model):
    """Against the Moffat the stars were drawn with, pixel included, through the rotated WCS at the position."""
    path, wcs, _ = model
    ccd = PiffModel(path).for_ccd(0)
    for x, y in POSITIONS:
        X, Y = x + 1.0, y + 1.0
        truth = true_psf(X, Y).drawImage(nx=STAMP, ny=STAMP, wcs=wcs.local(galsim.PositionD(X, Y)),
                                         use_true_center=True, method="auto").array
        truth /= truth.sum()
        img = ccd.image_at(x, y).image
        assert np.abs(img - truth).max() / truth.max() < TRUTH_TOL, (x, y)
        # the shape is the PSF's in this CCD's pixel frame: the sky shear carried through the rotated WCS
        got, want = (galsim.hsm.FindAdaptiveMom(galsim.Image(a, scale=1.0)).observed_shape for a in (img, truth))
        assert abs(got.g1 - want.g1) < 5e-3 and abs(got.g2 - want.g2) < 5e-3


@pytest.mark.parametrize("n", [25, 31])
def test_image_at_sums_to_one_and_is_centred(model, n):
    """Sum 1, centroid on array index (n // 2, n // 2) to 1e-3 pixel (odd stamps: symmetric truncation)."""
    path, _, _ = model
    ccd = PiffModel(path, stamp_size=n).for_ccd(0)
    yy, xx = np.indices((n, n))
    for x, y in POSITIONS:
        img, _ = ccd.image_at(x, y)
        assert img.shape == (n, n) and img.sum() == pytest.approx(1.0, abs=1e-12)
        assert abs((img * xx).sum() - n // 2) < 1e-3 and abs((img * yy).sum() - n // 2) < 1e-3, (x, y)


def test_even_stamp_is_centred_on_n_over_2(model):
    """An even stamp has its centre on index n // 2 too: the odd stamp one larger less its last row and column."""
    path, _, _ = model
    even, odd = (PiffModel(path, stamp_size=n).for_ccd(0) for n in (24, 25))
    for x, y in POSITIONS:
        a = even.image_at(x, y).image
        b = odd.image_at(x, y).image[:24, :24]
        assert np.abs(a - b / b.sum()).max() < 1e-12 * a.max() + 1e-15


def test_chipnum_mapping(model, tmp_path):
    """Header CHIPNUM before CCDNUM, the only chip, then the CCD index; an explicit list; errors list the chips."""
    path, wcs, _ = model
    psf = piff.read(str(path))
    # a two-chip model: chip 5's pixel grid is turned 90 degrees against chip 3's
    wcs90 = galsim.GSFitsWCS(header=_header(110.0))
    psf.wcs = {3: wcs, 5: wcs90}
    two = tmp_path / "two.piff"
    psf.write(str(two))
    ref = piff.read(str(two))

    with pytest.raises(ShearfitValueError, match=r"two.piff.*chipnums \[3, 5\]"):
        PiffModel(two, n_ccd=2)                         # indices 0, 1 are not chips of the model
    hdrs = [fits.Header({"CCDNUM": 3, "CHIPNUM": 5}), fits.Header({"CCDNUM": 5, "CHIPNUM": 3})]
    assert PiffModel(two, n_ccd=2, headers=hdrs).chipnums == [5, 3]          # CHIPNUM first
    assert PiffModel(two, n_ccd=2, headers=[fits.Header({"CCDNUM": 3}), fits.Header({"CCDNUM": 5})]).chipnums == [3, 5]
    # a CCD left out of the exposure: the headers of the others, by CCD index
    m = PiffModel(two, n_ccd=3, headers={0: fits.Header({"CCDNUM": 5}), 2: fits.Header({"CCDNUM": 3})})
    assert m.chipnums == [5, None, 3]
    with pytest.raises(ShearfitValueError, match="CCD 1 has no CHIPNUM/CCDNUM"):
        m.for_ccd(1)
    m = PiffModel(two, n_ccd=2, chipnums=[5, 3])
    for i, chip in enumerate([5, 3]):
        img = m.for_ccd(i).image_at(60.0, 80.0).image
        assert np.abs(img - _piff_draw(ref, 60.0, 80.0, chipnum=chip)).max() < DRAW_TOL * img.max()
    # the two chips really differ (a 90 degree turn of an elliptical PSF), so the test above tells them apart
    a, b = (m.for_ccd(i).image_at(60.0, 80.0).image for i in range(2))
    assert np.abs(a - b).max() > 0.05 * a.max()
    with pytest.raises(ShearfitValueError, match=r"chipnum\(s\) \[4\]"):
        PiffModel(two, chipnums=[3, 4])
    # one chip, one CCD: that chip whatever its number or the header's (the model's chip is 0 here)
    assert PiffModel(path, n_ccd=1, headers=[fits.Header({"CCDNUM": 1})]).chipnums == [0]
    with pytest.raises(ShearfitValueError, match="2 CCD"):
        PiffModel(path, n_ccd=2)


def test_errors_are_one_line_and_name_the_file(model, tmp_path, monkeypatch):
    path, _, _ = model
    missing = tmp_path / "nope.piff"
    plain = tmp_path / "plain.piff"
    fits.PrimaryHDU(np.zeros((5, 5))).writeto(plain)
    text = tmp_path / "text.piff"
    text.write_text("not a Piff file\n")
    for f, exc, what in [(missing, ShearfitIOError, "does not exist"), (plain, ShearfitIOError, "not a Piff model"),
                         (text, ShearfitIOError, "not a Piff model"), (tmp_path, ShearfitIOError, "directory")]:
        with pytest.raises(exc, match=what) as info:
            PiffModel(f)
        assert str(f) in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(ShearfitValueError, match="stamp_size"):
        PiffModel(path, stamp_size=3)
    # piff not installed: an import of it fails
    monkeypatch.setitem(sys.modules, "piff", None)
    with pytest.raises(ShearfitIOError, match="install piff to read .piff PSF models") as info:
        PiffModel(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_model_pickles(model):
    """The per-CCD models cross process boundaries (the pipeline's workers get them pickled)."""
    path, _, _ = model
    ccd = PiffModel(path, n_ccd=1).for_ccd(0)
    again = pickle.loads(pickle.dumps(ccd))
    assert np.array_equal(again.image_at(50.2, 60.7).image, ccd.image_at(50.2, 60.7).image)


def test_load_psf_hook(model):
    """A ``psf:`` path ending in .piff becomes one Piff model per CCD of the exposure."""
    path, _, _ = model
    assert is_piff_path(path) and is_piff_path("X.PIFF") and not is_piff_path("x.psf")
    spec = types.SimpleNamespace(psf=str(path), image="exp0.fits")
    epsf = _load_psf(spec, 1, 0)
    got, k = epsf.at(0, 40.5, 70.25)
    assert k == 1 and np.array_equal(got, PiffModel(path).for_ccd(0).image_at(40.5, 70.25).image)
    assert epsf.shift(0, 40.5, 70.25) == (0.0, 0.0)


# ----------------------------------------------------------------------------------------------------------
# the pipeline on a tiny simulated field
# ----------------------------------------------------------------------------------------------------------

def _piff_from_field_stars(d, spec, stars, sc, out):
    """Fit Piff's Moffat model (beta fixed at 3.5; linear over the CCD) to the stars cut from one exposure."""
    with fits.open(d / spec["image"]) as h, fits.open(d / spec["weight"]) as hw:
        hdr, data, w = h[1].header, h[1].data.astype(float), hw[1].data.astype(float)
    wcs = galsim.GSFitsWCS(header=hdr)
    full, wim = galsim.ImageD(data, wcs=wcs), galsim.ImageD(w, wcs=wcs)
    pointing = galsim.CelestialCoord(sc.ra * galsim.degrees, sc.dec * galsim.degrees)
    slist = []
    for ra, dec in zip(stars["ra"], stars["dec"]):
        pos = wcs.toImage(galsim.CelestialCoord(ra * galsim.degrees, dec * galsim.degrees))
        c = galsim.PositionI(int(round(pos.x)), int(round(pos.y)))
        b = galsim.BoundsI(c.x - 12, c.x + 12, c.y - 12, c.y + 12)
        if full.bounds.includes(b):
            slist.append(piff.Star(piff.StarData(full[b].copy(), pos, weight=wim[b].copy(), pointing=pointing,
                                                 properties={"chipnum": 0}), None))
    psf = piff.SimplePSF(piff.GSObjectModel(galsim.Moffat(beta=3.5, fwhm=0.7)), piff.Polynomial(order=1))
    psf.set_context({0: wcs}, pointing)
    psf.fit(slist)
    psf.write(str(out))
    return len(slist)


def test_field_measured_with_piff_models(tmp_path):
    """The tiny preset, measured with Piff models fitted to each exposure's stars and with the true PSF images.

    Both runs see the same pixels (same noise), so their differences are the PSF models' alone: Piff's
    Moffat has beta fixed at 3.5 (the truth's is drawn in [2.5, 4.5] per exposure) and follows the PSF's
    variation over the CCD, where the true-PSF images are the PSF at the CCD centre only (the simulation
    varies FWHM and ellipticity by ~2 % over the field). Measured: max |e_piff - e_true| 0.014, means
    below 0.004, against a median statistical error sqrt(e_var) of 0.027 and a shape noise of ~0.25.
    The tolerances (0.03 per galaxy, 0.01 in the mean, 0.01 in the PSF ellipticity) are ~2x those.
    """
    from shearfit.io.fieldconfig import load_field_config
    from shearfit.pipeline.driver import measure_field
    from shearfit.simulate.field import simulate_field, simulation_config

    sc = simulation_config({"preset": "tiny", "seed": 5})
    simulate_field(sc, tmp_path)
    stars = Table.read(tmp_path / "stars.fits")
    conf = yaml.safe_load((tmp_path / "field_truepsf.yaml").read_text())
    for k, spec in enumerate(conf["exposures"]):
        assert _piff_from_field_stars(tmp_path, spec, stars, sc, tmp_path / f"exp{k}.piff") >= 15
        spec["psf"] = f"exp{k}.piff"
    conf["output"] = "shear_piff.fits"
    (tmp_path / "field_piff.yaml").write_text(yaml.safe_dump(conf))

    tt = measure_field(load_field_config(tmp_path / "field_truepsf.yaml"), tmp_path / "shear_true.fits")
    tp = measure_field(load_field_config(tmp_path / "field_piff.yaml"), tmp_path / "shear_piff.fits")
    gal = ~np.asarray(Table.read(tmp_path / "truth.fits")["is_star"])
    ft, fp = np.asarray(tt["fitclass"])[gal], np.asarray(tp["fitclass"])[gal]
    # the same objects measured (most of the rest are blends, -3, with either PSF)
    assert np.sum(fp == 0) >= max(10, np.sum(ft == 0) - 2)
    assert np.mean(fp == ft) >= 0.9
    both = (ft == 0) & (fp == 0)
    de = np.stack([np.asarray(tp[c])[gal][both] - np.asarray(tt[c])[gal][both] for c in ("e1", "e2")])
    print(f"{both.sum()} galaxies: max |de| = {np.abs(de).max():.4f}, mean de = {de.mean(axis=1)}")
    assert np.abs(de).max() < 0.03
    assert np.all(np.abs(de.mean(axis=1)) < 0.01)
    # the PSF at the CCD centre, where the true-PSF image is the truth: the same shape and size
    for k in range(sc.n_exposures):
        with fits.open(tmp_path / f"exp{k}.psf.fits") as h:
            true_img, over = h[1].data.astype(float), h[1].header["OVERSAMP"]
        piff_img = PiffModel(tmp_path / f"exp{k}.piff", n_ccd=1).for_ccd(0).image_at(
            0.5 * (sc.ccd_nx - 1), 0.5 * (sc.ccd_ny - 1)).image
        mt = galsim.hsm.FindAdaptiveMom(galsim.Image(true_img, scale=1.0 / over))
        mp = galsim.hsm.FindAdaptiveMom(galsim.Image(piff_img, scale=1.0))
        dg = (mp.observed_shape.g1 - mt.observed_shape.g1, mp.observed_shape.g2 - mt.observed_shape.g2)
        ds = mp.moments_sigma / (mt.moments_sigma / over) - 1
        print(f"exposure {k}: PSF at the centre, Piff - true: dg = ({dg[0]:+.4f}, {dg[1]:+.4f}), dsigma/sigma = {ds:+.4f}")
        assert max(abs(dg[0]), abs(dg[1])) < 0.015 and abs(ds) < 0.025
    # over the CCD the PSF varies (by ~0.01 in ellipticity here); the true-PSF run uses the centre's everywhere
    for c in ("psf_e1", "psf_e2"):
        assert np.all(np.abs(np.asarray(tp[c])[gal][both] - np.asarray(tt[c])[gal][both]) < 0.03)

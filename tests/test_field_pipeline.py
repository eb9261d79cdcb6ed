"""End to end: a small GalSim-simulated field through ``shearfit measure``.

Two exposures of one CCD each, the second dithered and with its pixel grid
rotated by 30 degrees; GalSim draws every galaxy through its own celestial
WCS (so the sky frame on the simulation side is GalSim's, not shearfit's
Jacobian code); the PSF is given as a FITS image per exposure; the
galaxies are a ring of 4 orientations with one shear, at high SNR.
"""

import json

import numpy as np
import pytest
import yaml
from astropy.io import fits
from astropy.table import Table

galsim = pytest.importorskip("galsim")

from shearfit.app.cli import main  # noqa: E402
from shearfit.simulate.stamps import galaxy_profile, moffat_psf  # noqa: E402
from shearfit.pipeline import driver  # noqa: E402
from skyfield import DEC0, PIX, RA0, sky_header, write_dithered_exposure  # noqa: E402

G = (0.04, -0.03)


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    d = tmp_path_factory.mktemp("field")
    n = 200
    rng = np.random.default_rng(4)
    gals = []
    # 2 rings of 4 orientations, on a grid well inside the CCD
    for k, (r, e) in enumerate([(0.35, 0.3), (0.5, 0.45)]):
        for j in range(4):
            ej = e * np.exp(1j * np.pi * j / 2)
            ra = RA0 + (-(k - 0.5) * 40 * PIX / 3600) / np.cos(np.radians(DEC0))
            dec = DEC0 + (j - 1.5) * 40 * PIX / 3600
            gals.append(dict(id=10 * k + j, ra=ra, dec=dec, r=r, e1=ej.real, e2=ej.imag, mag=22.0))
    specs = []
    for x, (shift, ang, fwhm) in enumerate([((0.0, 0.0), 0.0, 0.65), ((3.3, -2.6), 30.0, 0.7)]):
        h = sky_header(n, shift, ang)
        wcs = galsim.GSFitsWCS(header=h)
        img = galsim.ImageD(n, n, wcs=wcs)
        psf = moffat_psf(fwhm, 3.0, 0.05, -0.03)
        for g in gals:
            pos = wcs.toImage(galsim.CelestialCoord(g["ra"] * galsim.degrees, g["dec"] * galsim.degrees))
            prof = galsim.Convolve(galaxy_profile(g["r"], 0.1, g["e1"], g["e2"], flux=2e4, g1=G[0], g2=G[1]), psf)
            stamp = prof.drawImage(wcs=wcs.local(pos), nx=64, ny=64, center=pos)
            b = stamp.bounds & img.bounds
            img[b] += stamp[b]
        sigma = 0.5
        data = img.array + rng.normal(0, sigma, img.array.shape)
        fits.PrimaryHDU(data, header=h).writeto(d / f"exp{x}.fits")
        fits.PrimaryHDU(np.full(data.shape, 1 / sigma ** 2), header=h).writeto(d / f"exp{x}.weight.fits")
        # the PSF in this exposure's pixel frame: draw it through the local WCS at the centre
        pim = psf.drawImage(wcs=wcs.local(galsim.PositionD(n / 2, n / 2)), nx=48, ny=48,
                            use_true_center=False).array
        fits.PrimaryHDU(pim / pim.sum()).writeto(d / f"exp{x}.psf.fits")
        specs.append({"image": f"exp{x}.fits", "weight": f"exp{x}.weight.fits", "psf": f"exp{x}.psf.fits"})
    cat = Table(rows=[(g["id"], g["ra"], g["dec"], g["mag"]) for g in gals], names=("ID", "RA", "DEC", "MAG"))
    cat.add_row((99, RA0 + 1.0, DEC0, 22.0))   # off every exposure
    cat.write(d / "objects.fits")
    (d / "field.yaml").write_text(yaml.safe_dump({"exposures": specs, "catalog": "objects.fits"}))
    return d, gals


def test_measure_field_end_to_end(field, capsys):
    d, gals = field
    out = d / "shear.fits"
    assert main(["measure", str(d / "field.yaml"), "--out", str(out), "--quiet"]) == 0
    t = Table.read(out)
    for col in ("id", "ra", "dec", "mag", "e1", "e2", "weight", "e_var", "fitclass", "snr", "scalelength",
                "bulge_fraction", "model_flux", "n_exposures_used", "psf_e1", "psf_e2", "m"):
        assert col in t.colnames
    assert list(t["id"]) == [g["id"] for g in gals] + [99]          # input order
    assert t["fitclass"][-1] == -6                                   # off every exposure
    good = t[:-1]
    assert np.all(good["fitclass"] == 0) and np.all(good["n_exposures_used"] == 2)
    # the sheared intrinsic shapes, in the (u, v) frame
    for row, g in zip(good, gals):
        s = galsim.Shear(g1=G[0], g2=G[1]) + galsim.Shear(g1=g["e1"], g2=g["e2"])
        assert abs(row["e1"] - s.g1) < 0.03 and abs(row["e2"] - s.g2) < 0.03
    # ring averages recover the shear (2 rings, high SNR)
    assert np.mean(good["e1"]) == pytest.approx(G[0], abs=0.01)
    assert np.mean(good["e2"]) == pytest.approx(G[1], abs=0.01)
    # the PSF ellipticity column: the Moffat's (0.05, -0.03) in the sky frame
    assert np.all(np.abs(good["psf_e1"] - 0.05) < 0.01) and np.all(np.abs(good["psf_e2"] + 0.03) < 0.01)
    # the PSF size column: the mean over the two exposures of 2.3548 sigma of GalSim's adaptive moments of the
    # Moffats (FWHM 0.65" and 0.7"), in arcsec whatever the pixel grid's rotation
    hsm = [2.3548 * PIX * galsim.hsm.FindAdaptiveMom(moffat_psf(f, 3.0, 0.05, -0.03).drawImage(
        nx=48, ny=48, scale=PIX)).moments_sigma for f in (0.65, 0.7)]
    assert np.allclose(good["psf_fwhm"], np.mean(hsm), rtol=2e-3) and 0.675 < np.mean(hsm) < 0.85
    hdr = fits.getheader(out, 1)
    assert "SFCONFIG" in hdr and "SFVERS" in hdr
    from shearfit.engine.kernel import kernel_info
    assert hdr["SFKERNEL"] == kernel_info()["path"] and hdr["SFISA"] == kernel_info()["isa"]
    # too few galaxies for bins of 100: one bin, every galaxy the mean of lensfit's weights; 0 off the exposures
    assert hdr["ISOBINS"] == 1 and t["iso_weight"][-1] == 0
    np.testing.assert_allclose(good["iso_weight"], np.mean(good["weight"]), rtol=1e-12)
    # the same catalogue with two worker processes, bit for bit
    out2 = d / "shear_j2.fits"
    assert main(["measure", str(d / "field.yaml"), "--out", str(out2), "--quiet", "-j", "2"]) == 0
    t2 = Table.read(out2)
    for col in ("e1", "e2", "weight", "fitclass", "snr", "iso_weight"):
        assert np.array_equal(np.asarray(t[col]), np.asarray(t2[col]), equal_nan=True)


def test_measure_bad_config_is_one_line(field, capsys):
    d, _ = field
    bad = d / "bad.yaml"
    bad.write_text("exposures: [{image: exp0.fits}]\ncatalog: objects.fits\nstamp_sizee: 48\n")
    assert main(["measure", str(bad), "--out", str(d / "x.fits")]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "stamp_sizee" in err and not (d / "x.fits").exists()


@pytest.fixture(scope="module")
def crowded(tmp_path_factory):
    """Aligned exposures with a blended pair and bad columns.

    Masking of separate neighbours is tested on stamps in test_field_blends.py: in a field at
    SNR ~50 a neighbour within the 48-pixel stamp is usually inside the object's 2-sigma
    isophote of the PSF-smoothed co-add (the smoothing lowers the noise about 5 times), so the
    paper's criterion calls it a blend.
    """
    d = tmp_path_factory.mktemp("crowded")
    n = 200
    rng = np.random.default_rng(8)
    def sky(dx, dy):   # pixel offsets from the field centre -> (ra, dec); x is west-positive here
        return RA0 - dx * PIX / 3600 / np.cos(np.radians(DEC0)), DEC0 + dy * PIX / 3600
    objs = {  # name: (dx, dy, r, e1, e2, flux, in catalogue)
        "isolated": (-50, -50, 0.3, 0.2, 0.1, 400.0, True),
        "blend_a": (40, -50, 0.3, 0.1, 0.0, 400.0, True),
        "blend_b": (49, -46, 0.3, -0.1, 0.2, 400.0, False),     # 9.8 px away: isophotes merge, two peaks
        "with_neighbour": (-50, 40, 0.3, 0.0, 0.2, 400.0, True),
        "neighbour": (-50 + 22, 40 + 6, 0.2, 0.3, 0.0, 0.0, False),   # 23 px away, faint: separate isophote
        "bad_column_near": (40, 40, 0.3, 0.1, 0.1, 400.0, True),
        "bad_column_far": (0, 0, 0.3, -0.2, 0.0, 400.0, True),
        "close_a": (0, 72, 0.2, 0.1, 0.0, 400.0, True),
        "close_b": (2, 73.5, 0.2, -0.1, 0.1, 300.0, True),      # 2.5 px away: one maximum, two catalogue rows
    }
    specs = []
    for x, shift in enumerate([(0.0, 0.0), (1.4, -0.8)]):
        h = sky_header(n, shift, 0.0)
        wcs = galsim.GSFitsWCS(header=h)
        img = galsim.ImageD(n, n, wcs=wcs)
        psf = moffat_psf(0.7, 3.0, 0.02, 0.0)
        for name, (dx, dy, r, e1, e2, flux, _) in objs.items():
            ra, dec = sky(dx, dy)
            pos = wcs.toImage(galsim.CelestialCoord(ra * galsim.degrees, dec * galsim.degrees))
            prof = galsim.Convolve(galaxy_profile(r, 0.0, e1, e2, flux=flux), psf)
            stamp = prof.drawImage(wcs=wcs.local(pos), nx=64, ny=64, center=pos)
            b = stamp.bounds & img.bounds
            img[b] += stamp[b]
        data = img.array + rng.normal(0, 1.0, (n, n))
        w = np.ones((n, n))
        if x == 0:
            ra, dec = sky(*objs["bad_column_near"][:2])
            col = int(round(wcs.toImage(galsim.CelestialCoord(ra * galsim.degrees, dec * galsim.degrees)).x - 1))
            w[:, col + 1] = 0.0        # crosses that galaxy's isophote, one pixel from its centre
            ra, dec = sky(*objs["bad_column_far"][:2])
            col = int(round(wcs.toImage(galsim.CelestialCoord(ra * galsim.degrees, dec * galsim.degrees)).x - 1))
            w[:, col + 21] = 0.0       # inside the stamp but far outside the isophote
        fits.PrimaryHDU(data, header=h).writeto(d / f"exp{x}.fits")
        fits.PrimaryHDU(w, header=h).writeto(d / f"exp{x}.weight.fits")
        pim = psf.drawImage(wcs=wcs.local(galsim.PositionD(n / 2, n / 2)), nx=48, ny=48, use_true_center=False).array
        fits.PrimaryHDU(pim / pim.sum()).writeto(d / f"exp{x}.psf.fits")
        specs.append({"image": f"exp{x}.fits", "weight": f"exp{x}.weight.fits", "psf": f"exp{x}.psf.fits"})
    names = [k for k, v in objs.items() if v[6]]
    rows = [(i, *sky(*objs[k][:2]), 22.0) for i, k in enumerate(names)]
    Table(rows=rows, names=("id", "ra", "dec", "mag")).write(d / "objects.fits")
    (d / "field.yaml").write_text(yaml.safe_dump({"exposures": specs, "catalog": "objects.fits"}))
    return d, names, objs


def test_blends_neighbours_and_masks(crowded):
    d, names, objs = crowded
    out = d / "shear.fits"
    assert main(["measure", str(d / "field.yaml"), "--out", str(out), "--quiet"]) == 0
    t = Table.read(out)
    row = {k: t[i] for i, k in enumerate(names)}
    assert row["blend_a"]["fitclass"] == -3
    # a pair under the PSF is one maximum; each is inside the other's isophote, listed in the catalogue
    assert row["close_a"]["fitclass"] == -3 and row["close_b"]["fitclass"] == -3
    for k in ("isolated", "bad_column_far"):
        assert row[k]["fitclass"] == 0 and row[k]["n_exposures_used"] == 2, k
    # the bad column through its isophote drops that exposure; the object is still measured
    assert row["bad_column_near"]["fitclass"] == 0 and row["bad_column_near"]["n_exposures_used"] == 1
    # shapes of the truth within the noise
    for k in ("isolated", "bad_column_far", "bad_column_near"):
        _, _, r, e1, e2, _, _ = objs[k]
        sd = np.sqrt(row[k]["e_var"])
        assert abs(row[k]["e1"] - e1) < 4 * sd + 0.01 and abs(row[k]["e2"] - e2) < 4 * sd + 0.01, k


def test_catalogue_blends_reach_across_chunks(crowded):
    """The close pair measured one object per chunk: each chunk still knows the other's catalogue position, while
    without catalogue_blends the deblender, seeing one maximum, fits the pair as a galaxy."""
    d, names, objs = crowded
    got = {}
    for flag in ("true", "false"):
        out = d / f"shear_chunks_{flag}.fits"
        assert main(["measure", str(d / "field.yaml"), "chunk_size=1", f"catalogue_blends={flag}", "--out", str(out),
                     "--quiet"]) == 0
        t = Table.read(out)
        got[flag] = {k: int(t["fitclass"][i]) for i, k in enumerate(names)}
    assert got["true"]["close_a"] == got["true"]["close_b"] == -3
    assert 0 in (got["false"]["close_a"], got["false"]["close_b"])
    assert {k: v for k, v in got["true"].items() if not k.startswith("close")} == \
        {k: v for k, v in got["false"].items() if not k.startswith("close")}


def test_measure_applies_a_given_calibration(field):
    from shearfit.calib.calibrate import calibration_m

    d, gals = field
    (d / "cal.yaml").write_text("alpha: 0.1\nbeta: -0.5\n")
    conf = yaml.safe_load((d / "field.yaml").read_text())
    conf["calibration"] = "cal.yaml"
    (d / "field_cal.yaml").write_text(yaml.safe_dump(conf))
    out = d / "shear_cal.fits"
    assert main(["measure", str(d / "field_cal.yaml"), "--out", str(out), "--quiet"]) == 0
    t = Table.read(out)
    good = t["fitclass"] == 0
    np.testing.assert_allclose(t["m"][good], calibration_m(t["snr"][good], t["scalelength"][good], 0.1, -0.5))
    assert not np.any(np.isfinite(np.ma.filled(t["m"][~good], np.nan)))
    hdr = fits.getheader(out, 1)
    assert hdr["CALALPHA"] == 0.1 and hdr["CALBETA"] == -0.5 and "cal.yaml" in hdr.comments["CALALPHA"]


def _large_galaxy_field(d, r=1.2, e=(0.25, -0.15)):
    """One CCD, two exposures (the second rotated by 30 degrees), one galaxy of scalelength r arcsec: its model,
    truncated at 4.5 r (29 pixels for 1.2"), does not fit half a 48-pixel stamp (24); no noise to speak of."""
    n = 260
    rng = np.random.default_rng(7)
    specs = []
    for x, (shift, ang) in enumerate([((0.0, 0.0), 0.0), ((2.3, -1.6), 30.0)]):
        spec, _ = write_dithered_exposure(d, f"big{x}", n, shift, ang,
                                          [(RA0, DEC0, galaxy_profile(r, 0.0, e[0], e[1], flux=1e6))],
                                          moffat_psf(0.7, 3.0, 0.03, 0.02), rng, stamp=200)
        specs.append(spec)
    Table(rows=[(1, RA0, DEC0, 19.0)], names=("id", "ra", "dec", "mag")).write(d / "big.fits")
    (d / "big.yaml").write_text(yaml.safe_dump({"exposures": specs, "catalog": "big.fits"}))
    return d / "big.yaml"


def test_stamps_grow_for_a_large_galaxy(tmp_path):
    """A galaxy too large for the 48-pixel stamp is measured again on a larger stamp (64 pixels here) and
    recovered, where the paper's fixed stamp (max_stamp_size=48) flags it -4."""
    cfg = _large_galaxy_field(tmp_path)
    fixed, grown = tmp_path / "fixed.fits", tmp_path / "grown.fits"
    assert main(["measure", str(cfg), "max_stamp_size=48", "--out", str(fixed), "--quiet"]) == 0
    assert main(["measure", str(cfg), "--out", str(grown), "--quiet"]) == 0
    f, g = Table.read(fixed)[0], Table.read(grown)[0]
    assert f["fitclass"] == -4 and f["stamp_size"] == 48 and f["weight"] == 0
    assert g["fitclass"] == 0 and g["stamp_size"] == 64 and g["weight"] > 0   # 29 pixels fit half of 64
    # intrinsic shape (0.25, -0.15), no shear: recovered at this SNR to a few times its likelihood width
    assert abs(g["e1"] - 0.25) < 0.02 and abs(g["e2"] + 0.15) < 0.02, (g["e1"], g["e2"])
    assert g["scalelength"] == pytest.approx(1.2, rel=0.1)


def test_a_chunks_jacobians_and_psf_positions_are_those_of_one_call_each():
    """The pipeline takes every local Jacobian (and fitted-PSF position) of a chunk's objects in one vectorised
    call per CCD: the same numbers, to the bit, as one call per object and exposure."""
    from types import SimpleNamespace

    from shearfit.io.wcs import local_jacobian, pixel_to_sky
    from shearfit.pipeline.driver import _chunk_geometry

    h = sky_header(200, (1.5, -2.0), 30.0)

    class Frame:
        def model_uv(self, c, x, y):
            return pixel_to_sky(h, x, y)   # any vectorised function of (x, y) stands in for the model's frame

        def fitted_at_many(self, c, x, y, uv):
            return None   # no model images here (tests/test_psf_model.py checks images_at)

    exposures = [([SimpleNamespace(wcs=h)], Frame()), ([SimpleNamespace(wcs=h)], SimpleNamespace(model_uv=lambda *a: None))]
    hits = [[(0, 0, 10.0, 20.0), (1, 0, 11.5, 19.25)], [(0, 0, 150.25, 40.75)], [(0, 0, 10.0, 20.0)]]
    geo = _chunk_geometry(exposures, hits)
    assert len(geo) == 3
    for (e, c, x, y), (J, uv, got, shift, mom) in geo.items():
        assert got is None and shift is None and mom is None   # no fitted model, no moment grid here
        assert np.array_equal(J, local_jacobian(h, x, y))
        if e == 0:
            assert uv == tuple(pixel_to_sky(h, x, y))
        else:
            assert uv is None


def test_self_calibrated_fits_get_their_own_default_calibration(field):
    """With ``self_calibration: true`` and no calibration file, the m column comes from the package's table
    fitted with that setting in force (``default_calibration(self_calibration=True)``), which the header names;
    the plain fit's table would give other m."""
    from shearfit.calib.calibrate import default_calibration

    d, gals = field
    conf = yaml.safe_load((d / "field.yaml").read_text())
    conf["self_calibration"] = True
    conf.pop("calibration", None)
    (d / "field_selfcal.yaml").write_text(yaml.safe_dump(conf))
    out = d / "shear_selfcal.fits"
    assert main(["measure", str(d / "field_selfcal.yaml"), "--out", str(out), "--quiet"]) == 0
    t = Table.read(out)
    good = t["fitclass"] == 0
    assert good.sum() >= 2
    np.testing.assert_allclose(t["m"][good], default_calibration(self_calibration=True).m_of(t[good]))
    assert not np.allclose(t["m"][good], default_calibration().m_of(t[good]))
    hdr = fits.getheader(out, 1)
    assert "self-cal" in hdr.comments["CALALPHA"]
    assert json.loads(hdr["SFCONFIG"])["self_calibration"] is True


def test_noise_bias_corrected_fits_carry_no_simulation_calibration(field, monkeypatch):
    """With ``noise_bias_correction: true`` and no calibration file, the estimates are corrected in the engine
    (each object's added noise drawn from its own stream of ``metacal_seed``): the m column is 0, the header
    says ``CALMODE = 'noise-bias extrapolation'``, the same run repeated gives the same catalogue, and every
    object's fit is given a seed of its own."""
    d, gals = field
    conf = yaml.safe_load((d / "field.yaml").read_text())
    conf["self_calibration"] = True
    conf["noise_bias_correction"] = True
    conf.pop("calibration", None)
    (d / "field_nbc.yaml").write_text(yaml.safe_dump(conf))
    tabs = []
    for k in range(2):
        out = d / f"shear_nbc{k}.fits"
        assert main(["measure", str(d / "field_nbc.yaml"), "--out", str(out), "--quiet"]) == 0
        tabs.append(Table.read(out))
    t = tabs[0]
    good = t["fitclass"] == 0
    assert good.sum() >= 2
    assert np.all(t["m"][good] == 0.0)
    np.testing.assert_array_equal(t["e1"], tabs[1]["e1"])
    hdr = fits.getheader(d / "shear_nbc0.fits", 1)
    assert hdr["CALMODE"] == "noise-bias extrapolation"
    assert "CALALPHA" not in hdr
    # the bias measured on the fit's model instead: the header says so
    conf["noise_bias_on_model"] = True
    (d / "field_nbm.yaml").write_text(yaml.safe_dump(conf))
    assert main(["measure", str(d / "field_nbm.yaml"), "--out", str(d / "shear_nbm.fits"), "--quiet"]) == 0
    hdr_m = fits.getheader(d / "shear_nbm.fits", 1)
    assert hdr_m["CALMODE"] == "noise bias on the model" and "CALALPHA" not in hdr_m
    tm = Table.read(d / "shear_nbm.fits")
    assert np.all(tm["fitclass"] == t["fitclass"]) and np.all(tm["m"][good] == 0.0)
    assert json.loads(hdr["SFCONFIG"])["noise_bias_correction"] is True
    seeds = []
    real = driver.measure_object

    def spy(obs, mag, config=None, return_samples=False, noise_seed=None):
        seeds.append(noise_seed)
        return real(obs, mag, config, return_samples, noise_seed)

    monkeypatch.setattr(driver, "measure_object", spy)
    assert main(["measure", str(d / "field_nbc.yaml"), "--out", str(d / "shear_nbc2.fits"), "--quiet", "-j", "1"]) == 0
    assert len(seeds) >= good.sum() and len({tuple(x) for x in seeds}) == len(seeds)
    assert all(x[0] == 0 and x[2] == 1 for x in seeds)   # metacal_seed's default, the noise-bias stream


def test_psf_ellipticity_is_the_sheared_gaussians_on_the_sky():
    """The PSF's ellipticity column: a Gaussian PSF sheared by g in the sky frame, drawn by GalSim through each
    exposure's Jacobian (plain, rotated by 30 degrees with 4 % shear, flipped), gives g back from its adaptive
    moments carried to the sky (to HSM's precision); and its FWHM column the Gaussian's, 2.3548 sigma."""
    import galsim

    from shearfit.pipeline.driver import psf_ellipticity, psf_fwhm_arcsec, psf_moments

    th = np.radians(30.0)
    rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    g, sigma = (0.06, -0.035), 0.3
    for J in (0.2 * np.eye(2), 0.2 * np.diag([1.04, 0.96]) @ rot, 0.2 * np.array([[-1.0, 0.0], [0.0, 1.0]])):
        wcs = galsim.JacobianWCS(*J.ravel())
        img = galsim.Gaussian(sigma=sigma).shear(g1=g[0], g2=g[1]).drawImage(
            nx=48, ny=48, wcs=wcs, method="no_pixel", use_true_center=False).array
        img /= img.sum()
        mom = psf_moments(img)
        e1, e2 = psf_ellipticity(img, J, moments=mom)
        assert abs(e1 - g[0]) < 2e-3 and abs(e2 - g[1]) < 2e-3, (J, e1, e2)
        # det(M_sky) = sigma_sky^4 for any shear: the FWHM of the sky Gaussian
        assert psf_fwhm_arcsec(J, moments=mom) == pytest.approx(2.3548 * sigma, rel=2e-3)


def test_psf_moments_do_not_depend_on_which_guess_came_first():
    """HSM's starting size moves its moments in the last bits (1e-9 here): an image's remembered moments are
    those of the guess asked for, whichever guess reached it first, so a catalogue's PSF columns are the same
    for any order of its objects (chunking, workers). Fails if the memo answers a guess with another's moments."""
    import galsim

    from shearfit.pipeline.driver import psf_moments

    img = galsim.Moffat(beta=3.0, fwhm=0.9).shear(g1=0.03, g2=-0.02).drawImage(
        nx=96, ny=96, scale=0.0625, method="no_pixel").array
    img /= img.sum()
    ones = galsim.ImageI(np.ones(img.shape, np.int32), scale=1.0)

    def direct(guess):
        m = galsim.hsm.FindAdaptiveMom(galsim.Image(img, scale=1.0), weight=ones, guess_sig=guess)
        return m.moments_sigma, (m.observed_shape.g1, m.observed_shape.g2)

    def shared():   # a given PSF image: read-only, so that its moments are remembered
        ro = img.copy()
        ro.setflags(write=False)
        return ro

    s = direct(5.0)[0]
    assert direct(s) != direct(5.0)            # the guess matters at this precision: the test can fail
    assert psf_moments(shared()) == direct(5.0)
    assert psf_moments(shared(), s) == direct(s)       # not the first guess's moments
    assert psf_moments(shared()) == direct(5.0)
    # a model's image at one object (writable, its own) is measured directly, with the same moments
    assert psf_moments(img.copy(), s) == direct(s)
    assert psf_moments(img.copy()) == direct(5.0)


def test_measure_field_holds_blas_to_one_thread(field, monkeypatch):
    """shearfit measure -j 1 (in this process) runs with one BLAS thread, as its workers do, and restores it."""
    from blasthreads import threads_set_to

    from shearfit.workers import thread_controls

    libs = thread_controls()
    if not libs:
        pytest.skip("no BLAS or OpenMP thread control found through /proc/self/maps (not Linux)")
    seen = []
    real = driver._measure_chunk

    def chunk(k):
        seen.append([get() for get, _ in libs])
        return real(k)

    monkeypatch.setattr(driver, "_measure_chunk", chunk)
    d, _ = field
    with threads_set_to(libs, 2):
        assert main(["measure", str(d / "field.yaml"), "--out", str(d / "shear_threads.fits"), "--quiet", "-j", "1"]) == 0
        after = [get() for get, _ in libs]
    assert seen and all(s == [1] * len(libs) for s in seen)
    assert after == [2] * len(libs)


def test_local_dask_workers_start_without_the_trim_threshold():
    """The local Dask cluster of `shearfit measure -j N` starts its workers without Dask's MALLOC_TRIM_THRESHOLD_
    (which made every chunk fault its temporary arrays' pages in again), with one BLAS thread and no profiler."""
    pytest.importorskip("distributed")
    from shearfit.pipeline.driver import local_cluster_config
    from shearfit.workers import SINGLE_THREAD_ENV

    cfg = local_cluster_config()
    env = cfg["distributed.nanny.pre-spawn-environ"]
    assert "MALLOC_TRIM_THRESHOLD_" not in env
    assert all(env[k] == v for k, v in SINGLE_THREAD_ENV.items())
    assert cfg["distributed.worker.profile.enabled"] is False


def test_given_psf_images_stay_read_only_through_pickling():
    """A Dask worker (or a spawned pool's) receives the exposures' PSFs pickled: the given images must come back as
    read-only arrays of their own, so that what is remembered by PSF image (HSM's moments, the Moffat, transforms)
    is found by it instead of being measured again for every object."""
    import pickle

    from shearfit.observation import is_immutable
    from shearfit.pipeline.driver import _ExposurePSF, _immutable

    psf = _ExposurePSF(images=[_immutable((np.eye(7), 1)), None])
    for got in (pickle.loads(pickle.dumps(psf, protocol=5)), pickle.loads(pickle.dumps(psf, protocol=2))):
        assert is_immutable(got.images[0][0]) and got.images[1] is None
        assert np.array_equal(got.images[0][0], np.eye(7)) and got.images[0][1] == 1
    distributed = pytest.importorskip("distributed.protocol")
    got = distributed.deserialize(*distributed.serialize(psf))
    assert is_immutable(got.images[0][0])

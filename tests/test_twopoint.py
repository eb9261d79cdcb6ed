"""shearfit xipm: TreeCorr two-point functions, the calibration term 1+K and its systematic covariance."""

import numpy as np
import pytest
import yaml
from astropy.io import fits
from astropy.table import Table

import galsim
import treecorr

from shearfit.calib.calibrate import calibration_samples
from shearfit.app.cli import main
from shearfit.errors import ShearfitIOError, ShearfitValueError
from shearfit.stats.twopoint import parse_selection, read_shear_catalog, xipm

RA0, DEC0 = 35.0, -4.0


def _sky(u, v):
    """Catalogue-frame offsets (arcsec; +u west, +v north: GalSim's project) to RA, Dec."""
    c = galsim.CelestialCoord(RA0 * galsim.degrees, DEC0 * galsim.degrees)
    pts = [c.deproject(a * galsim.arcsec, b * galsim.arcsec) for a, b in zip(u, v)]
    return np.array([p.ra.deg for p in pts]), np.array([p.dec.deg for p in pts])


def test_catalogue_convention_is_treecorrs():
    """A pattern tangential in the catalogue frame is a positive tangential shear for TreeCorr."""
    rng = np.random.default_rng(1)
    u, v = rng.uniform(-600, 600, (2, 3000))
    ra, dec = _sky(u, v)
    e = -0.1 * np.exp(2j * np.arctan2(v, u))
    src = treecorr.Catalog(ra=ra, dec=dec, ra_units="deg", dec_units="deg", g1=e.real, g2=e.imag)
    lens = treecorr.Catalog(ra=[RA0], dec=[DEC0], ra_units="deg", dec_units="deg")
    ng = treecorr.NGCorrelation(min_sep=1, max_sep=10, nbins=3, sep_units="arcmin")
    ng.process(lens, src)
    np.testing.assert_allclose(ng.xi, 0.1, atol=1e-3)
    np.testing.assert_allclose(ng.xi_im, 0.0, atol=1e-3)


def _field(n=3000, seed=2, m_range=(-0.2, 0.0)):
    rng = np.random.default_rng(seed)
    ps = galsim.PowerSpectrum(e_power_function=lambda k: 1e-4 * (np.maximum(k, 1e-3) / 1e-3) ** -1.2,
                              units=galsim.arcsec)
    ps.buildGrid(grid_spacing=30.0, ngrid=160, rng=galsim.BaseDeviate(seed), center=galsim.PositionD(0, 0))
    u, v = rng.uniform(-2000, 2000, (2, n))
    g1, g2 = ps.getShear([galsim.PositionD(a, b) for a, b in zip(u, v)])
    scale = 0.03 / np.sqrt(np.mean(np.asarray(g1) ** 2 + np.asarray(g2) ** 2) / 2)   # shear rms 0.03
    g1, g2 = scale * np.asarray(g1), scale * np.asarray(g2)
    ra, dec = _sky(u, v)
    m = rng.uniform(*m_range, n)
    w = rng.uniform(0.5, 1.5, n)
    tab = Table({"id": np.arange(n), "ra": ra, "dec": dec, "e1": (1 + m) * g1, "e2": (1 + m) * g2, "weight": w,
                 "fitclass": np.zeros(n, int), "m": m, "snr": rng.uniform(8, 80, n),
                 "scalelength": rng.uniform(0.1, 1.0, n), "z": rng.uniform(0, 1.5, n)})
    return tab, np.asarray(g1), np.asarray(g2)


def test_calibrated_xip_is_the_input_fields():
    """e = (1 + m) g: dividing by 1 + K recovers the xi+ of the input shears; the raw one is low by ~2 <m>."""
    tab, g1, g2 = _field()
    out, cov = xipm(tab, min_sep=2.0, max_sep=40.0, nbins=6)
    assert cov is None
    ref = treecorr.GGCorrelation(min_sep=2.0, max_sep=40.0, nbins=6, sep_units="arcmin")
    ref.process(treecorr.Catalog(ra=tab["ra"], dec=tab["dec"], ra_units="deg", dec_units="deg", g1=g1, g2=g2,
                                 w=tab["weight"]))
    np.testing.assert_allclose(out["xip"], ref.xip, rtol=0.03)
    assert np.all(np.abs(out["xip_raw"]) < 0.9 * np.abs(ref.xip))
    np.testing.assert_allclose(out["one_plus_k"], np.mean(1 + tab["m"]) ** 2, rtol=0.01)
    assert set(("theta", "xip", "xim", "xip_raw", "xim_raw", "one_plus_k", "sigma_xip", "sigma_xim",
                "npairs")) <= set(out.colnames)


def _calibration_file(path, a0=0.05, b0=-0.4):
    ga = np.linspace(a0 - 0.05, a0 + 0.05, 21)
    gb = np.linspace(b0 - 0.2, b0 + 0.2, 21)
    A, B = np.meshgrid(ga, gb, indexing="ij")
    ll = -0.5 * (((A - a0) / 0.01) ** 2 + ((B - b0) / 0.04) ** 2)
    path.write_text(yaml.safe_dump({"alpha": a0, "beta": b0, "grid_alpha": ga.tolist(), "grid_beta": gb.tolist(),
                                    "loglike": ll.tolist()}))
    return path


def test_calibration_samples_follow_the_likelihood(tmp_path):
    a, b = calibration_samples(_calibration_file(tmp_path / "cal.yaml"), 4000, np.random.default_rng(0))
    assert np.mean(a) == pytest.approx(0.05, abs=1e-3) and np.std(a) == pytest.approx(0.01, rel=0.1)
    assert np.mean(b) == pytest.approx(-0.4, abs=4e-3) and np.std(b) == pytest.approx(0.04, rel=0.1)
    bad = tmp_path / "bad.yaml"
    bad.write_text("alpha: 0.05\nbeta: -0.4\n")
    with pytest.raises(ShearfitIOError, match="likelihood grid"):
        calibration_samples(bad, 10, np.random.default_rng(0))


def test_systematic_covariance_from_the_calibration(tmp_path):
    tab, _, _ = _field(n=1500)
    cal = _calibration_file(tmp_path / "cal.yaml")
    out, cov = xipm(tab, min_sep=2.0, max_sep=40.0, nbins=4, calibration=str(cal), n_sys=40)
    assert cov.shape == (8, 8)
    sig = np.sqrt(np.diag(cov))
    # the calibration's 20 % uncertainty on beta moves xi_cal by a few per cent: far above zero, below 20 %
    rel = sig[:4] / np.abs(out["xip"])
    assert np.all(rel > 1e-3) and np.all(rel < 0.2)
    # the xi+ bins move together (one calibration for all): strongly correlated
    corr = cov[:4, :4] / np.outer(sig[:4], sig[:4])
    assert np.min(np.abs(corr)) > 0.8


def test_selection_and_errors(tmp_path):
    tab, _, _ = _field(n=400)
    tab["fitclass"][:10] = -3
    p = tmp_path / "shear.fits"
    tab.write(p)
    sel = read_shear_catalog(p, [parse_selection("z:0.5:1.0")])
    z = np.asarray(tab["z"])
    assert len(sel) == int(np.sum((z >= 0.5) & (z < 1.0) & (np.arange(len(tab)) >= 10)))
    with pytest.raises(ShearfitValueError, match="COLUMN:MIN:MAX"):
        parse_selection("z:0.5")
    with pytest.raises(ShearfitIOError, match="'zphot'"):
        read_shear_catalog(p, [("zphot", 0, 1)])
    t2 = tab.copy()
    t2.remove_column("weight")
    t2.write(tmp_path / "noweight.fits")
    with pytest.raises(ShearfitIOError, match="no column 'weight'"):
        read_shear_catalog(tmp_path / "noweight.fits")


def test_cli(tmp_path, capsys):
    tab, _, _ = _field(n=600)
    p = tmp_path / "shear.fits"
    tab.write(p)
    cal = _calibration_file(tmp_path / "cal.yaml")
    out = tmp_path / "xipm.fits"
    assert main(["xipm", str(p), "--out", str(out), "--min-sep", "2", "--max-sep", "30", "--nbins", "3",
                 "--calibration", str(cal), "--n-sys", "10", "--select", "snr:10:"]) == 0
    assert "xi+" in capsys.readouterr().out
    with fits.open(out) as h:
        assert len(h["XIPM"].data) == 3 and h["SYSCOV"].data.shape == (6, 6)
        assert h["XIPM"].header["NGAL"] == int(np.sum(tab["snr"] >= 10))
    # bins wider than the field are named as empty, not printed as NaN
    assert main(["xipm", str(p), "--out", str(tmp_path / "x3.fits"), "--min-sep", "2", "--max-sep", "5000",
                 "--nbins", "4"]) == 0
    text = capsys.readouterr().out
    assert "no pairs" in text and "nan" not in text.lower()
    assert main(["xipm", str(p), "--out", str(tmp_path / "x2.fits"), "--min-sep", "5", "--max-sep", "2"]) != 0
    assert not (tmp_path / "x2.fits").exists()

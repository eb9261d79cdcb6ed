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
from shearfit.stats.twopoint import DEFAULT_ANGLE_SLOP, parse_selection, read_shear_catalog, xipm

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
    ref = treecorr.GGCorrelation(min_sep=2.0, max_sep=40.0, nbins=6, sep_units="arcmin", bin_slop=0,
                               angle_slop=DEFAULT_ANGLE_SLOP)   # xipm's default
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
    # another column of weights: it becomes 'weight', lensfit's is kept beside it
    with pytest.raises(ShearfitIOError, match="no column 'iso_weight'"):
        read_shear_catalog(p, weight_column="iso_weight")
    t3 = tab.copy()
    t3["iso_weight"] = np.where(np.arange(len(t3)) % 2 == 0, 2.0, 0.0)
    t3.write(tmp_path / "iso.fits")
    iso = read_shear_catalog(tmp_path / "iso.fits", weight_column="iso_weight")
    assert len(iso) == int(np.sum(np.arange(10, len(t3)) % 2 == 0)) and np.all(iso["weight"] == 2.0)
    np.testing.assert_array_equal(iso["lensfit_weight"], t3["weight"][10::2])
    t3["weight_1p"] = t3["weight"]
    t3.write(tmp_path / "mcal.fits")
    with pytest.raises(ShearfitValueError, match="metacal catalogue"):
        read_shear_catalog(tmp_path / "mcal.fits", weight_column="iso_weight")


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


def _two_bin_catalogue(tmp_path, n=1200, seed=5):
    """One shear field, two redshift bins (z below / above 0.75) with a different m each (-0.2 and -0.05)."""
    tab, g1, g2 = _field(n=n, seed=seed)
    hi = np.asarray(tab["z"]) >= 0.75
    tab["m"] = np.where(hi, -0.05, -0.2)
    tab["e1"], tab["e2"] = (1 + tab["m"]) * g1, (1 + tab["m"]) * g2
    tab["zbin"] = hi.astype(int)
    p = tmp_path / "shear.fits"
    tab.write(p)
    return p, tab, g1, g2


XI_ARGS = ["--min-sep", "2", "--max-sep", "30", "--nbins", "4", "--quiet"]


def test_tomographic_bins_every_pair_with_its_header(tmp_path):
    p, tab, _, _ = _two_bin_catalogue(tmp_path, n=900)
    tab["zbin"] = np.digitize(tab["z"], [0.5, 1.0])          # three bins: 0, 1, 2
    tab.write(p, overwrite=True)
    out = tmp_path / "xi.fits"
    assert main(["xipm", str(p), "--out", str(out), "--bins", "zbin:0,1,2,3", *XI_ARGS]) == 0
    counts = [int(np.sum(tab["zbin"] == k)) for k in range(3)]
    with fits.open(out) as h:
        names = [x.name for x in h[1:]]
        assert names == ["XIPM_0_0", "XIPM_0_1", "XIPM_0_2", "XIPM_1_1", "XIPM_1_2", "XIPM_2_2"]
        assert h[0].header["BINCOL"] == "zbin" and h[0].header["NTOMO"] == 3
        for name in names:
            i, j = (int(x) for x in name.split("_")[1:])
            hd = h[name].header
            assert hd["PAIR"] == f"{i}_{j}" and (hd["BIN1"], hd["BIN2"]) == (i, j) and hd["BINCOL"] == "zbin"
            assert (hd["BIN1LO"], hd["BIN1HI"], hd["BIN2LO"], hd["BIN2HI"]) == (i, i + 1, j, j + 1)
            assert (hd["NGAL1"], hd["NGAL2"]) == (counts[i], counts[j])
            assert hd["CALIB"] == "catalogue m column"
            assert {"theta", "xip", "xim", "xip_raw", "xim_raw", "one_plus_k", "sigma_xip", "sigma_xim",
                    "npairs"} <= set(h[name].columns.names)
            assert len(h[name].data) == 4


def test_auto_pair_is_the_selected_bins_run(tmp_path):
    """XIPM_1_1 of --bins is, number for number, a --select run on that bin; --select applies before --bins."""
    p, tab, _, _ = _two_bin_catalogue(tmp_path)
    a, b = tmp_path / "bins.fits", tmp_path / "sel.fits"
    assert main(["xipm", str(p), "--out", str(a), "--bins", "z:0,0.75,1.5", "--select", "snr:20:", *XI_ARGS]) == 0
    assert main(["xipm", str(p), "--out", str(b), "--select", "z:0.75:1.5", "--select", "snr:20:", *XI_ARGS]) == 0
    with fits.open(a) as ha, fits.open(b) as hb:
        assert [x.name for x in hb] == ["PRIMARY", "XIPM"]      # without --bins: as before
        for col in ("theta", "xip", "xim", "xip_raw", "xim_raw", "one_plus_k", "sigma_xip", "sigma_xim", "npairs"):
            # the same up to TreeCorr's threaded summation order
            np.testing.assert_allclose(ha["XIPM_1_1"].data[col], hb["XIPM"].data[col], rtol=1e-12, atol=1e-18)
        assert ha["XIPM_1_1"].header["NGAL1"] == hb["XIPM"].header["NGAL"]
        assert hb["XIPM"].header["NGAL"] == int(np.sum((tab["z"] >= 0.75) & (tab["snr"] >= 20)))


def test_cross_pair_of_one_shear_field(tmp_path):
    """Two bins of the same (noise-free) shear field: the cross pair's 1 + K is (1 + m_0)(1 + m_1), its calibrated
    xi+- is TreeCorr's cross-correlation of the two bins' true shears, and all three pairs measure the field's xi+."""
    p, tab, g1, g2 = _two_bin_catalogue(tmp_path, n=3000)
    out = tmp_path / "xi.fits"
    assert main(["xipm", str(p), "--out", str(out), "--bins", "zbin:0,1,2", *XI_ARGS]) == 0
    cfg = dict(min_sep=2.0, max_sep=30.0, nbins=4, sep_units="arcmin", bin_slop=0, angle_slop=DEFAULT_ANGLE_SLOP)

    def cat(s):
        return treecorr.Catalog(ra=tab["ra"][s], dec=tab["dec"][s], ra_units="deg", dec_units="deg", g1=g1[s],
                                g2=g2[s], w=tab["weight"][s])

    ref, cross = treecorr.GGCorrelation(**cfg), treecorr.GGCorrelation(**cfg)
    ref.process(cat(np.ones(len(tab), bool)))
    cross.process(cat(tab["zbin"] == 0), cat(tab["zbin"] == 1))
    with fits.open(out) as h:
        x = {k: Table(h[f"XIPM_{k}"].data) for k in ("0_0", "0_1", "1_1")}
    np.testing.assert_allclose(x["0_0"]["one_plus_k"], 0.8 ** 2, rtol=1e-7)
    np.testing.assert_allclose(x["1_1"]["one_plus_k"], 0.95 ** 2, rtol=1e-7)
    np.testing.assert_allclose(x["0_1"]["one_plus_k"], 0.8 * 0.95, rtol=1e-7)
    np.testing.assert_allclose(x["0_1"]["xip"], cross.xip, rtol=1e-6)
    np.testing.assert_allclose(x["0_1"]["xim"], cross.xim, rtol=1e-6)
    np.testing.assert_allclose(x["0_1"]["npairs"], cross.npairs)
    for k in ("0_0", "0_1", "1_1"):
        np.testing.assert_allclose(x[k]["xip"], ref.xip, atol=0.1 * np.max(np.abs(ref.xip)))


def test_jackknife_covariance_and_plot(tmp_path):
    p, tab, _, _ = _two_bin_catalogue(tmp_path, n=1500)
    tab["e1"] += np.random.default_rng(3).normal(0, 0.26, len(tab))
    tab["e2"] += np.random.default_rng(4).normal(0, 0.26, len(tab))
    tab.write(p, overwrite=True)
    out, png = tmp_path / "xi.fits", tmp_path / "xi.png"
    assert main(["xipm", str(p), "--out", str(out), "--bins", "zbin:0,1,2", "--patches", "6", "--plot", str(png),
                 *XI_ARGS]) == 0
    with fits.open(out) as h:
        cov = h["COV"].data
        assert cov.shape == (3 * 2 * 4, 3 * 2 * 4)
        hc = h["COV"].header
        assert hc["NPATCH"] == 6 and hc["NTHETA"] == 4 and hc["NPAIRBIN"] == 3
        assert [hc[f"PAIR{k}"] for k in range(3)] == ["0_0", "0_1", "1_1"]
        for k, name in enumerate(("XIPM_0_0", "XIPM_0_1", "XIPM_1_1")):
            d = h[name].data
            blk = np.diag(cov)[8 * k:8 * (k + 1)]
            np.testing.assert_allclose(blk[:4], d["sigma_xip_jk"] ** 2, rtol=1e-12)
            np.testing.assert_allclose(blk[4:], d["sigma_xim_jk"] ** 2, rtol=1e-12)
            # the jackknife errors are of the shape noise's size (a few patches: a loose check)
            assert np.all(d["sigma_xip_jk"] > 0.2 * d["sigma_xip"]) and np.all(d["sigma_xip_jk"] < 5 * d["sigma_xip"])
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # seeded patches: the same covariance again; one sample: COV of (xip, xim) and the columns in XIPM
    out2 = tmp_path / "one.fits"
    assert main(["xipm", str(p), "--out", str(out2), "--patches", "6", *XI_ARGS]) == 0
    with fits.open(out2) as h:
        assert h["COV"].data.shape == (8, 8) and "sigma_xim_jk" in h["XIPM"].columns.names
        np.testing.assert_allclose(np.diag(h["COV"].data)[:4], h["XIPM"].data["sigma_xip_jk"] ** 2, rtol=1e-12)


@pytest.mark.parametrize("spec, needle", [("zphot:0,1", "'zphot'"), ("z:0.5,0.2", "'z:0.5,0.2'"),
                                          ("z:0,0.5,0.5", "'z:0,0.5,0.5'"), ("z", "'z'"), ("z:0,a", "'z:0,a'")])
def test_bad_bins_spec_is_a_one_line_error(tmp_path, capsys, spec, needle):
    tab, _, _ = _field(n=100)
    p = tmp_path / "shear.fits"
    tab.write(p)
    out = tmp_path / "xi.fits"
    assert main(["xipm", str(p), "--out", str(out), "--bins", spec, *XI_ARGS]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("shearfit: error:") and needle in err and "\n" not in err
    assert not out.exists() and list(tmp_path.iterdir()) == [p]

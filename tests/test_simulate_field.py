"""``shearfit simulate``: presets, reproducibility, truth, defects in the weights, the second suite."""

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

galsim = pytest.importorskip("galsim")

from shearfit.app.cli import main  # noqa: E402
from shearfit.errors import ShearfitValueError  # noqa: E402
from shearfit.simulate.field import PRESETS, simulate_field, simulation_config  # noqa: E402


def test_config_presets_and_errors():
    assert simulation_config().suite == "great"
    for name in PRESETS:
        simulation_config({"preset": name})
    assert simulation_config({"preset": "second"}).n_exposures == 1
    with pytest.raises(ShearfitValueError, match="unknown simulation key 'shaer'"):
        simulation_config({"shaer": [0.1, 0]})
    with pytest.raises(ShearfitValueError, match="preset"):
        simulation_config({"preset": "huge"})
    with pytest.raises(ShearfitValueError, match="suite"):
        simulation_config({"suite": "third"})


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    sc = simulation_config({"preset": "tiny", "seed": 7, "shear_rms": 0.05})
    res = simulate_field(sc, d / "a")
    return sc, res, d


def test_field_files_and_truth(tiny):
    sc, res, d = tiny
    a = d / "a"
    for name in ("exp0.fits", "exp2.weight.fits", "exp1.psf.fits", "objects.fits", "stars.fits", "truth.fits",
                 "field.yaml", "field_truepsf.yaml", "simulation.yaml"):
        assert (a / name).exists(), name
    t = Table.read(a / "truth.fits")
    for col in ("id", "ra", "dec", "mag", "g1", "g2", "e1_int", "e2_int", "scalelength", "bulge_fraction",
                "is_star", "snr"):
        assert col in t.colnames
    assert t.meta["SEED"] == 7
    gal = t[~t["is_star"]]
    assert len(gal) == res["n_galaxies"] and np.sum(t["is_star"]) == res["n_stars"] > 8
    # a shear field: the shear varies, with about the requested rms
    assert 0.02 < np.sqrt(np.mean(gal["g1"] ** 2 + gal["g2"] ** 2) / 2) < 0.1
    # 90-degree pairs: consecutive galaxies have opposite intrinsic ellipticity and the same size
    assert np.allclose(gal["e1_int"][1::2], -gal["e1_int"][0::2][: len(gal) // 2])
    assert np.allclose(gal["scalelength"][1::2], gal["scalelength"][0::2][: len(gal) // 2])
    # PSF given 3x oversampled, normalised
    with fits.open(a / "exp0.psf.fits") as h:
        assert h[1].header["OVERSAMP"] == 3 and h[1].data.sum() == pytest.approx(1.0)


def test_snr_is_the_five_pixel_aperture_snr(tiny):
    sc, res, d = tiny
    t = Table.read(d / "a" / "truth.fits")
    g = t[~t["is_star"]]
    # independent check for one galaxy: redraw it without noise through exposure 0's WCS
    from shearfit.simulate.stamps import galaxy_profile, mag_to_flux
    from shearfit.simulate import field as F

    i = int(np.argmax(g["snr"]))
    row = g[i]
    h = fits.getheader(d / "a" / "exp0.fits", 1)
    wcs = galsim.GSFitsWCS(header=h)
    pos = wcs.toImage(galsim.CelestialCoord(row["ra"] * galsim.degrees, row["dec"] * galsim.degrees))
    assert 1 <= pos.x <= sc.ccd_nx and 1 <= pos.y <= sc.ccd_ny
    assert 3 < row["snr"] < 1e4
    prof = galaxy_profile(row["scalelength"], row["bulge_fraction"], row["e1_int"], row["e2_int"],
                          flux=mag_to_flux(row["mag"]), g1=row["g1"], g2=row["g2"], is_bulge=bool(row["is_bulge"]))
    # the PSF differs per exposure: compare the aperture flux with the flux, not the exact SNR
    stamp = prof.drawImage(wcs=wcs.local(pos), nx=64, ny=64, center=pos, method="no_pixel")
    assert F._aperture_sum(stamp, pos) < mag_to_flux(row["mag"])


def test_same_seed_same_field_and_defects_in_weights(tiny, tmp_path):
    sc, res, d = tiny
    res2 = simulate_field(sc, tmp_path / "b")
    with fits.open(d / "a" / "exp1.fits") as h1, fits.open(tmp_path / "b" / "exp1.fits") as h2:
        assert np.array_equal(h1[1].data, h2[1].data)
    with fits.open(d / "a" / "exp0.weight.fits") as w:
        wt = w[1].data
    bad = wt == 0
    assert bad.any() and bad.mean() < 0.05
    assert res2["n_galaxies"] == res["n_galaxies"]


def test_second_suite_cli(tmp_path, capsys):
    cfg = tmp_path / "sim.yaml"
    cfg.write_text("preset: second-small\nccd_nx: 200\nccd_ny: 200\ngalaxy_density: 80\nstar_density: 30\n")
    assert main(["simulate", str(cfg), "--out", str(tmp_path / "s"), "--seed", "3"]) == 0
    assert "second field" in capsys.readouterr().out
    t = Table.read(tmp_path / "s" / "truth.fits")
    assert t.meta["SUITE"] == "second" and t.meta["SEED"] == 3
    assert len(fits.open(tmp_path / "s" / "exp0.fits")) == 2       # one exposure, one CCD
    assert not (tmp_path / "s" / "exp1.fits").exists()


def test_simulate_bad_config_is_one_line(tmp_path, capsys):
    cfg = tmp_path / "sim.yaml"
    cfg.write_text("preset: small\nn_exposures: 0\n")
    assert main(["simulate", str(cfg), "--out", str(tmp_path / "x")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "n_exposures" in err


def test_field_demo_end_to_end(tmp_path):
    """The demo's whole chain (simulate +g/-g, PSF from stars, measure, match, m and c) on the tiny preset."""
    import io

    from shearfit.app.demo import run_field_demo

    buf = io.StringIO()
    s = run_field_demo(out_dir=tmp_path / "demo", processes=2, preset="tiny", stream=buf)
    text = buf.getvalue()
    assert "input shear" in text and "multiplicative" in text and str(tmp_path / "demo") in text
    assert s["n_galaxies"] >= 12
    # bright galaxies (mag 20-23), true shear 0.04 / -0.03: the raw m is small, within a loose bound
    assert all(abs(m) < 0.3 for m in s["m"]) and all(e > 0 for e in s["m_err"])
    assert (tmp_path / "demo" / "field_plus" / "shear.fits").exists()


def test_coherent_psf_anisotropy_keeps_the_rest_of_the_field():
    """psf_e_fixed sets every exposure's PSF ellipticity and draws nothing else differently."""
    from shearfit.simulate.field import _exposure_psf

    a = simulation_config({"seed": 3})
    b = simulation_config({"seed": 3, "psf_e_fixed": [0.1, -0.02]})
    ra, rb = np.random.default_rng(5), np.random.default_rng(5)
    pa, pb = _exposure_psf(a, ra), _exposure_psf(b, rb)
    assert (pb["e1"], pb["e2"]) == (0.1, -0.02)
    assert pa["fwhm"] == pb["fwhm"] and ra.uniform() == rb.uniform()
    with pytest.raises(ShearfitValueError, match="psf_e_fixed"):
        simulation_config({"psf_e_fixed": [0.6, 0.0]})


def test_exposure_rotation_turns_each_exposures_pixel_grid():
    """exposure_rotation turns each exposure's pixel grid on the sky by a normal deviate of that rms (degrees),
    the same for all its CCDs, keeping the pixel scale: no two exposures then share a Jacobian. 0 (the default)
    leaves every exposure aligned, header for header as before the key existed."""
    from shearfit.simulate.field import _ccd_header

    plain = simulation_config({"seed": 4})
    h0 = _ccd_header(plain, 1, 3)
    assert (h0["CD1_2"], h0["CD2_1"]) == (0.0, 0.0) and h0["CD1_1"] == -h0["CD2_2"]
    turned = simulation_config({"seed": 4, "exposure_rotation": 1.0})
    angles = []
    for k in range(400):
        cds = [np.array([[h["CD1_1"], h["CD1_2"]], [h["CD2_1"], h["CD2_2"]]])
               for h in (_ccd_header(turned, c, k) for c in range(2))]
        assert np.array_equal(cds[0], cds[1])                       # one turn per exposure
        r = cds[0] @ np.linalg.inv(np.array([[h0["CD1_1"], 0.0], [0.0, h0["CD2_2"]]]))
        np.testing.assert_allclose(r @ r.T, np.eye(2), atol=1e-12)   # a rotation: the pixel scale kept
        angles.append(np.degrees(np.arctan2(r[1, 0], r[0, 0])))
    angles = np.array(angles)
    assert np.unique(angles).size == angles.size
    # rms 1 degree: 400 deviates put the sample rms within 0.1 of it (its error is 0.035)
    assert abs(np.sqrt(np.mean(angles ** 2)) - 1.0) < 0.1 and abs(np.mean(angles)) < 0.15
    with pytest.raises(ShearfitValueError, match="exposure_rotation"):
        simulation_config({"exposure_rotation": 20})


def test_antithetic_twin_reverses_only_the_noise(tmp_path):
    """noise_sign: -1 writes the same field with the pixel noise negated, everything else equal."""
    base = {"preset": "tiny", "seed": 11, "ccd_nx": 160, "ccd_ny": 160, "n_exposures": 1}
    simulate_field(simulation_config(base), tmp_path / "p")
    simulate_field(simulation_config(dict(base, noise_sign=-1)), tmp_path / "n")
    tp, tn = Table.read(tmp_path / "p" / "truth.fits"), Table.read(tmp_path / "n" / "truth.fits")
    assert tp.meta["NOISESGN"] == 1 and tn.meta["NOISESGN"] == -1 and tn.meta["SIGMA"] == tp.meta["SIGMA"]
    for c in ("e1_int", "scalelength", "snr", "ra"):
        assert np.array_equal(tp[c], tn[c])
    a, b = fits.getdata(tmp_path / "p" / "exp0.fits", 1), fits.getdata(tmp_path / "n" / "exp0.fits", 1)
    wa, wb = fits.getdata(tmp_path / "p" / "exp0.weight.fits", 1), fits.getdata(tmp_path / "n" / "exp0.weight.fits", 1)
    assert np.array_equal(wa, wb)                       # the same defects
    sigma = tp.meta["SIGMA"]
    # the twins differ by twice the Gaussian noise drawn for (seed, exposure 0, CCD 0), to float32 rounding
    noise = np.random.default_rng([11, 0, 0]).normal(0.0, sigma, a.shape)
    scale = np.abs(a).max()
    assert np.max(np.abs((a.astype(float) - b) - 2 * noise)) < 1e-6 * scale
    assert abs(np.std(a.astype(float) - b) / (2 * sigma) - 1) < 0.02
    # noise_sign: 0, the same field without its noise: the mean of the twins, the same weights
    simulate_field(simulation_config(dict(base, noise_sign=0)), tmp_path / "z")
    z = fits.getdata(tmp_path / "z" / "exp0.fits", 1)
    assert Table.read(tmp_path / "z" / "truth.fits").meta["NOISESGN"] == 0
    assert np.max(np.abs(z - 0.5 * (a.astype(float) + b))) < 1e-6 * scale
    assert np.array_equal(fits.getdata(tmp_path / "z" / "exp0.weight.fits", 1), wa)
    with pytest.raises(ShearfitValueError, match="noise_sign"):
        simulation_config({"noise_sign": 2})


def test_truth_galaxies(tiny, tmp_path):
    """truth_galaxies: a field's galaxies (no stars) within a magnitude range, sorted, with their intrinsic
    ellipticities; a table that is not a truth table is named."""
    from shearfit.simulate.field import truth_galaxies

    sc, res, d = tiny
    t = Table.read(d / "a" / "truth.fits")
    gal = truth_galaxies([d / "a" / "truth.fits"], (21.0, 22.5))
    sel = ~np.asarray(t["is_star"]) & (t["mag"] >= 21.0) & (t["mag"] <= 22.5)
    assert gal["mag"].size == sel.sum() > 2 and np.all(np.diff(gal["mag"]) >= 0)
    assert sorted(gal["e1"]) == sorted(np.asarray(t["e1_int"])[sel])
    Table({"id": [1]}).write(tmp_path / "x.fits")
    with pytest.raises(ShearfitValueError, match="x.fits: no column mag"):
        truth_galaxies([tmp_path / "x.fits"])


def test_an_interrupted_field_has_no_truth_and_is_simulated_again(tmp_path, monkeypatch):
    """truth.fits is written last: simulate_missing (resumable suites) takes a field with one as whole."""
    from shearfit.simulate import field as field_mod

    write = field_mod._write_text

    def killed(path, text):
        if str(path).endswith("simulation.yaml"):
            raise KeyboardInterrupt
        write(path, text)

    monkeypatch.setattr(field_mod, "_write_text", killed)
    mapping = {"preset": "tiny", "seed": 7}
    with pytest.raises(KeyboardInterrupt):
        field_mod.simulate_missing((str(tmp_path / "f"), mapping))
    assert (tmp_path / "f" / "field.yaml").exists() and not (tmp_path / "f" / "truth.fits").exists()
    monkeypatch.setattr(field_mod, "_write_text", write)
    field_mod.simulate_missing((str(tmp_path / "f"), mapping))
    assert (tmp_path / "f" / "truth.fits").exists() and (tmp_path / "f" / "simulation.yaml").exists()

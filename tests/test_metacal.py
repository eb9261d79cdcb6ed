"""Metacalibration on the lensfit engine: versions, response, noise symmetry, selection response, pipeline."""

from dataclasses import replace

import numpy as np
import pytest
from astropy.table import Table

import shearfit
from shearfit.errors import FITCLASS_GALAXY
from shearfit.calib.metacal import (E_GRID_MIN, REPLAY_FIRST_MARGIN, ensemble_response, measure_metacal,
                                    metacal_observations, metacal_shear)
from shearfit.simulate.metacal_check import QuietNormal
from shearfit.simulate.stamps import draw_psf_image, draw_stamp, galaxy_profile, moffat_psf, noise_for_snr

PIX = 0.187


def _obs(r, e, snr=None, n_exp=3, J=None, seed=0, g=(0.0, 0.0)):
    rng = np.random.default_rng(seed)
    J = PIX * np.array([[-1.0, 0.0], [0.0, 1.0]]) if J is None else J
    offs = rng.uniform(-0.5, 0.5, (n_exp, 2))
    psfs = [moffat_psf(0.6 + 0.05 * i, 3.0, 0.04 * (-1) ** i, 0.03) for i in range(n_exp)]
    gal = galaxy_profile(r, 0.1, e[0], e[1], flux=1000.0, g1=g[0], g2=g[1])
    ims = [draw_stamp(gal, p, J, o) for p, o in zip(psfs, offs)]
    sig = noise_for_snr(ims, snr) if snr else noise_for_snr(ims, 300.0)   # noise-free, SNR-300 weights
    return [shearfit.Observation(image=im + (rng.normal(0, sig, im.shape) if snr else 0.0),
                                 weight=np.full(im.shape, 1 / sig ** 2), psf=draw_psf_image(p, J, size=25),
                                 jacobian=J, offset=tuple(o)) for im, p, o in zip(ims, psfs, offs)]


@pytest.mark.parametrize("J", [None, PIX * np.array([[0.6, -0.8], [0.8, 0.6]])])
def test_noise_free_response_is_the_identity_in_the_sky_frame(J):
    """A resolved noise-free galaxy: the noshear fit is the plain fit, and R = de/dg is the analytic response
    of its ellipticity to a shear (lensfit is unbiased there), also on a rotated pixel grid: the metacal
    shear acts in the catalogue's (u, v) frame."""
    obs = _obs(0.45, (0.25, -0.1), J=J)
    plain = shearfit.measure_object(obs, 22.0)
    Rs = []
    for seed in range(6):
        mc = measure_metacal(obs, 22.0, rng=np.random.default_rng(seed))
        n = mc.noshear
        assert n.fitclass == FITCLASS_GALAXY
        # the same up to the symmetrising noise added at the weights' level (SNR 300 here)
        assert abs(n.e1 - plain.e1) < 0.03 and abs(n.e2 - plain.e2) < 0.03
        # the sheared versions move the estimate the way a shear of delta does
        assert mc.results["1p"].e1 > n.e1 > mc.results["1m"].e1
        assert mc.results["2p"].e2 > n.e2 > mc.results["2m"].e2
        Rs.append(mc.R)
    # a shear g takes e to (e + g) / (1 + g* e), so de = dg - e^2 dg*: with e^2 = a + ib,
    # R = [[1 - a, -b], [-b, 1 + a]] for one galaxy (the identity only on average over orientations)
    e2 = complex(0.25, -0.1) ** 2
    expected = np.array([[1 - e2.real, -e2.imag], [-e2.imag, 1 + e2.real]])
    Rs = np.array(Rs)
    err = Rs.std(axis=0, ddof=1) / np.sqrt(len(Rs))
    assert np.all(np.abs(Rs.mean(axis=0) - expected) < 3 * err + 0.005), (Rs.mean(axis=0), err, expected)


def test_symmetrised_noise_has_no_preferred_direction():
    """On pure noise, the 1p version's noise correlates equally along x and y (the rotated field's job);
    without it the shear's anisotropy shows."""
    J = PIX * np.array([[-1.0, 0.0], [0.0, 1.0]])
    psf = draw_psf_image(moffat_psf(0.7, 3.0), J, size=25)
    rng = np.random.default_rng(3)
    cx, cy = [], []
    for _ in range(60):
        im = rng.normal(0, 1.0, (48, 48))
        o = shearfit.Observation(image=im, weight=np.ones((48, 48)), psf=psf, jacobian=J)
        v = metacal_observations(o, delta=0.2, rng=rng, versions=("1p",))["1p"]
        a = v.image[6:-6, 6:-6]
        a = a - a.mean()
        cx.append(np.mean(a[:, 1:] * a[:, :-1]) / np.mean(a * a))
        cy.append(np.mean(a[1:, :] * a[:-1, :]) / np.mean(a * a))
    d = np.array(cx) - np.array(cy)
    assert abs(d.mean()) < 3 * d.std() / np.sqrt(d.size) + 2e-3
    # the unsymmetrised part alone (the processed image, without the added field) is anisotropic
    ux, uy = [], []
    for _ in range(30):
        im = rng.normal(0, 1.0, (48, 48))
        o = shearfit.Observation(image=im, weight=np.ones((48, 48)), psf=psf, jacobian=J)
        both = metacal_observations(o, delta=0.2, rng=np.random.default_rng(7), versions=("1p",))["1p"].image
        added = metacal_observations(shearfit.Observation(image=np.zeros((48, 48)), weight=np.ones((48, 48)),
                                                          psf=psf, jacobian=J), delta=0.2,
                                     rng=np.random.default_rng(7), versions=("1p",))["1p"].image
        a = (both - added)[6:-6, 6:-6]
        ux.append(np.mean(a[:, 1:] * a[:, :-1]) / np.mean(a * a))
        uy.append(np.mean(a[1:, :] * a[:-1, :]) / np.mean(a * a))
    du = np.array(ux) - np.array(uy)
    assert abs(du.mean()) > 5 * du.std() / np.sqrt(du.size)


def test_weights_scale_with_the_processed_noise_and_masks_grow():
    obs = _obs(0.3, (0.1, 0.1), snr=30, n_exp=1)[0]
    w = np.array(obs.weight)
    w[20, 30] = 0.0
    o = shearfit.Observation(image=obs.image, weight=w, psf=obs.psf, jacobian=obs.jacobian)
    v = metacal_observations(o, rng=np.random.default_rng(0))
    for name, ob in v.items():
        assert ob.weight[20, 30] == 0 and ob.weight[21, 31] == 0 and ob.weight[20, 33] > 0
        assert np.all(ob.weight[:3] == 0) and np.all(ob.weight[:, -3:] == 0)
        assert abs(ob.psf.sum() - 1) < 1e-6
    # the reconvolution smooths: each version's noise is below the input's, doubled by the added field
    ratio = v["noshear"].weight[24, 24] / w[24, 24]
    assert 0.5 < ratio < 50


def _table(n, rng, delta=0.01, shape_weights=False):
    """A synthetic metacal catalogue: e = e_int + R g, intrinsic shapes in +-pairs (no shape noise).

    ``shape_weights``: each version's weight falls with its own measured |e| (as lensfit's does).
    """
    R_true = np.array([[0.8, 0.02], [-0.01, 0.75]])
    g = np.array([0.02, -0.03])
    eint = rng.normal(0, 0.25, (n // 2, 2))
    eint = np.concatenate([eint, -eint])
    cols = {}

    def version(dg):
        return eint + (R_true @ (g + dg))[None, :]

    def weight(e):
        return 10.0 * np.exp(-np.sum(e * e, axis=1) / 0.08) if shape_weights else np.full(n, 10.0)

    e0 = version(np.zeros(2))
    cols.update(e1=e0[:, 0], e2=e0[:, 1], weight=weight(e0), fitclass=np.zeros(n, int))
    for name, dg in (("1p", (delta, 0)), ("1m", (-delta, 0)), ("2p", (0, delta)), ("2m", (0, -delta))):
        e = version(np.array(dg, float))
        cols.update({f"e1_{name}": e[:, 0], f"e2_{name}": e[:, 1], f"weight_{name}": weight(e),
                     f"fitclass_{name}": np.zeros(n, int)})
    for i in range(2):
        for j in range(2):
            cols[f"R{i + 1}{j + 1}"] = np.full(n, R_true[i, j])
    t = Table(cols)
    t.meta["MCDELTA"] = delta
    return t, R_true, g


def test_ensemble_response_and_selection_response():
    rng = np.random.default_rng(2)
    t, R_true, g = _table(100000, rng)
    R, Rg, Rs = ensemble_response(t)
    assert np.allclose(Rg, R_true) and np.allclose(Rs, 0, atol=1e-9)
    assert np.allclose(metacal_shear(t), g, atol=1e-9)
    # a cut on the measured |e| keeps fewer galaxies aligned with the shear: a selection bias that the
    # selection response, from each version's own |e|, corrects

    def cut(tab, sfx):
        return np.hypot(np.asarray(tab[f"e1{sfx}"]), np.asarray(tab[f"e2{sfx}"])) < 0.3

    keep = cut(t, "")
    naive = np.linalg.solve(R_true, [np.mean(np.asarray(t["e1"])[keep]), np.mean(np.asarray(t["e2"])[keep])])
    assert np.all(np.abs(naive / g - 1) > 0.1)
    R, Rg, Rs = ensemble_response(t, select=cut)
    assert Rs[0, 0] < -0.05 and Rs[1, 1] < -0.05
    est = metacal_shear(t, select=cut)
    # a hard cut's response rests on the few galaxies that cross it: a few per cent of noise here
    assert np.allclose(est, g, rtol=0.1), (est, naive, g)
    # weights falling with the measured |e| bias the weighted mean the same way; smooth, so the
    # correction is precise
    t, R_true, g = _table(100000, rng, shape_weights=True)
    w = np.asarray(t["weight"])
    naive = np.linalg.solve(R_true, [np.average(t["e1"], weights=w), np.average(t["e2"], weights=w)])
    assert np.all(np.abs(naive / g - 1) > 0.1)
    est = metacal_shear(t)
    assert np.allclose(est, g, rtol=3e-3), (est, naive, g)


def _ring_table(n_gal, rng):
    """A noisy metacal ring table: 4 objects per galaxy and sign, failed fits and non-finite R here and there."""
    n = n_gal * 8
    t = Table({"galaxy": np.repeat(np.arange(n_gal), 8), "sign": np.tile(np.repeat([1, -1], 4), n_gal)})
    for sfx in ("", "_1p", "_1m", "_2p", "_2m"):
        t[f"e1{sfx}"] = rng.normal(0, 0.3, n)
        t[f"e2{sfx}"] = rng.normal(0, 0.3, n)
        t[f"weight{sfx}"] = rng.uniform(1, 20, n)
        t[f"fitclass{sfx}"] = np.where(rng.random(n) < 0.1, rng.choice([-1, 1, 2], n), 0)
    t["e1"][rng.random(n) < 0.03] = np.nan
    t["weight"][rng.random(n) < 0.03] = np.nan
    for name in ("R11", "R12", "R21", "R22"):
        t[name] = rng.normal(0.9 if name[1] == name[2] else 0.0, 0.5, n)
    t["R12"][rng.random(n) < 0.05] = np.nan
    return t


def test_metacal_ring_sums_give_the_catalogue_shear():
    """m and c from per-galaxy sums equal those of metacal_shear on each sign's objects, and a bootstrap's
    multiplicities equal the galaxies repeated."""
    from shearfit.calib.bias import metacal_bias_from_sums, metacal_ring_sums

    rng = np.random.default_rng(7)
    n_gal, g = 40, np.array([0.03, -0.02])
    t = _ring_table(n_gal, rng)

    def direct(tab):
        plus, minus = tab[tab["sign"] > 0], tab[tab["sign"] < 0]
        sp, sm = metacal_shear(plus, delta=0.01), metacal_shear(minus, delta=0.01)
        w = [np.where(np.asarray(x["fitclass"]) == 0, np.nan_to_num(np.asarray(x["weight"])), 0) for x in (plus, minus)]
        e = [np.nan_to_num(np.stack([np.asarray(x["e1"]), np.asarray(x["e2"])])) @ wi / wi.sum()
             for x, wi in zip((plus, minus), w)]
        return (sp - sm) / (2 * g) - 1, (sp + sm) / 2, (e[0] - e[1]) / (2 * g) - 1, ensemble_response(plus, delta=0.01)

    m, c, raw, (_, Rg_plus, Rs_plus) = direct(t)
    sums = metacal_ring_sums(t, n_gal)
    bias, Rg, Rs = metacal_bias_from_sums(sums, g)
    assert np.allclose(bias[:2], m, rtol=0, atol=1e-12) and np.allclose(bias[2:4], c, rtol=0, atol=1e-12)
    assert np.allclose(bias[4:6], raw, rtol=0, atol=1e-12)
    _, Rg_minus, Rs_minus = ensemble_response(t[t["sign"] < 0], delta=0.01)
    assert np.allclose(Rg, (Rg_plus + Rg_minus) / 2) and np.allclose(Rs, (Rs_plus + Rs_minus) / 2)
    # the diagonal and scalar forms divide <e> by R's diagonal and by its mean
    assert not np.allclose(bias[6:8], bias[:2]) and not np.allclose(bias[8:10], bias[6:8])

    counts = rng.integers(0, 3, (2, n_gal)).astype(float)
    boot = metacal_bias_from_sums(sums, g, counts)[0]
    for k in range(2):
        rows = np.concatenate([np.flatnonzero(t["galaxy"] == i) for i in range(n_gal) for _ in range(int(counts[k, i]))])
        m_k, c_k, _, _ = direct(t[rows])
        assert np.allclose(boot[k, :4], np.concatenate([m_k, c_k]), rtol=0, atol=1e-12)


def test_metacal_ring_sums_without_selection_count_every_measured_object_in_every_version():
    """select=False: every object with finite e and R weighs one in the noshear sums and in every version's,
    whatever its fitclass and weight, so the selection response is zero and m is that of <e> / <R_gamma>."""
    from shearfit.calib.bias import metacal_bias_from_sums, metacal_ring_sums

    rng = np.random.default_rng(8)
    n_gal, g = 30, np.array([0.03, -0.02])
    t = _ring_table(n_gal, rng)
    sums = metacal_ring_sums(t, n_gal, select=False)
    measured = (np.isfinite(np.asarray(t["e1"])) & np.isfinite(np.asarray(t["e2"]))
                & np.all([np.isfinite(np.asarray(t[c])) for c in ("R11", "R12", "R21", "R22")], axis=0))
    # stars (fitclass 1) and failed versions count where their e and R are finite
    assert np.any(measured & (np.asarray(t["fitclass"]) != 0))
    for k in (0, 3, 8, 11, 14, 17):   # w, w_R and each version's w
        assert sums[k].sum() == measured.sum()
    bias, Rg, Rs = metacal_bias_from_sums(sums, g)
    assert np.all(Rs == 0)
    shear = {}
    for sign in (1, -1):
        sel = measured & (np.asarray(t["sign"]) == sign)
        e = np.array([np.asarray(t["e1"])[sel].mean(), np.asarray(t["e2"])[sel].mean()])
        R = np.array([[np.asarray(t[f"R{i}{j}"])[sel].mean() for j in (1, 2)] for i in (1, 2)])
        shear[sign] = np.linalg.solve(R, e)
    assert np.allclose(bias[:2], (shear[1] - shear[-1]) / (2 * g) - 1, rtol=0, atol=1e-12)
    # the default selects: other sums
    assert not np.allclose(metacal_ring_sums(t, n_gal), sums)


def test_versions_fitted_on_their_own_are_the_plain_fits_of_the_versions():
    """replay=False: each version is fitted as measure_object fits it (its own choices), the noshear fit is the
    replaying run's, and R is the difference of those fits."""
    obs = _obs(0.4, (0.2, -0.1), snr=40, n_exp=2, seed=3)
    fresh = measure_metacal(obs, 22.0, rng=np.random.default_rng(4), replay=False)
    replayed = measure_metacal(obs, 22.0, rng=np.random.default_rng(4))
    assert fresh.noshear.e1 == replayed.noshear.e1 and fresh.noshear.e2 == replayed.noshear.e2
    cfg = replace(shearfit.config.as_config(None), e_grid_min=E_GRID_MIN)
    rng = np.random.default_rng(4)
    versions = [metacal_observations(o, 0.01, rng) for o in obs]
    own = shearfit.measure_object([v["1p"] for v in versions], 22.0, cfg)
    assert abs(fresh.results["1p"].e1 - own.e1) < 1e-12 and abs(fresh.results["1p"].e2 - own.e2) < 1e-12
    assert fresh.R[0, 0] == (fresh.results["1p"].e1 - fresh.results["1m"].e1) / 0.02
    # the replays' estimates are other numbers (the samples are the noshear fit's), the response alike
    assert fresh.results["1p"].e1 != replayed.results["1p"].e1
    assert abs(fresh.R[0, 0] - replayed.R[0, 0]) < 0.3


def test_pipeline_metacal_columns(tmp_path):
    from shearfit.app.cli import main
    from shearfit.errors import ShearfitValueError
    from shearfit.io.fieldconfig import PipelineConfig
    from shearfit.simulate.field import simulate_field, simulation_config

    d = tmp_path / "f"
    simulate_field(simulation_config({"preset": "tiny", "seed": 5, "n_exposures": 2, "ccd_nx": 200, "ccd_ny": 200}),
                   str(d))
    out = tmp_path / "mc.fits"
    assert main(["measure", str(d / "field_truepsf.yaml"), "calibration=metacal", "--out", str(out), "--quiet"]) == 0
    t = Table.read(out)
    assert t.meta["CALMODE"] == "metacal" and t.meta["MCDELTA"] == 0.01
    for c in ("e1_1p", "weight_2m", "fitclass_1m", "R11", "R22"):
        assert c in t.colnames
    gal = np.asarray(t["fitclass"]) == FITCLASS_GALAXY
    assert gal.sum() >= 3
    assert 0.3 < np.nanmedian(np.asarray(t["R11"])[gal]) < 1.5
    assert np.all(np.asarray(t["m"])[gal] == 0)
    # objects flagged before their fits (blended, too few exposures, ...) carry the flag in every version
    fc = np.asarray(t["fitclass"])
    early = (fc < 0) & (np.asarray(t["n_exposures_used"]) == 0)
    assert early.any()
    for v in ("1p", "1m", "2p", "2m"):
        assert np.array_equal(np.asarray(t[f"fitclass_{v}"])[early], fc[early])
    # the same run again gives the same catalogue (the noise fields are seeded per object id)
    out2 = tmp_path / "mc2.fits"
    assert main(["measure", str(d / "field_truepsf.yaml"), "calibration=metacal", "--out", str(out2),
                 "--quiet"]) == 0
    assert np.array_equal(np.asarray(Table.read(out2)["R11"]), np.asarray(t["R11"]), equal_nan=True)
    assert t.meta["MCREPLAY"] is True
    # metacal_replay: false fits each version on its own: the same noshear fits, other sheared ones
    out3 = tmp_path / "mc_own.fits"
    assert main(["measure", str(d / "field_truepsf.yaml"), "calibration=metacal", "metacal_replay=false", "--out",
                 str(out3), "--quiet"]) == 0
    t3 = Table.read(out3)
    assert t3.meta["MCREPLAY"] is False
    assert np.array_equal(np.asarray(t3["e1"]), np.asarray(t["e1"]), equal_nan=True)
    assert not np.array_equal(np.asarray(t3["e1_1p"])[gal], np.asarray(t["e1_1p"])[gal])
    assert 0.3 < np.nanmedian(np.asarray(t3["R11"])[gal]) < 1.5
    # metacal_own_grid and metacal_own_position: the replays run their own ellipticity grids and find their own
    # positions: the same noshear fits, other sheared ones
    out4 = tmp_path / "mc_grid.fits"
    assert main(["measure", str(d / "field_truepsf.yaml"), "calibration=metacal", "metacal_own_grid=true",
                 "metacal_own_position=true", "--out", str(out4), "--quiet"]) == 0
    t4 = Table.read(out4)
    assert t4.meta["MCOWNGRD"] is True and t.meta["MCOWNGRD"] is False and t3.meta["MCOWNGRD"] is False
    assert t4.meta["MCOWNPOS"] is True and t.meta["MCOWNPOS"] is False
    assert np.array_equal(np.asarray(t4["e1"]), np.asarray(t["e1"]), equal_nan=True)
    assert not np.array_equal(np.asarray(t4["e1_1p"])[gal], np.asarray(t["e1_1p"])[gal])
    assert 0.3 < np.nanmedian(np.asarray(t4["R11"])[gal]) < 1.5
    assert main(["measure", str(d / "field_truepsf.yaml"), "calibration=metacal", "metacal_own_grid=true",
                 "sampling=two-pass", "--out", str(tmp_path / "bad.fits"), "--quiet"]) != 0
    assert not (tmp_path / "bad.fits").exists()
    # metacal_noise_sign=-1 (an antithetic twin's run) negates the symmetrising noise: every galaxy's response
    # moves (a single object's R is noisy: 0.4-1.2 here), their median stays a response's
    out3 = tmp_path / "mc3.fits"
    assert main(["measure", str(d / "field_truepsf.yaml"), "calibration=metacal", "metacal_noise_sign=-1",
                 "--out", str(out3), "--quiet"]) == 0
    r3 = np.asarray(Table.read(out3)["R11"])[gal]
    assert np.all(np.isfinite(r3)) and np.all(r3 != np.asarray(t["R11"])[gal])
    assert 0.3 < np.median(r3) < 1.5
    # metacal_psf=round: the versions' new PSF is the round envelope, named in the header
    out4 = tmp_path / "mc4.fits"
    assert main(["measure", str(d / "field_truepsf.yaml"), "calibration=metacal", "metacal_psf=round",
                 "--out", str(out4), "--quiet"]) == 0
    t4 = Table.read(out4)
    assert t4.meta["MCPSF"] == "round" and t.meta["MCPSF"] == "dilated"
    r4 = np.asarray(t4["R11"])[gal]
    assert np.all(np.isfinite(r4)) and 0.3 < np.median(r4) < 1.5
    with pytest.raises(ShearfitValueError, match="metacal_psf='square'"):
        PipelineConfig(metacal_psf="square")


def test_xipm_and_calibrate_read_a_metacal_catalogue(tmp_path):
    from astropy.io import fits

    from shearfit.calib.calibrate import matched_galaxies
    from shearfit.app.cli import main

    rng = np.random.default_rng(4)
    t, R_true, g = _table(2000, rng)
    n = len(t)
    t["id"] = np.arange(n)
    t["ra"] = 10 + rng.uniform(0, 0.05, n)
    t["dec"] = rng.uniform(0, 0.05, n)
    t["snr"] = np.full(n, 20.0)
    t["scalelength"] = np.full(n, 0.3)
    t["m"] = np.zeros(n)
    t.meta["CALMODE"] = "metacal"
    cat = tmp_path / "mc.fits"
    t.write(cat)
    out = tmp_path / "xi.fits"
    assert main(["xipm", str(cat), "--out", str(out), "--min-sep", "0.5", "--max-sep", "2", "--nbins", "2",
                 "--quiet"]) == 0
    h = fits.getheader(out, 1)
    assert h["CALIB"] == "metacal response" and h["MCR11"] == pytest.approx(0.8)
    x = Table.read(out)
    assert np.allclose(x["one_plus_k"], (0.5 * (0.8 + 0.75)) ** 2)
    truth = Table({"id": np.arange(n), "g1": np.full(n, g[0]), "g2": np.full(n, g[1]), "e1_int": np.zeros(n),
                   "e2_int": np.zeros(n), "is_star": np.zeros(n, bool)})
    truth.write(tmp_path / "truth.fits")
    mt = matched_galaxies(cat, tmp_path / "truth.fits")
    corrected = np.linalg.solve(R_true, np.stack([np.asarray(t["e1"]), np.asarray(t["e2"])]))
    assert np.allclose(np.asarray(mt["e1"]), corrected[0]) and np.allclose(np.asarray(mt["e2"]), corrected[1])


def test_non_square_stamp_is_processed_with_a_warning(caplog):
    J = PIX * np.eye(2)
    psf = draw_psf_image(moffat_psf(0.7, 3.0), J, size=25)
    o = shearfit.Observation(image=np.random.default_rng(0).normal(0, 1, (40, 48)), weight=np.ones((40, 48)),
                             psf=psf, jacobian=J)
    with caplog.at_level("WARNING", logger="shearfit.calib.metacal"):
        v = metacal_observations(o, rng=np.random.default_rng(1), versions=("noshear", "1p"))
    assert set(v) == {"noshear", "1p"} and v["1p"].image.shape == (40, 48)
    assert "not square" in caplog.text


def test_new_psf_moffat_is_the_exposures_dilated():
    """A given App. A Moffat is dilated with the PSF (shared alias tables), and matches a fit to the new PSF."""
    import galsim

    from shearfit.engine.model import psf_moffat
    from shearfit.observation import Observation

    psf = galsim.Moffat(beta=3.0, fwhm=0.45 / 0.187).shear(g1=0.05)
    im = galsim.Convolve(psf, galsim.Pixel(1.0)).drawImage(nx=48, ny=48, scale=1.0, method="no_pixel",
                                                          use_true_center=False).array
    im /= im.sum()
    m0 = psf_moffat(im)
    o = Observation(np.random.default_rng(1).normal(0, 1, (48, 48)), im, 0.187 * np.eye(2),
                    weight=np.ones((48, 48)), psf_moffat=m0)
    v = metacal_observations(o, 0.01, np.random.default_rng(0))
    rs, beta = v["noshear"].psf_moffat
    assert rs == pytest.approx(1.02 * m0[0]) and beta == m0[1]
    assert all(v[k].psf_moffat == (rs, beta) for k in v)
    refit = psf_moffat(v["noshear"].psf)
    assert rs == pytest.approx(refit[0], rel=0.01) and beta == pytest.approx(refit[1], rel=0.01)


def _fields(r):
    return (r.e1, r.e2, r.e_var, r.weight, r.scalelength, r.bulge_fraction, r.model_flux, r.fitclass, r.snr)


@pytest.mark.parametrize("sampling", ["adaptive", "two-pass"])
def test_a_replayed_fit_of_the_same_stamps_is_the_fit_itself(sampling):
    """measure_versions replays the first version's choices; on identical stamps it must give what measure_object
    gives, to rounding, when every reference sample is evaluated again and when only those near the cut are (they
    are then evaluated in other batches, and a few samples' posterior means can differ by one unit in the last
    place with their position in a batch: 3 of 304 on this object; the fit evaluates the size nodes of the
    samples it does not take for the tail together, the replay those of all, so that their batches differ too)."""
    from shearfit.engine.measure import measure_versions

    obs = _obs(0.3, (0.2, 0.1), snr=20, seed=4)
    cfg = {"sampling": sampling}
    plain = shearfit.measure_object(obs, 23.0, cfg)
    for margin in (np.inf, 10.0):
        first, again = measure_versions([obs, obs], 23.0, cfg, margin=margin)
        assert _fields(first) == _fields(plain)
        assert np.allclose(_fields(again), _fields(plain), rtol=1e-13, atol=0)
        assert again.fitclass == plain.fitclass
        if margin < np.inf:
            assert again.n_samples < plain.n_samples
    # the replay evaluates fewer models than a fit of its own (no size-locating passes, no far samples)
    assert again.n_models < first.n_models


def test_replayed_versions_follow_a_small_shear_linearly():
    """A galaxy drawn by GalSim at shears +-d with the same noise, the unsheared version the reference:
    the replayed estimates respond to the shear, and (e1(+d) - e1(-d)) / 2d is nearly the same for d = 0.01
    and 0.005. Not to second order in d: a sample crossing the posterior cut moves the estimate by a step
    (seed 1's e1 in steps of 0.0025 in g rises 1.1 per unit g in most steps and 1.4-1.7 in three of eight,
    session 74), so that the two differ by up to 0.11 at SNR 15; a replay that lost the samples' weights
    would not respond near 1 at all."""
    from shearfit.engine.measure import measure_versions

    for seed in range(3):
        R = []
        for d in (0.01, 0.005):
            vs = [_obs(0.3, (0.2, 0.1), snr=15, seed=seed, g=(s * d, 0.0)) for s in (0, 1, -1)]
            res = measure_versions(vs, 23.0)
            assert all(r.fitclass == FITCLASS_GALAXY for r in res)
            R.append((res[1].e1 - res[2].e1) / (2 * d))
        assert 0.2 < R[0] < 2.0
        assert abs(R[0] - R[1]) < 0.15, (seed, R)


def test_replays_that_evaluate_near_the_cut_first_give_the_same_estimates():
    """With a first margin, a replay evaluates the samples above the noshear fit's cut first and of the rest only
    those its change of the posterior, predicted from the first, could lift to within the first margin of its own
    cut: the estimates are those of the full 10-nat margin, to rounding (the
    compiled marginalisation's vector exponentials may differ in the last place with an element's position in a
    batch; e_var, a difference of sums of e^2, to their rounding; the numpy loops to 1e-10), for metacal's sheared
    versions of galaxies at SNR 15 to 300, with fewer samples evaluated."""
    from shearfit.calib.metacal import REPLAY_FIRST_MARGIN, VERSIONS
    from shearfit.engine import likelihood
    from shearfit.engine.measure import measure_versions

    fewer = 0
    # the numpy loops' sums round differently with a batch's composition: 1.7e-12 seen (the bulge fraction)
    rtol = 1e-12 if likelihood.USE_KERNEL else 1e-10
    for seed in range(4):
        obs = _obs(0.25, (0.3 * (-1) ** seed, 0.1), snr=[15, 40, 100, 300][seed], seed=seed)
        per = [metacal_observations(o, 0.01, np.random.default_rng(seed)) for o in obs]
        versions = [[v[name] for v in per] for name in VERSIONS]
        full = measure_versions(versions, 23.0, margin=10.0)
        for fm in (REPLAY_FIRST_MARGIN, 0.25):
            first = measure_versions(versions, 23.0, margin=10.0, first_margin=fm)
            for a, b in zip(full, first):
                fa, fb = np.array(_fields(a), float), np.array(_fields(b), float)
                np.testing.assert_allclose(np.delete(fa, 2), np.delete(fb, 2), rtol=rtol, atol=0)
                # e_var, <e^2> - <e>^2 of e ~ 0.3: to rounding of the sums of e^2 (~0.1), not of e_var (~1e-4)
                assert abs(a.e_var - b.e_var) < 0.1 * rtol
                fewer += b.n_samples < a.n_samples
    assert fewer >= 16


def test_versions_replayed_together_are_replayed_one_by_one(monkeypatch):
    """measure_versions evaluates the sheared versions' replays together (VersionLikelihoods: one binning per
    ellipticity for all four, each version's size nodes in one compiled call as its own like's): the estimates
    of replaying each version on its own, to the bit without a first margin; with one, where each version
    evaluates the samples it needs alone (the others' binned with them, its models made only at its own: the same
    samples and models as alone), to rounding; and with versions at their own positions (which without fold
    groups among the modes still bin together)."""
    from shearfit.calib.metacal import VERSIONS
    from shearfit.engine import likelihood, sampling
    from shearfit.engine.measure import _measure, measure_versions

    if not likelihood.USE_KERNEL:
        pytest.skip("compiled kernel not built")
    joint = []
    real = sampling.VersionLikelihoods._chunk
    monkeypatch.setattr(sampling.VersionLikelihoods, "_chunk", lambda self, *a: joint.append(len(self.likes))
                        or real(self, *a))
    for seed, first_margin, own in ((1, None, False), (2, 1.0, False), (3, 1.0, True)):
        obs = _obs(0.25, (0.3, -0.1), snr=25, seed=seed)
        per = [metacal_observations(o, 0.01, np.random.default_rng(seed)) for o in obs]
        versions = [[v[name] for v in per] for name in VERSIONS]
        together = measure_versions(versions, 23.0, margin=10.0, first_margin=first_margin, own_position=own)
        ref, plan = _measure(versions[0], 23.0, shearfit.FitConfig(), False, margin=10.0)
        assert _fields(together[0]) == _fields(ref)
        for v, res in zip(versions[1:], together[1:]):
            alone = _measure(v, 23.0, shearfit.FitConfig(), False, plan=plan, margin=10.0,
                             first_margin=first_margin, own_position=own)[0]
            if first_margin is None:
                assert _fields(res) == _fields(alone)
                assert (res.fitclass, res.n_samples, res.n_models) == (alone.fitclass, alone.n_samples, alone.n_models)
            else:
                np.testing.assert_allclose(np.delete(np.array(_fields(res), float), 2),
                                           np.delete(np.array(_fields(alone), float), 2), rtol=1e-12, atol=0)
                assert (res.fitclass, res.n_samples, res.n_models) == (alone.fitclass, alone.n_samples, alone.n_models)
    assert joint and max(joint) == 4


def test_versions_share_their_quadratic_sums_to_the_bit(monkeypatch):
    """The replays' size nodes in one compiled call (KERNEL.size_nodes_versions) sum the modes' quadratic terms
    and the fold groups' pairs once for the four versions (they are the modes', not the data's): each version's
    estimate and every number of its fit are those of its own replay, to the bit, on exposures with their own
    rotations, whose fold groups give pairs."""
    from shearfit.calib.metacal import VERSIONS
    from shearfit.engine import likelihood, sampling
    from shearfit.engine.measure import _measure, measure_versions
    from shearfit.simulate.stamps import ring_set

    if not likelihood.USE_KERNEL:
        pytest.skip("compiled kernel not built")
    pairs = []
    real = sampling.VersionLikelihoods._nodes_versions
    monkeypatch.setattr(sampling.VersionLikelihoods, "_nodes_versions", lambda self, *a: pairs.append(
        likelihood.packed_bins(self.likes[0].jm)[5].size) or real(self, *a))
    cfg = shearfit.FitConfig()
    sim = ring_set(2, (0.0, 0.0), np.random.default_rng(7), n_rotations=1, n_exposures=4, snr_range=(20, 40),
                   stamp_size=40, rotate_exposures=True)
    for k, (obs, _) in enumerate(sim):
        per = [metacal_observations(o, 0.01, np.random.default_rng(k)) for o in obs]
        versions = [[v[name] for v in per] for name in VERSIONS]
        # (every sample within the margin, the same for every version: which ones a first margin picks depends on
        # the versions evaluated together, test_versions_replayed_together_are_replayed_one_by_one)
        together = measure_versions(versions, 23.0, cfg, margin=10.0)
        ref, plan = _measure(versions[0], 23.0, cfg, False, margin=10.0)
        for v, res in zip(versions[1:], together[1:]):
            alone = _measure(v, 23.0, cfg, False, plan=plan, margin=10.0)[0]
            assert _fields(res) == _fields(alone)
            assert (res.fitclass, res.n_samples, res.n_models) == (alone.fitclass, alone.n_samples, alone.n_models)
    assert pairs and max(pairs) > 0


def test_versions_evaluated_where_each_needs_are_their_numbers_there(monkeypatch):
    """VersionLikelihoods with ``need`` (each version's own samples of the ellipticities evaluated together: metacal's
    near-cut replays, sampling._evaluate_near_cut): at a version's own samples its numbers to rounding, NaN at the
    others (the flux and bulge-fraction marginals and the size integral not made there), its best fit (the
    star/galaxy test's chi^2 and the SNR) still the one over every model, and only its own models counted; the
    same with one likelihood after another (no joint evaluation) to rounding."""
    import copy

    from shearfit.calib.metacal import VERSIONS
    from shearfit.engine import likelihood, measure
    from shearfit.engine.measure import measure_versions

    if not likelihood.USE_KERNEL:
        pytest.skip("compiled kernel not built")
    got = []
    real = measure.replay_versions
    monkeypatch.setattr(measure, "replay_versions", lambda likes, ref, *a: got.append((copy.deepcopy(likes), ref))
                        or real(likes, ref, *a))
    obs = _obs(0.25, (0.3, -0.1), snr=15, seed=4)
    per = [metacal_observations(o, 0.01, np.random.default_rng(4)) for o in obs]
    measure_versions([[v[name] for v in per] for name in VERSIONS], 23.0, margin=10.0)
    likes, ref = got[0]
    assert likes.joint and len(likes.likes) == 4
    keep = np.isfinite(ref.logpost)
    e1, e2 = ref.e1[keep], ref.e2[keep]
    need = np.random.default_rng(5).random((e1.size, 4)) < 0.4
    need[:, 2] = False                       # a version that needs none of them
    need[np.argmax(ref.logpost[keep])] = [False, True, False, True]   # its best model among the others' samples
    every, some = copy.deepcopy(likes), copy.deepcopy(likes)
    n0 = [lk.n_models for lk in some.likes]
    full, part = every(e1, e2), some(e1, e2, need=need)
    nr = likes.likes[0].x.size
    fields = ("logl_disk", "logl_bulge", "mean_r", "mean_b", "mean_flux")
    for v in range(4):
        k = need[:, v]
        for f in fields:
            a, b = getattr(full[v], f), getattr(part[v], f)
            # (the same arithmetic on other batches of models: its vector loops' remainders may round otherwise)
            np.testing.assert_allclose(b[k], a[k], rtol=1e-13, atol=0, err_msg=f"{v} {f}")
            assert np.isnan(b[~k]).all(), (v, f)
        assert (some.likes[v].best_chi2_gal, some.likes[v].best_snr) == (every.likes[v].best_chi2_gal,
                                                                         every.likes[v].best_snr), v
        assert some.likes[v].n_models - n0[v] == np.count_nonzero(k) * nr
    one = copy.deepcopy(likes)
    one.joint = False
    alone = one(e1, e2, need=need)
    for v in range(4):
        for f in fields:
            np.testing.assert_allclose(getattr(alone[v], f), getattr(part[v], f), rtol=1e-12, atol=0, equal_nan=True)


def test_versions_round_bins_made_together_are_each_versions_own():
    """The replays' point sources (and round models) bin the four versions' modes at e = 0 in one call
    (likelihood.seed_round_bins): each version's bins are those of its own mode_bins, to the bit, and so are the
    point source's sums."""
    from copy import copy

    from shearfit.calib.metacal import VERSIONS
    from shearfit.engine import likelihood
    from shearfit.engine.measure import _measure, _replay_exposures_versions, _replay_joint
    from shearfit.engine.profiles import fast_pair
    from shearfit.simulate.stamps import ring_set

    if not likelihood.USE_KERNEL:
        pytest.skip("compiled kernel not built")
    cfg = shearfit.FitConfig()
    obs, _ = next(iter(ring_set(1, (0.0, 0.0), np.random.default_rng(3), n_rotations=1, n_exposures=3,
                                snr_range=(20, 40), stamp_size=40, rotate_exposures=True)))
    per = [metacal_observations(o, 0.01, np.random.default_rng(5)) for o in obs]
    versions = [[v[name] for v in per] for name in VERSIONS]
    plan = _measure(versions[0], 23.0, cfg, False, margin=10.0)[1]
    jms = [_replay_joint(ex, 23.0, cfg, plan)[0] for ex in _replay_exposures_versions(versions[1:], cfg, plan)]
    alone = [copy(j) for j in jms]
    likelihood.seed_round_bins(jms, cfg.mode_bins_per_octave)
    fast = fast_pair(cfg.truncation)
    for jm, own in zip(jms, alone):
        seeded = jm._round[1]
        made = likelihood.mode_bins(own, np.zeros(1), np.zeros(1), cfg.mode_bins_per_octave)
        for f in ("lo", "offsets", "columns", "dc"):
            assert bytes(getattr(seeded, f)) == bytes(np.asarray(getattr(made, f)).tobytes()), f
        assert np.array_equal(seeded.shape, made.shape)
        a = likelihood.model_sums(jm, [0.0], [0.0], [0.0], fast, cfg.bulge_size_ratio,
                                  bins_per_octave=cfg.mode_bins_per_octave)
        b = likelihood.model_sums(own, [0.0], [0.0], [0.0], fast, cfg.bulge_size_ratio,
                                  bins_per_octave=cfg.mode_bins_per_octave)
        assert all(np.array_equal(getattr(a, f), getattr(b, f)) for f in a.__dataclass_fields__)
    assert len({bytes(j._round[1].columns) for j in jms}) == len(jms)   # the versions' data differ


def test_masks_grow_as_scipys_binary_dilation():
    from scipy import ndimage

    from shearfit.calib.metacal import _grown

    rng = np.random.default_rng(11)
    for shape, frac in (((48, 48), 0.01), ((40, 56), 0.05), ((7, 5), 0.2), ((48, 48), 0.0)):
        m = rng.random(shape) < frac
        m[0, rng.integers(shape[1])] = True   # one on the edge
        for steps in (1, 2, 3):
            assert np.array_equal(_grown(m, steps), ndimage.binary_dilation(m, iterations=steps))


def test_replay_needs_the_same_psfs():
    from shearfit.errors import ShearfitValueError
    from shearfit.engine.measure import measure_versions

    obs = _obs(0.3, (0.2, 0.1), snr=20, seed=4)
    other = []
    for o in obs:
        psf = o.psf[2:-2, 2:-2]
        other.append(shearfit.Observation(image=o.image, weight=o.weight, psf=psf / psf.sum(), jacobian=o.jacobian,
                                          offset=o.offset))
    with pytest.raises(ShearfitValueError, match="same PSFs"):
        measure_versions([obs, other], 23.0)


def test_a_version_reuses_the_modes_of_the_first():
    """prepare_exposure(like=...) transforms only the pixels: the same ExposureModes as a fresh preparation."""
    from shearfit.engine.model import prepare_exposure

    a = _obs(0.3, (0.2, 0.1), snr=20, seed=4)[0]
    b = _obs(0.3, (0.2, 0.1), snr=20, seed=4, g=(0.01, 0.0))[0]
    cfg = shearfit.FitConfig()
    fresh = prepare_exposure(b, cfg)
    reused = prepare_exposure(b, cfg, like=prepare_exposure(a, cfg))
    from dataclasses import fields

    for f in fields(fresh):   # every field (prepare_exposure makes the reused one field by field)
        assert np.array_equal(getattr(fresh, f.name), getattr(reused, f.name)), f.name
    assert not np.array_equal(fresh.data_ft, prepare_exposure(a, cfg).data_ft)


def _versions_with(monkeypatch, obs, rng_seed, quiet, **settings):
    from shearfit.calib import metacal

    with monkeypatch.context() as m:
        for name, value in settings.items():
            m.setattr(metacal, name, value)
        rng = QuietNormal(rng_seed) if quiet else np.random.default_rng(rng_seed)
        return metacal_observations(obs, rng=rng)


def _worst(a, b):
    """Largest difference of two sets of versions on their unmasked pixels, in units of the noshear peak."""
    good = a["noshear"].weight > 0
    peak = np.abs(a["noshear"].image[good]).max()
    return max(np.abs(a[v].image - b[v].image)[good].max() for v in a) / peak


@pytest.mark.parametrize("J", [None, PIX * np.array([[0.3, -0.95], [0.94, 0.31]])])
def test_versions_of_a_noise_free_galaxy_keep_to_galsims_grid(monkeypatch, J):
    """The versions are drawn on a periodic grid of 4/3 stamp widths (for speed): for noise-free galaxies,
    on an unrotated and a rotated, sheared pixel grid, every version stays within 1e-4 of its peak of the
    one drawn on GalSim's own grid, away from the masked edge; the 1p - 1m difference the response comes
    from did change the images."""
    for seed, (r, e) in enumerate([(0.3, (0.2, -0.1)), (0.6, (-0.3, 0.25)), (0.15, (0.05, 0.4))]):
        for ob in _obs(r, e, n_exp=2, seed=seed, J=J):
            fast = _versions_with(monkeypatch, ob, 5, True)
            ref = _versions_with(monkeypatch, ob, 5, True, WRAP_STAMPS=0)
            assert _worst(fast, ref) < 1e-4
            d = fast["1p"].image - fast["1m"].image
            assert np.abs(d).max() > 1e-3 * np.abs(fast["noshear"].image).max()


def _fixed_sample_responses(monkeypatch, n_gal, seed, psf="dilated", **settings):
    """Per noise-free galaxy: metacal's diagonal R and the true shear response A of the noshear fit (GalSim
    renders at +-h), every fit replaying the unsheared noshear fit's choices
    (:func:`shearfit.simulate.metacal_check.fixed_sample_responses`)."""
    from dataclasses import replace

    from shearfit.calib import metacal
    from shearfit.engine.measure import as_config
    from shearfit.simulate.metacal_check import fixed_sample_responses, shear_sets

    h = 0.01
    sets = shear_sets(n_gal, h, seed, n_exposures=2, snr_range=(15, 30), mag_range=(22, 24), stamp_size=48,
                      add_noise=False)
    cfg = replace(as_config(None), e_grid_min=metacal.E_GRID_MIN)
    out = []
    with monkeypatch.context() as m:
        for name, value in settings.items():
            m.setattr(metacal, name, value)
        for i in range(n_gal):
            R, A, _, fitclasses = fixed_sample_responses(sets, i, h, 0.01, cfg, 3, free=False, psf=psf)
            assert all(c == FITCLASS_GALAXY for c in fitclasses)
            out.append((R, A))
    d = np.array(out)
    return d[:, 0], d[:, 1]


def test_metacal_response_of_noise_free_galaxies_is_their_true_shear_response(monkeypatch):
    """At fixed samples, metacal's R of a noise-free galaxy is its true shear response (GalSim shearing the
    galaxy before the PSF) to 1e-3 per galaxy and to 3e-4 on average (seen: 5e-4 and 1.5e-4); GalSim's
    cubic k-interpolant instead of its quintic, for the stamp or for the PSF, fails this: its anisotropic
    errors bias the response to shears along the pixel diagonals (by 3.7e-3 and 1.3e-3 here)."""
    R, A = _fixed_sample_responses(monkeypatch, 6, 12)
    assert np.abs(A - R).max() < 1e-3, A - R
    assert np.all(np.abs(A.mean(axis=0) / R.mean(axis=0) - 1) < 3e-4)
    for setting in ("K_INTERPOLANT", "PSF_K_INTERPOLANT"):
        Rc, Ac = _fixed_sample_responses(monkeypatch, 6, 12, **{setting: "cubic"})
        assert np.abs(Ac[:, 1].mean() / Rc[:, 1].mean() - 1) > 6e-4, setting


def test_round_new_psf_keeps_the_response_of_noise_free_galaxies_their_true_shear_response(monkeypatch):
    """The same with metacal's round new PSF (``psf='round'``): its versions still respond as a true shear
    does, to 1e-3 per galaxy and 3e-4 on average (seen: 1.9e-4 and 6e-5)."""
    R, A = _fixed_sample_responses(monkeypatch, 6, 12, psf="round")
    assert np.abs(A - R).max() < 1e-3, A - R
    assert np.all(np.abs(A.mean(axis=0) / R.mean(axis=0) - 1) < 3e-4)


def test_round_new_psf_of_an_oversampled_psf_and_an_unknown_name():
    """An oversampled PSF's round new PSF is drawn on its own pixels and round on the sky (GalSim's adaptive
    moments: |e| < 1e-3 for a PSF of |e| 0.1), the versions made through GalSim's objects; an unknown ``psf`` is
    a one-line error naming it."""
    import galsim

    from shearfit.calib import metacal
    from shearfit.errors import ShearfitValueError

    J = PIX * np.array([[0.6, -0.8], [0.8, 0.6]])
    psf = moffat_psf(0.65, 3.0, 0.05, 0.0)
    pim = draw_psf_image(psf, J, size=25, oversampling=3)
    gal = galaxy_profile(0.3, 0.1, 0.1, 0.0, flux=1000.0)
    im = draw_stamp(gal, psf, J, (0.0, 0.0))
    o = shearfit.Observation(image=im, weight=np.full(im.shape, 1e4), psf=pim, psf_oversampling=3, jacobian=J)
    v = metacal_observations(o, rng=np.random.default_rng(0), psf="round")
    assert v["noshear"].psf.shape == pim.shape and abs(v["noshear"].psf.sum() - 1) < 1e-12
    prof = metacal._interpolated(v["noshear"].psf, metacal._wcs(J, 3))
    m = galsim.hsm.FindAdaptiveMom(prof.drawImage(nx=96, ny=96, scale=PIX / 3, method="no_pixel"))
    m0 = galsim.hsm.FindAdaptiveMom(metacal._interpolated(pim, metacal._wcs(J, 3)).drawImage(
        nx=96, ny=96, scale=PIX / 3, method="no_pixel"))
    assert abs(m0.observed_shape.e1) > 0.05 and np.hypot(m.observed_shape.e1, m.observed_shape.e2) < 1e-3
    assert np.all(np.isfinite(v["1p"].image)) and not np.array_equal(v["1p"].image, v["noshear"].image)
    with pytest.raises(ShearfitValueError, match="psf='square'"):
        metacal_observations(o, psf="square")


def test_noise_processed_on_the_smaller_grid_has_the_same_variance(monkeypatch):
    """The stamp's noise and the symmetrising noise go through the same operations on either grid: the
    versions' noise variance (and so their weights) agrees with GalSim's grid's to 2 %, on pure-noise
    stamps."""
    J = PIX * np.array([[-1.0, 0.0], [0.0, 1.0]])
    psf = draw_psf_image(moffat_psf(0.65, 3.0, 0.03, -0.02), J, size=25)
    rng = np.random.default_rng(11)
    ratios = []
    for k in range(6):
        o = shearfit.Observation(image=rng.normal(0, 1.0, (48, 48)), weight=np.ones((48, 48)), psf=psf, jacobian=J)
        fast = _versions_with(monkeypatch, o, k, False)
        ref = _versions_with(monkeypatch, o, k, False, WRAP_STAMPS=0)
        good = fast["noshear"].weight > 0
        ratios.append([np.var(fast[v].image[good]) / np.var(ref[v].image[good]) for v in fast])
        assert np.allclose(fast["noshear"].weight[good], ref["noshear"].weight[good], rtol=0.05)
    assert abs(np.mean(ratios) - 1) < 0.02, np.mean(ratios)


@pytest.mark.parametrize("J", [None, PIX * np.array([[0.3, -0.95], [0.94, 0.31]])])
def test_batched_band_limited_draw_is_galsims_own(J, monkeypatch):
    """The versions' images are drawn in one batch per stamp, each product evaluated only within the
    deconvolution's band and the PSF factors shared between the versions and the noise: every image equals
    GalSim's plain ``Convolve(...).drawImage`` of the same profiles (to 1e-7 of the peak), also on a
    rotated, sheared pixel grid."""
    import galsim

    from shearfit.calib import metacal

    obs = _obs(0.3, (0.2, -0.1), snr=40, n_exp=1, seed=4, J=J)[0]
    seen = []
    orig_draw = metacal._Drawer.draw

    def plain(self, products, bands):
        # the same products drawn by GalSim's own Convolution, one drawImage each
        ny, nx = self.shape
        for product, band in zip(products, bands):
            n, _, dk = self._grid(product)
            seen.append((int(np.ceil(band / (dk * self.sigma_min))) + 1, n))
        return [galsim.Convolution(p).drawImage(nx=nx, ny=ny, wcs=self.wcs, method="no_pixel",
                                                use_true_center=False).array for p in products]

    monkeypatch.setattr(metacal, "WRAP_STAMPS", 0)   # GalSim's own FFT grid (the default grid: the test above)
    fast = metacal_observations(obs, rng=np.random.default_rng(5))
    try:
        metacal._Drawer.draw = plain
        ref = metacal_observations(obs, rng=np.random.default_rng(5))
    finally:
        metacal._Drawer.draw = orig_draw
    peak = np.abs(ref["noshear"].image).max()
    for name in ref:
        assert np.abs(fast[name].image - ref[name].image).max() < 1e-7 * peak, name
        assert np.allclose(fast[name].weight, ref[name].weight, rtol=1e-6, atol=0)
    assert len(seen) == 10    # five versions and their noise, drawn by GalSim in the reference


@pytest.mark.parametrize("fwhm, shape", [(0.9, (40, 40)), (0.6, (40, 40)), (0.9, (41, 41)), (0.6, (36, 45))])
def test_drawer_folds_a_band_beyond_nyquist_as_galsim_does(fwhm, shape):
    """A PSF whose transform GalSim finds wider than the grid's Nyquist frequency (here 0.6": its maxk is
    that of the interpolant, 17 / arcsec) puts the deconvolution's band beyond the grid: the drawer folds
    the k image onto the grid as GalSim's drawFFT does; with a 0.9" PSF the band is inside. Either way the
    images are GalSim's own, for sheared products on a rotated grid, on even, odd and oblong stamps."""
    import galsim

    from shearfit.calib import metacal

    J = PIX * np.array([[0.3, -0.95], [0.94, 0.31]])
    wcs = metacal._wcs(J)
    rng = np.random.default_rng(2)
    psf = metacal._interpolated(draw_psf_image(moffat_psf(fwhm, 3.0, 0.05, -0.02), J, size=33), wcs,
                                calculate_maxk=True, k_interpolant="cubic")
    gal = metacal._interpolated(rng.normal(size=shape), wcs)
    inv, new = galsim.Deconvolve(psf), psf.dilate(1.02)
    products, bands = [], []
    for g1, g2 in ((0.0, 0.0), (0.01, 0.0), (0.0, -0.01)):
        gi, ii = (gal.shear(g1=g1, g2=g2), inv.shear(g1=g1, g2=g2)) if (g1 or g2) else (gal, inv)
        products.append([gi, ii, new])
        bands.append(ii.maxk)
    drawer = metacal._Drawer(shape, wcs, fft_size=0)   # GalSim's own FFT grid
    fast = drawer.draw(products, bands)
    n, _, dk = drawer._grid(products[0])
    r = int(np.ceil(bands[0] / (dk * drawer.sigma_min))) + 1
    assert (r >= n // 2) == (fwhm < 0.7)
    for p, im in zip(products, fast):
        ref = galsim.Convolution(p).drawImage(nx=shape[1], ny=shape[0], wcs=wcs, method="no_pixel",
                                              use_true_center=False).array
        assert np.abs(im - ref).max() < 1e-7 * np.abs(ref).max()
    # on the default, smaller grid (folded there too when the band reaches beyond it), a compact galaxy's
    # products stay GalSim's own to 1e-4 of the peak away from the edge
    from shearfit.simulate.stamps import draw_stamp, galaxy_profile
    psf_prof = moffat_psf(fwhm, 3.0, 0.05, -0.02)
    stamp = draw_stamp(galaxy_profile(0.3, 0.2, 0.2, -0.1, flux=100.0), psf_prof, J, (0.2, -0.3), stamp_size=shape[0])
    cg = metacal._interpolated(np.pad(stamp, ((0, 0), (0, shape[1] - shape[0])))
                               if shape[1] > shape[0] else stamp, wcs, k_interpolant="cubic")
    prods = [[cg.shear(g1=g1, g2=g2) if (g1 or g2) else cg] + p[1:] for p, (g1, g2) in
             zip(products, ((0.0, 0.0), (0.01, 0.0), (0.0, -0.01)))]
    small = metacal._Drawer(shape, wcs)
    assert small._grid(prods[0])[0] == small.fft_size < n
    for p, im in zip(prods, small.draw(prods, bands)):
        ref = galsim.Convolution(p).drawImage(nx=shape[1], ny=shape[0], wcs=wcs, method="no_pixel",
                                              use_true_center=False).array
        assert np.abs(im - ref)[3:-3, 3:-3].max() < 1e-4 * np.abs(ref).max()


@pytest.mark.parametrize("k", [1, 3])
def test_new_psf_is_drawn_in_its_pixel_frame_as_through_the_jacobian(k):
    """The dilated PSF's image is drawn in the PSF's own pixel frame (a dilation commutes with the
    Jacobian; GalSim then interpolates separably): the same pixels as drawing the dilated PSF through a
    rotated, sheared Jacobian, to float32 rounding, natively and oversampled."""
    from shearfit.calib import metacal

    J = PIX * np.array([[0.3, -0.95], [0.94, 0.31]])
    img = draw_psf_image(moffat_psf(0.7, 3.0, 0.05, -0.03), J, size=25 * k, oversampling=k)
    obs = shearfit.Observation(image=np.zeros((40, 40)), weight=np.ones((40, 40)), psf=img, jacobian=J,
                               psf_oversampling=k)
    got = metacal_observations(obs, delta=0.01, rng=np.random.default_rng(1), versions=("noshear",))["noshear"].psf
    pwcs = metacal._wcs(J, k)
    ref = metacal._draw(metacal._interpolated(img, pwcs).dilate(1.02), img.shape, pwcs)
    ref = ref / ref.sum()
    assert np.abs(got - ref).max() < 1e-6 * ref.max()


def test_replayed_versions_can_find_their_own_position():
    """With ``own_position``, measure_versions' versions find their own cross-correlation peak (from the
    first's) and replay every other choice: a noise-free galaxy moved by (0.4, 0.3) pixels in every exposure
    gives the first version's estimate to 1e-5, at its own offset; replaying the first's position as well (the
    default) leaves the moved galaxy off the model's centre, and its estimate off by a few 1e-4."""
    from shearfit.engine.measure import measure_versions

    def stamps(d):
        rng = np.random.default_rng(0)
        J = PIX * np.array([[-1.0, 0.0], [0.0, 1.0]])
        offs = rng.uniform(-0.5, 0.5, (3, 2))
        psfs = [moffat_psf(0.6 + 0.05 * i, 3.0, 0.04 * (-1) ** i, 0.03) for i in range(3)]
        gal = galaxy_profile(0.3, 0.1, 0.2, 0.1, flux=1000.0)
        ims = [draw_stamp(gal, p, J, o + np.asarray(d)) for p, o in zip(psfs, offs)]
        sig = noise_for_snr([draw_stamp(gal, p, J, o) for p, o in zip(psfs, offs)], 300.0)
        return [shearfit.Observation(image=im, weight=np.full(im.shape, 1 / sig ** 2), psf=draw_psf_image(p, J, size=25),
                                     jacobian=J, offset=tuple(o)) for im, p, o in zip(ims, psfs, offs)]

    ref, moved = stamps((0.0, 0.0)), stamps((0.4, 0.3))
    a, b = measure_versions([ref, moved], 23.0, own_position=True)
    assert a.fitclass == b.fitclass == FITCLASS_GALAXY
    assert abs(b.e1 - a.e1) < 1e-5 and abs(b.e2 - a.e2) < 1e-5
    assert abs(b.centroid_shift - np.hypot(0.4, 0.3)) < 0.01 and a.centroid_shift < 0.01
    a, b = measure_versions([ref, moved], 23.0)
    assert b.centroid_shift == a.centroid_shift
    assert np.hypot(b.e1 - a.e1, b.e2 - a.e2) > 2e-4


def _noisy_reference_and_version(seed, jacobian, version_noise):
    """Three exposures of a faint (SNR 12) galaxy with their own elliptical PSFs and dithers: a noisy reference and
    a version of it with more noise (``version_noise`` of the reference's sigma) added, as Observations."""
    rng = np.random.default_rng(seed)
    J = PIX * np.asarray(jacobian, float)
    offs = rng.uniform(-0.5, 0.5, (3, 2))
    psfs = [moffat_psf(0.6 + 0.05 * i, 3.0, 0.04 * (-1) ** i, 0.03) for i in range(3)]
    gal = galaxy_profile(0.25, 0.2, -0.1, 0.1, flux=1000.0)
    clean = [draw_stamp(gal, p, J, o) for p, o in zip(psfs, offs)]
    sig = noise_for_snr(clean, 12.0)

    def obs(ims):
        return [shearfit.Observation(image=im, weight=np.full(im.shape, 1 / sig ** 2),
                                     psf=draw_psf_image(p, J, size=25), jacobian=J, offset=tuple(o))
                for im, p, o in zip(ims, psfs, offs)]

    ref = obs([im + rng.normal(0, sig, im.shape) for im in clean])
    return ref, obs([o.image + rng.normal(0, version_noise * sig, o.image.shape) for o in ref])


def test_replayed_versions_can_place_their_own_size_nodes():
    """With ``own_sizes``, a version places its size nodes and centres from its own round model's size posterior
    and replays every other choice: the reference's own pixels give the reference's nodes, centre and estimate
    (to 1e-12); a version with other noise gets nodes of its own, and an estimate that differs from the full
    replay's (which keeps the reference's nodes) but lies within a tenth of the error on e of it."""
    from shearfit.config import as_config
    from shearfit.engine.measure import _measure, _replay_exposures, _replay_likelihood, measure_versions

    ref, ver = _noisy_reference_and_version(5, [[0.0, -1.0], [1.0, 0.0]], 0.3)
    cfg = as_config(None)
    res, plan = _measure(ref, 23.0, cfg, False)
    assert res.fitclass == FITCLASS_GALAXY

    def version_like(o, own):
        return _replay_likelihood(_replay_exposures(o, cfg, plan), 23.0, cfg, plan, own_sizes=own)[1]

    same = version_like(ref, True)
    assert np.array_equal(same.x, plan.size_nodes) and same.r_center == plan.r_center and same.fixed_centres is None
    other = version_like(ver, True)
    assert not np.allclose(other.x, plan.size_nodes, rtol=0, atol=1e-3) and other.r_center != plan.r_center
    assert version_like(ver, False).fixed_centres is plan.centres
    a, b, c = measure_versions([ref, ref, ver], 23.0, own_sizes=True)
    assert abs(b.e1 - a.e1) < 1e-12 and abs(b.e2 - a.e2) < 1e-12
    replayed = measure_versions([ref, ver], 23.0)[1]
    d = np.hypot(replayed.e1 - c.e1, replayed.e2 - c.e2)
    assert 1e-6 < d < 0.1 * np.sqrt(replayed.e_var)


def test_versions_can_run_their_own_ellipticity_grid():
    """``adaptive_versions`` runs the adaptive grid on each version's own likelihood, the reference's samples
    evaluated once for all: with every reference sample evaluated (an infinite margin) it is
    ``adaptive_samples`` on the version's likelihood, sample for sample; with the default margin the same
    estimate to 1e-9; the reference's own version gives the reference's estimate. The noisy version's grid
    differs from the reference's, with samples the reference never had (so the replay's cells would not be its
    own, and the centres of new samples are exercised)."""
    from shearfit.config import as_config
    from shearfit.engine.measure import _measure, _replay_exposures, _replay_likelihood, measure_versions
    from shearfit.engine.sampling import VersionLikelihoods, adaptive_samples, adaptive_versions, estimate

    ref, ver = _noisy_reference_and_version(3, [[-1.0, 0.0], [0.0, 1.0]], 0.5)
    cfg = as_config(None)
    res, plan = _measure(ref, 23.0, cfg, False)
    assert res.fitclass == FITCLASS_GALAXY

    def version_like(o):
        return _replay_likelihood(_replay_exposures(o, cfg, plan), 23.0, cfg, plan)[1]

    full = adaptive_samples(version_like(ver), cfg)
    own = adaptive_versions(VersionLikelihoods([version_like(ver)]), plan.samples, cfg, np.inf)[0]
    keys = {(round(a, 9), round(b, 9)) for a, b in zip(plan.samples.e1, plan.samples.e2)}
    assert np.array_equal(own.e1, full.e1) and np.array_equal(own.e2, full.e2)
    assert np.array_equal(own.area, full.area)
    assert np.allclose(own.logpost, full.logpost, rtol=0, atol=1e-9, equal_nan=True)
    assert not all((round(a, 9), round(b, 9)) in keys for a, b in zip(own.e1, own.e2))   # new samples
    ea, eb = estimate(own, cfg), estimate(full, cfg)
    assert abs(ea.e1 - eb.e1) < 1e-9 and abs(ea.e2 - eb.e2) < 1e-9
    for first in (None, REPLAY_FIRST_MARGIN):   # the margins metacal's replays use
        d = adaptive_versions(VersionLikelihoods([version_like(ver)]), plan.samples, cfg, 10.0, first)[0]
        ed = estimate(d, cfg)
        assert abs(ed.e1 - eb.e1) < 1e-9 and abs(ed.e2 - eb.e2) < 1e-9
        assert np.count_nonzero(d.evaluated) < d.e1.size
    a, b, c = measure_versions([ref, ref, ver], 23.0, first_margin=REPLAY_FIRST_MARGIN, own_samples=True)
    assert abs(b.e1 - a.e1) < 1e-12 and abs(b.e2 - a.e2) < 1e-12
    assert abs(c.e1 - ed.e1) < 1e-12 and abs(c.e2 - ed.e2) < 1e-12
    replayed = measure_versions([ref, ver], 23.0)[1]
    assert np.hypot(replayed.e1 - c.e1, replayed.e2 - c.e2) > 1e-4


def test_replayed_grid_misses_the_response_through_its_choices():
    """benchmarks/metacal_grid_synthetic.py on made-up Gaussian likelihoods with the package's grids, priors and
    estimator: where the posterior cut is far in the tails (1e-6), the likelihood mean is the peak, and the replays'
    and own grids' responses are 1 (to 1e-4) and agree object by object; with the paper's cut at a width where the
    grid's step choice is borderline (0.05: about 30 samples above 5 % at a 0.04 step), the replays' R exceeds the
    own grids' (the choices' response: benchmarks/README.md, session 49) by more than 5 of its errors. Fails if a
    replay's samples or cells differ from the reference fit's, or if the script's pairing is broken."""
    from dataclasses import replace

    from scripts import load_script

    syn = load_script("benchmarks/metacal_grid_synthetic.py")
    seed = np.random.SeedSequence(7)
    far = replace(syn._settings([]), posterior_cut=1e-6)
    got = np.array(syn.responses((seed, 120, ("fixed", 0.05), "e", 0.3, 0.01, far)))
    assert np.all(np.abs(got[:, 0] - 1) < 1e-4) and np.all(np.abs(got[:, 0] - got[:, 1]) < 1e-4)
    got = np.array(syn.responses((seed, 400, ("fixed", 0.05), "e", 0.3, 0.01, syn._settings([]))))
    d = got[:, 0] - got[:, 1]
    assert d.mean() > 5 * d.std() / np.sqrt(d.size), (d.mean(), d.std())


def test_symmetrising_noise_cancels_the_noise_shear_under_elliptical_psfs_and_rotated_grids():
    """benchmarks/metacal_noise_symmetry.py in small, on exposures with elliptical Moffat PSFs and rotated (and
    flipped) pixel grids at delta = 0.01. The versions' expected noise power (from the impulse responses of the
    stamp's path and the added field's): without the symmetrising noise its spin-2 moments respond to the step
    (about 5 over every wavevector, 1.2 at low ones); with it what is left is below 2e-4 of that on average (the
    script: 1e-5 on 7000 exposures). The same on pure-noise stamps (Monte Carlo), within its errors. Fails if the added
    field's correlation does not end up turned by 90 degrees against the stamp noise's (neither turn made: its
    noise is then sheared as the stamp's; a turn back by +90 instead of -90 degrees is the same correlation)."""
    from scripts import load_script

    sym = load_script("benchmarks/metacal_noise_symmetry.py")
    rng = np.random.default_rng(11)
    exact, noisy = [], []
    for k, angle in enumerate((0.4, 1.3, 2.2, 3.0)):
        c, s = np.cos(angle), np.sin(angle)
        J = PIX * np.array([[c, -s], [s, c]]) @ np.diag([1.0, -1.0 if k % 2 else 1.0])
        for o in _obs(0.3, (0.2, 0.1), snr=20, n_exp=6, J=J, seed=k):
            exact.append(sym.expected_noise_response(o))
            noisy.append(sym.noise_shear_response(o, rng))
    exact, noisy = np.array(exact), np.array(noisy)   # (exposures, with / without, every K / low-pass, response)
    for band in (0, 1):
        without = exact[:, 1, band, :2].mean()
        assert without > 1.0
        assert abs(exact[:, 0, band, :2].mean()) < 2e-4 * without, (band, exact[:, 0, band, :2].mean(), without)
    resp = np.concatenate([noisy[:, :, 0, 0], noisy[:, :, 0, 1]])   # every K: dq1/dg1 and dq2/dg2
    without, with_ = resp[:, 1], resp[:, 0]
    assert without.mean() > 3.0
    assert abs(with_.mean()) < max(5 * with_.std() / np.sqrt(with_.size), 0.05 * without.mean()), with_.mean()


@pytest.mark.parametrize("shape", [(48, 48), (40, 33), (6, 6)])
def test_compiled_noise_and_weights_are_the_numpy_lines(shape):
    """metacal_observations' steps before and after the images (the masked stamp, the symmetrising noise times sigma,
    the grown mask and its edge, var_in; the versions' weights from the processed noise's variance), compiled, give the
    numpy lines' numbers to the bit: a stamp without masked pixels, one with a bad column, zero and varying weights
    (a cosmic ray's pixels), and a stamp all edge (var_in 1, var_out var_in)."""
    from shearfit.calib import kspace, metacal

    if not kspace.USE_KERNEL:
        pytest.skip("the compiled kernel is not built")
    rng = np.random.default_rng(11)
    for case in range(3):
        w = np.full(shape, 2.5e3)
        if case >= 1:
            w[:, shape[1] // 3] = 0.0
            w[shape[0] // 2, shape[1] // 2] = 0.0
        if case == 2:
            w *= rng.uniform(0.5, 2.0, shape)
        image = rng.normal(size=shape)
        units = rng.normal(size=shape)
        a, b = units.copy(), units.copy()
        want = metacal._noise_numpy(w, image, a)
        got = metacal._noise_compiled(w, image, b)
        assert np.array_equal(a, b) and np.array_equal(want[0], got[0]) and np.array_equal(want[1], got[1])
        assert got[2] == want[2] and (got[2] == 1.0) == (not (~want[1]).any())
        noise0 = rng.normal(scale=0.03, size=shape)
        assert np.array_equal(metacal._weight_numpy(noise0, want[1], w, want[2]),
                              metacal._weight_compiled(noise0, got[1], w, got[2]))


@pytest.mark.parametrize("psf", ["dilated", "round"])
def test_psf_tables_made_in_part_are_read_only_where_made(psf, monkeypatch):
    """An oversampled PSF image of its own at each object (PSFEx, Piff) has its padded table made only at the
    columns the bands read (kspace.padded_transform_within): with the columns not made set to NaN, the versions'
    images are those made from the whole tables, to the bit, for PSFs whose band lies within the stamp's Nyquist
    square (a third of the table made) and for an undersampled one whose band reaches beyond it (the table then
    made whole), on a rotated, sheared pixel grid."""
    from shearfit.calib import kspace, metacal

    J = PIX * np.array([[0.3, -0.95], [0.94, 0.31]])
    gal = galaxy_profile(0.3, 0.1, 0.2, -0.1, flux=1000.0)
    made = []
    for fwhm in (0.7, 0.45, 0.25):
        p = moffat_psf(fwhm, 3.0, 0.05, -0.03)
        im = draw_stamp(gal, p, J, (0.2, -0.1), stamp_size=48)
        obs = shearfit.Observation(image=im + np.random.default_rng(2).normal(0.0, 0.5, im.shape),
                                   weight=np.full(im.shape, 4.0), psf=draw_psf_image(p, J, size=48 * 3, oversampling=3),
                                   jacobian=J, psf_oversampling=3)
        metacal._PSF_TABLES.clear()
        with monkeypatch.context() as m:
            m.setattr(kspace, "UNMADE", np.nan)
            got = metacal_observations(obs, rng=np.random.default_rng(5), psf=psf)
            made.append(min(memo["columns"] / memo["table"].shape[1] for _, memo in metacal._PSF_TABLES.values()))
        metacal._PSF_TABLES.clear()
        with monkeypatch.context() as m:   # the whole tables
            m.setattr(metacal, "_psf_table", lambda im, n, columns, f=metacal._psf_table: f(im, n, n // 2 + 1))
            want = metacal_observations(obs, rng=np.random.default_rng(5), psf=psf)
        metacal._PSF_TABLES.clear()
        for name in want:
            assert np.all(np.isfinite(got[name].image)), (fwhm, name)
            assert np.array_equal(got[name].image, want[name].image), (fwhm, name)
            assert np.array_equal(got[name].weight, want[name].weight), (fwhm, name)
    assert made[0] < 0.5 and made[-1] == 1.0, made


def test_small_psf_images_are_dilated_afresh_as_the_memory_would_give_them(monkeypatch):
    """A PSF image of at most DILATE_DIRECT_MAX pixels a side is dilated afresh (not looked up by its contents), the
    same pixels as the remembered path's, normalised to unit sum and read-only; a wider one is remembered (the same
    array for an equal image)."""
    from shearfit.calib import metacal

    img = draw_psf_image(moffat_psf(0.7, 3.0, 0.05, -0.03), PIX * np.eye(2), size=25)
    img.setflags(write=False)
    fresh = metacal._dilated_psf(img, 1.02)
    assert not fresh.flags.writeable and abs(fresh.sum() - 1) < 1e-12
    assert metacal._dilated_psf(img, 1.02) is not fresh   # not remembered
    monkeypatch.setattr(metacal, "DILATE_DIRECT_MAX", 0)
    metacal._DILATED.clear()
    kept = metacal._dilated_psf(img, 1.02)
    assert np.array_equal(kept, fresh) and metacal._dilated_psf(img.copy(), 1.02) is kept

"""The ring-test statistics (shearfit.calib.bias) and the demo (shearfit.app.demo_stamps)."""

import math

import numpy as np
import pytest
import yaml
from astropy.table import Table

from shearfit.errors import ShearfitValueError
from shearfit.calib.bias import (bias_from_sums, format_with_error, galaxy_column, mean_shear,
                                          ring_sums, shear_bias, shear_bias_by_snr)

G = np.array([0.03, -0.02])
M_TRUE = np.array([0.04, -0.07])
C_TRUE = np.array([0.002, -0.003])


def ring_table(n_gal, n_rot, rng, m=M_TRUE, c=C_TRUE, g=G):
    """Objects e = (1 + m) s g + c + (noise that cancels exactly over each galaxy's ring).

    The intrinsic shape and a galaxy-level 'pixel noise' both rotate around the
    ring (so they sum to zero over it) and are shared by +g and -g; the weight
    is constant over a galaxy's objects, so the weighted ring sum of the noise
    vanishes too.
    """
    rows = []
    for i in range(n_gal):
        e_int = 0.3 * complex(*rng.normal(size=2))
        noise = 0.05 * complex(*rng.normal(size=2))
        w = rng.uniform(1.0, 20.0)
        snr = rng.uniform(10.0, 100.0)
        for sign in (+1, -1):
            for j in range(n_rot):
                rot = np.exp(2j * np.pi * j / n_rot)
                e = (1 + m) * sign * g + c + np.array([(e_int * rot).real, (e_int * rot).imag]) \
                    + np.array([(noise * rot).real, (noise * rot).imag])
                rows.append((i, sign, j, 0, e[0], e[1], w, snr))
    return Table(rows=rows, names=("galaxy", "sign", "rotation", "fitclass", "e1", "e2", "weight", "snr_target"))


def with_rejects(tab, n_gal, rng):
    """Append stars, failures and NaN shapes (as extra galaxies) that must not enter the means."""
    extra = []
    for k, (fitclass, e, w) in enumerate([(1, 0.9, 5.0), (-2, np.nan, np.nan), (0, np.nan, 3.0), (-5, 0.7, 0.0)]):
        for sign in (+1, -1):
            extra.append((n_gal + k, sign, 0, fitclass, e, -e, w, 50.0))
    out = tab.copy()
    for row in extra:
        out.add_row(row)
    return out, n_gal + 4


# --------------------------------------------------------------------------- estimator

@pytest.mark.parametrize("weighted", [True, False])
@pytest.mark.parametrize("n_rot", [2, 4])
def test_bias_exact_when_noise_cancels(weighted, n_rot):
    rng = np.random.default_rng(11)
    n_gal = 30
    tab, n_tot = with_rejects(ring_table(n_gal, n_rot, rng), n_gal, rng)
    sums = ring_sums(tab, n_tot, weighted=weighted)
    assert sums.shape == (3, n_tot, 2)
    assert np.all(sums[:, n_gal:] == 0)  # stars, failures and NaN shapes carry no weight
    est, err = shear_bias(sums, G, n_boot=200, rng=1)
    np.testing.assert_allclose(est, np.concatenate([M_TRUE, C_TRUE]), rtol=0, atol=1e-12)
    # every resampling gives the same m and c, up to rounding, when the noise cancels per galaxy
    assert np.all(np.isfinite(err)) and np.all(err < 1e-10)
    mean, mean_err = mean_shear(sums, n_boot=50, rng=2)
    np.testing.assert_allclose(mean[0], (1 + M_TRUE) * G + C_TRUE, atol=1e-12)
    np.testing.assert_allclose(mean[1], -(1 + M_TRUE) * G + C_TRUE, atol=1e-12)


def test_bias_works_on_structured_arrays_and_mappings():
    rng = np.random.default_rng(5)
    tab = ring_table(5, 4, rng)
    ref = ring_sums(tab, 5)
    np.testing.assert_array_equal(ring_sums(tab.as_array(), 5), ref)
    np.testing.assert_array_equal(ring_sums({k: np.asarray(tab[k]) for k in tab.colnames}, 5), ref)


def test_bootstrap_error_matches_analytic_standard_error():
    # e_(i,+-) = +-(1 + m) g + c + a_i +- d_i, one object per sign, unit weights: then exactly
    # m_hat = m + mean(d) / g and c_hat = c + mean(a), with standard errors std / sqrt(N).
    rng = np.random.default_rng(2024)
    n_gal = 400
    a = rng.normal(0.0, 0.01, size=(n_gal, 2))
    d = rng.normal(0.0, 0.004, size=(n_gal, 2))
    rows = []
    for i in range(n_gal):
        for sign in (+1, -1):
            e = sign * (1 + M_TRUE) * G + C_TRUE + a[i] + sign * d[i]
            rows.append((i, sign, 0, e[0], e[1], 1.0))
    tab = Table(rows=rows, names=("galaxy", "sign", "fitclass", "e1", "e2", "weight"))
    est, err = shear_bias(ring_sums(tab, n_gal, weighted=False), G, n_boot=4000, rng=np.random.default_rng(7))
    np.testing.assert_allclose(est[:2], M_TRUE + d.mean(axis=0) / G, atol=1e-12)
    np.testing.assert_allclose(est[2:], C_TRUE + a.mean(axis=0), atol=1e-12)
    analytic = np.concatenate([d.std(axis=0, ddof=1) / np.sqrt(n_gal) / np.abs(G),
                               a.std(axis=0, ddof=1) / np.sqrt(n_gal)])
    np.testing.assert_allclose(err, analytic, rtol=0.2)


def test_bias_edge_cases():
    rng = np.random.default_rng(3)
    tab = ring_table(1, 4, rng)
    sums = ring_sums(tab, 1)
    est, err = shear_bias(sums, G, n_boot=100, rng=0)
    np.testing.assert_allclose(est, np.concatenate([M_TRUE, C_TRUE]), atol=1e-12)
    assert np.all(np.isnan(err))  # one galaxy: no bootstrap error
    # a zero shear component has no m, but c is still measured
    est0 = bias_from_sums(ring_sums(ring_table(3, 4, rng, g=np.array([0.02, 0.0])), 3), [0.02, 0.0])
    assert math.isfinite(est0[0]) and math.isnan(est0[1]) and np.all(np.isfinite(est0[2:]))
    # all weights zero: NaN, no warning (RuntimeWarnings from shearfit are errors in this suite)
    tab["weight"] = 0.0
    est, err = shear_bias(ring_sums(tab, 1), G, n_boot=10, rng=0)
    assert np.all(np.isnan(est))
    with pytest.raises(ShearfitValueError):
        ring_sums(tab, 0)


def test_bias_by_snr_bins():
    rng = np.random.default_rng(8)
    n_gal = 40
    tab = ring_table(n_gal, 4, rng)
    sums = ring_sums(tab, n_gal)
    snr = galaxy_column(tab, "snr_target", n_gal)
    assert snr.shape == (n_gal,) and np.all((snr >= 10) & (snr <= 100))
    edges = [10, 30, 60, 100]
    bins = shear_bias_by_snr(sums, snr, edges, G, n_boot=50, rng=1)
    assert [b["lo"] for b in bins] == [10, 30, 60] and [b["hi"] for b in bins] == [30, 60, 100]
    assert sum(b["n_galaxies"] for b in bins) == n_gal
    assert sorted(np.concatenate([b["galaxies"] for b in bins]).tolist()) == list(range(n_gal))
    for b in bins:
        if b["n_galaxies"] >= 2:
            np.testing.assert_allclose(b["estimate"], np.concatenate([M_TRUE, C_TRUE]), atol=1e-12)
    with pytest.raises(ShearfitValueError):
        shear_bias_by_snr(sums, snr[:-1], edges, G)
    with pytest.raises(ShearfitValueError):
        shear_bias_by_snr(sums, snr, [30, 10], G)


def test_format_with_error():
    assert format_with_error(0.0123, 0.0045) == " +0.01230 +/-  0.00450"
    assert format_with_error(-1.5, 0.25, scale=10, digits=1) == "-15.0 +/-  2.5"
    assert format_with_error(float("nan"), 0.1).strip() == "nan"
    assert format_with_error(0.1, float("nan")).endswith("nan")


# --------------------------------------------------------------------------- demo

def test_run_demo_small(tmp_path):
    from shearfit.app.demo_stamps import OBJECTS_FILE, SUMMARY_FILE, run_demo

    # 3 galaxies x 4 orientations x 2 shears = 24 objects on 3 exposures at high SNR: about 10 s
    # at the engine's speed of this writing (0.3 - 0.6 s per object). Two galaxies or two
    # orientations give bootstrap errors that mean little (a full ring of 4 is needed for the
    # shape noise to cancel beyond first order).
    g = (0.03, -0.02)
    out = tmp_path / "demo"
    s = run_demo(out_dir=out, n_galaxies=3, n_rotations=4, n_exposures=3, snr_range=(200, 200), shear=g,
                 processes=1, quiet=True, seed=1)

    # outputs exist and are well formed
    obj, summ = out / OBJECTS_FILE, out / SUMMARY_FILE
    assert obj.is_file() and summ.is_file()
    assert sorted(p.name for p in out.iterdir()) == sorted([OBJECTS_FILE, SUMMARY_FILE])  # no temporary left
    tab = Table.read(obj)
    assert len(tab) == 24 == s["n_objects"]
    for col in ("galaxy", "sign", "rotation", "e1", "e2", "weight", "fitclass", "snr", "mag", "time"):
        assert col in tab.colnames
    assert sorted(set(tab["sign"].tolist())) == [-1, 1]
    assert np.all(np.isfinite(tab["time"]))
    on_disk = yaml.safe_load(summ.read_text())
    assert on_disk["seed"] == 1 and on_disk["input_shear"] == list(g)
    assert on_disk["config"]["truncation"] == 4.5  # the resolved engine configuration
    assert on_disk["bias"] == pytest.approx(s["bias"])
    assert s["outputs"] == {"objects": str(obj.resolve()), "summary": str(summ.resolve())}

    # the numbers
    fc = s["fitclass"]
    assert fc["galaxy"] + fc["star"] + fc["failed"] == pytest.approx(1.0)
    assert fc["galaxy"] >= 0.5
    for k in ("m1", "m2", "c1", "c2"):
        assert math.isfinite(s["bias"][k]), k
        assert math.isfinite(s["bias_err"][k]) and s["bias_err"][k] >= 0, k
    plus, minus = np.array(s["mean_shear"]["plus"]), np.array(s["mean_shear"]["minus"])
    shear_hat = 0.5 * (plus - minus)  # (1 + m) g: the additive part cancels
    assert np.all(np.sign(shear_hat) == np.sign(g))
    for k in ("m1", "m2"):
        assert abs(s["bias"][k]) < 5 * s["bias_err"][k] + 0.05, (k, s["bias"][k], s["bias_err"][k])
    for k in ("c1", "c2"):
        assert abs(s["bias"][k]) < 5 * s["bias_err"][k] + 0.02, (k, s["bias"][k], s["bias_err"][k])
    t = s["timing"]
    assert t["objects_per_s_per_process"] > 0 and t["processes"] == 1


def test_run_demo_rejects_bad_input():
    from shearfit.app.demo_stamps import run_demo

    with pytest.raises(ShearfitValueError):
        run_demo(n_galaxies=0, quiet=True)
    with pytest.raises(ShearfitValueError):
        run_demo(snr_range=(50, 20), quiet=True)
    with pytest.raises(ShearfitValueError):
        run_demo(shear=(0.9, 0.9), quiet=True)


def test_field_demo_m_is_the_weighted_means_response():
    """The field demo's m is the response of the weighted mean ellipticity with each field's own weights (which
    depend on |e| and so on the shear); its c comes from the residuals e - e_int with the pair's mean weight."""
    from astropy.table import Table

    from shearfit.app.demo import _pair_bias
    from shearfit.calib.calibrate import sheared_ellipticity

    rng = np.random.default_rng(3)
    n = 400
    eint = rng.normal(0, 0.25, (n, 2))
    eint[1::2] = -eint[0::2]                       # 90-degree twins
    g = np.array([0.04, -0.03])
    tabs, means = [], []
    for sign in (1, -1):
        es = sheared_ellipticity(eint[:, 0] + 1j * eint[:, 1], sign * (g[0] + 1j * g[1]))
        w = 1.0 / (0.09 + 0.5 * np.abs(es) ** 2)
        tabs.append(Table({"id": np.arange(n), "e1": es.real + 0.002, "e2": es.imag, "e1_int": eint[:, 0],
                           "e2_int": eint[:, 1], "weight": w, "m": np.full(n, -0.1)}))
        means.append(np.array([np.sum(w * es.real), np.sum(w * es.imag)]) / np.sum(w))
    est, err, n_pairs, K = _pair_bias(tabs[0], tabs[1], g, n_boot=20)
    ring = (means[0] - means[1]) / (2 * g) - 1
    assert est[0] == pytest.approx(ring[0], abs=1e-12) and est[1] == pytest.approx(ring[1], abs=1e-12)
    assert ring[0] < -0.05                         # the weights' response, which e - e_int would not show
    assert est[2] == pytest.approx(0.002, abs=2e-3) and abs(est[3]) < 2e-3
    assert n_pairs == n and K == pytest.approx(-0.1)

"""``shearfit calibrate``: bins, m and c per bin, the (alpha, beta) fit, closure on a synthetic catalogue."""

import numpy as np
import pytest
import yaml
from astropy.table import Table

from shearfit.calib.calibrate import _fit_mc, _group_codes, _residuals
from shearfit.calib.calibrate import (PAPER_ALPHA, CalibrationModel, bin_indices, calibrate, calibrated_bias,
                                      calibration_m, load_calibration, matched_galaxies, read_calibration,
                                      quantity_bins, sheared_ellipticity, stack_matched, write_calibration)
from shearfit.app.cli import main
from shearfit.errors import ShearfitIOError, ShearfitValueError

ALPHA, BETA = 0.08, -0.6


def _synthetic(tmp_path, n=40000, seed=0, alpha=ALPHA, beta=BETA, const_shear=False, c=(0.002, -0.001)):
    """Measured and truth tables whose ellipticities carry m(nu, r) of (alpha, beta), c and noise."""
    rng = np.random.default_rng(seed)
    snr = np.exp(rng.uniform(np.log(7), np.log(80), n))
    r = np.exp(rng.uniform(np.log(0.1), np.log(1.0), n))
    g = np.full((n, 2), [0.03, -0.02]) if const_shear else rng.normal(0, 0.05, (n, 2))
    eint = rng.normal(0, 0.25, (n, 2))
    m = calibration_m(snr, r, alpha, beta)
    noise = rng.normal(0, 1, (n, 2)) * (2.0 / snr)[:, None]
    e = eint + (1 + m)[:, None] * g + np.array(c) + noise
    w = 1.0 / (0.25 ** 2 + (2.0 / snr) ** 2)
    ids = np.arange(n)
    meas = Table({"id": ids, "e1": e[:, 0], "e2": e[:, 1], "weight": w, "fitclass": np.zeros(n, int), "snr": snr,
                  "scalelength": r})
    truth = Table({"id": ids, "g1": g[:, 0], "g2": g[:, 1], "e1_int": eint[:, 0], "e2_int": eint[:, 1],
                   "is_star": np.zeros(n, bool)})
    # a star and an unmeasured object, which the calibration must leave out
    meas.add_row((n, 0.0, 0.0, 0.0, 1, 100.0, 0.0))
    truth.add_row((n, 0.0, 0.0, 0.0, 0.0, True))
    meas.add_row((n + 1, np.nan, np.nan, 0.0, -2, np.nan, np.nan))
    truth.add_row((n + 1, 0.01, 0.0, 0.1, 0.0, False))
    mp, tp = tmp_path / f"m{seed}.fits", tmp_path / f"t{seed}.fits"
    meas.write(mp)
    truth.write(tp)
    return mp, tp


def test_bins_have_equal_numbers_and_shrink_for_small_samples():
    rng = np.random.default_rng(1)
    snr, r = rng.uniform(5, 50, 4000), rng.uniform(0.1, 1, 4000)
    idx, ns, nr = bin_indices(snr, r, 20, 20, min_per_bin=10)
    assert (ns, nr) == (20, 20)
    counts = np.bincount(idx, minlength=400)
    assert counts.min() == 10 and counts.max() == 10
    idx, ns, nr = bin_indices(snr[:500], r[:500], 20, 20, min_per_bin=50)
    assert ns * nr * 50 <= 500 and np.bincount(idx).min() >= 50 // 2


def test_recovers_alpha_beta_and_closes(tmp_path):
    mp, tp = _synthetic(tmp_path)
    res, bins, tab = calibrate([(mp, tp)], n_snr=8, n_size=8, n_boot=30)
    assert len(tab) == 40000                  # star and failed fit left out
    # the fitted parameters agree with the input within 3 sigma (errors from the bins' bootstrap)
    assert abs(res["alpha"] - ALPHA) < 3 * res["alpha_err"] + 1e-3
    assert abs(res["beta"] - BETA) < 3 * res["beta_err"]
    assert res["c1"] == pytest.approx(0.002, abs=2e-3) and res["c2"] == pytest.approx(-0.001, abs=2e-3)
    assert np.array(res["loglike"]).shape == (len(res["grid_alpha"]), len(res["grid_beta"]))
    # closure on an independent sample: the calibrated m is zero within its statistical reach
    mp2, tp2 = _synthetic(tmp_path, seed=5)
    cb = calibrated_bias(matched_galaxies(mp2, tp2), (res["alpha"], res["beta"]))
    assert cb["m_raw"] < -0.05                # a real noise bias to correct
    assert abs(cb["m_cal"]) < 0.015


def test_constant_shear_is_refused(tmp_path):
    mp, tp = _synthetic(tmp_path, n=2000, const_shear=True)
    with pytest.raises(ShearfitValueError, match="shear is the same"):
        calibrate([(mp, tp)])


def test_cli_writes_yaml_bins_plot_and_reads_back(tmp_path, capsys):
    mp, tp = _synthetic(tmp_path, n=6000)
    out = tmp_path / "cal.yaml"
    assert main(["calibrate", str(mp), str(tp), "--out", str(out), "--n-snr", "4", "--n-size", "4",
                 "--bootstrap", "10", "--model", "paper", "--size", "scalelength"]) == 0
    assert "alpha =" in capsys.readouterr().out
    assert (tmp_path / "cal_bins.fits").exists() and (tmp_path / "cal.png").exists()
    a, b = read_calibration(out)
    d = yaml.safe_load(out.read_text())
    assert (a, b) == (d["alpha"], d["beta"]) and d["paper_alpha"] == 0.057


def test_bad_inputs_name_the_file(tmp_path):
    mp, tp = _synthetic(tmp_path, n=500)
    Table({"id": [1]}).write(tmp_path / "bad.fits")
    with pytest.raises(ShearfitIOError, match="bad.fits: no column g1"):
        matched_galaxies(mp, tmp_path / "bad.fits")
    (tmp_path / "c.yaml").write_text("alpha: 0.1\n")
    with pytest.raises(ShearfitIOError, match="c.yaml: calibration has no key 'beta'"):
        read_calibration(tmp_path / "c.yaml")


def _paired_fields(tmp_path, n=6000, seed=3, shared=True, psf_range=None, m_offset=0.0):
    """Two fields of the same galaxies and noise (truth header SEED), shears +g and -g. With ``psf_range``
    (arcsec), each galaxy has a PSF FWHM drawn from it (column psf_fwhm) and its m depends on the resolution
    r / psf_fwhm (as m(nu, r) at r = 0.7 r / psf_fwhm): a larger PSF, a more negative m at the same r.
    ``m_offset`` is added to every galaxy's m (a seed's fields with PSFs of their own)."""
    rng = np.random.default_rng(seed)
    snr = np.exp(rng.uniform(np.log(7), np.log(80), n))
    r = np.exp(rng.uniform(np.log(0.1), np.log(1.0), n))
    eint = rng.normal(0, 0.25, (n, 2))
    psf = None if psf_range is None else rng.uniform(*psf_range, n)
    m = calibration_m(snr, r if psf is None else 0.7 * r / psf, ALPHA, BETA) + m_offset
    noise = rng.normal(0, 1, (n, 2)) * (2.0 / snr)[:, None]
    pairs = []
    for tag, sign in (("p", 1.0), ("m", -1.0)):
        g = sign * np.array([0.04, -0.03])
        own = noise if shared else rng.normal(0, 1, (n, 2)) * (2.0 / snr)[:, None]
        e = eint + (1 + m)[:, None] * g + own + 0.01 * rng.normal(0, 1, (n, 2)) * (2.0 / snr)[:, None]
        w = 1.0 / (0.25 ** 2 + (2.0 / snr) ** 2)
        ids = np.arange(n)
        meas = Table({"id": ids, "e1": e[:, 0], "e2": e[:, 1], "weight": w, "fitclass": np.zeros(n, int),
                      "snr": snr * (1 + 0.01 * rng.normal(size=n)), "scalelength": r, "m_true": m})
        if psf is not None:
            meas["psf_fwhm"] = psf
        truth = Table({"id": ids, "g1": np.full(n, g[0]), "g2": np.full(n, g[1]), "e1_int": eint[:, 0],
                       "e2_int": eint[:, 1], "is_star": np.zeros(n, bool)})
        truth.meta["SEED"] = seed
        name = f"{tag}{int(shared)}" + ("" if psf is None else f"_{psf_range[0]:g}") + f"_{seed}"
        mp, tp = tmp_path / f"pm{name}.fits", tmp_path / f"pt{name}.fits"
        meas.write(mp)
        truth.write(tp)
        pairs.append((mp, tp))
    return pairs


def test_fields_from_one_seed_pair_up_and_their_noise_cancels(tmp_path):
    pairs = _paired_fields(tmp_path)
    res, bins, tab = calibrate(pairs, n_snr=4, n_size=4, n_boot=50)
    # each galaxy's +g and -g rows form one group and share a bin
    assert res["n_groups"] == 6000 and res["n_galaxies"] == 12000
    groups = np.asarray(tab["group"])
    assert len(np.unique(groups)) == 6000
    # the shared noise cancels: m per bin is precise, and the errors (groups resampled together) know it;
    # each bin's m is the weighted mean of its galaxies' m (bins as calibrate makes them)
    assert np.median(bins["m_err"]) < 0.01
    idx, ns, nr = bin_indices(tab["snr"], tab["scalelength"], 4, 4, groups=_group_codes(tab))
    w, mt = np.asarray(tab["weight"], float), np.asarray(tab["m_true"], float)
    pred = np.array([np.sum((w * mt)[idx == b]) / np.sum(w[idx == b]) for b in bins["bin"]])
    pulls = (np.asarray(bins["m"]) - pred) / np.asarray(bins["m_err"])
    assert np.all(np.abs(pulls) < 5) and 0.4 < np.std(pulls) < 2.0
    cb = calibrated_bias(tab, (ALPHA, BETA))
    assert abs(cb["m_cal"]) < 4 * cb["m_cal_err"] and cb["m_cal_err"] < 0.003
    # without shared noise the same sample measures m ten times less precisely
    res_ind, bins_ind, tab_ind = calibrate(_paired_fields(tmp_path, shared=False), n_snr=4, n_size=4, n_boot=50)
    assert np.median(bins_ind["m_err"]) > 5 * np.median(bins["m_err"])


def test_m_is_the_response_of_the_weighted_mean_including_the_weights(tmp_path):
    """lensfit's weight depends on |e|: a galaxy sheared along its major axis is weighted differently at +g
    and -g, so the weighted mean ellipticity responds to shear by more than its galaxies do. With an exact
    estimator (e the true sheared ellipticity) and such weights, m is that response: the difference of the
    +g and -g fields' weighted means over 2g, as the ring test measures it, not the zero of the residuals
    e - e_s (which subtract the weights' response with e_s)."""
    rng = np.random.default_rng(4)
    n = 20000
    eint = rng.normal(0, 0.25, (n, 2))
    g = np.array([0.04, -0.03])
    pairs, means = [], []
    for tag, sign in (("p", 1.0), ("m", -1.0)):
        es = sheared_ellipticity(eint[:, 0] + 1j * eint[:, 1], sign * (g[0] + 1j * g[1]))
        w = 1.0 / (0.3 ** 2 + 0.5 * np.abs(es) ** 2)
        meas = Table({"id": np.arange(n), "e1": es.real, "e2": es.imag, "weight": w, "fitclass": np.zeros(n, int),
                      "snr": np.full(n, 20.0), "scalelength": np.full(n, 0.3)})
        truth = Table({"id": np.arange(n), "g1": np.full(n, sign * g[0]), "g2": np.full(n, sign * g[1]),
                       "e1_int": eint[:, 0], "e2_int": eint[:, 1], "is_star": np.zeros(n, bool)})
        truth.meta["SEED"] = 7
        meas.write(tmp_path / f"wm{tag}.fits")
        truth.write(tmp_path / f"wt{tag}.fits")
        pairs.append((tmp_path / f"wm{tag}.fits", tmp_path / f"wt{tag}.fits"))
        means.append(np.array([np.sum(w * es.real), np.sum(w * es.imag)]) / np.sum(w))
    ring = float((means[0] - means[1]) @ g / (2 * g @ g)) - 1
    tab = stack_matched(pairs)
    cb = calibrated_bias(tab, (PAPER_ALPHA, 0.0))            # beta = 0: no correction
    assert cb["m_raw"] == pytest.approx(ring, abs=1e-12)
    assert ring < -0.02                                       # weights falling with |e| damp the response
    assert abs(_fit_mc(*_residuals(tab))[0]) < 2e-3           # which the residuals' fit does not see
    res, bins, _ = calibrate(pairs, n_snr=2, n_size=2, n_boot=5)
    assert res["m_raw"] == pytest.approx(ring, abs=1e-12)


def test_cli_takes_several_pairs_and_refuses_an_odd_count(tmp_path, capsys):
    (mp, tp), (mm, tm) = _paired_fields(tmp_path, n=3000, psf_range=(0.6, 0.8))
    out = tmp_path / "cal2.yaml"
    assert main(["calibrate", str(mp), str(tp), str(mm), str(tm), "--out", str(out), "--n-snr", "3",
                 "--n-size", "3", "--bootstrap", "10"]) == 0
    d = yaml.safe_load(out.read_text())
    assert d["n_galaxies"] == 6000 and len(d["measured"]) == 2
    assert main(["calibrate", str(mp), str(tp), str(mm), "--out", str(out)]) != 0
    assert "has no partner" in capsys.readouterr().err


def test_binned_model_closes_where_the_paper_form_cannot(tmp_path):
    """m(nu, r) unlike the paper's form: the binned table applies each bin's m and closes; the form does not."""
    rng = np.random.default_rng(8)
    n = 60000
    snr = np.exp(rng.uniform(np.log(7), np.log(80), n))
    r = np.exp(rng.uniform(np.log(0.1), np.log(1.0), n))
    m_true = -0.4 * (r < 0.2) - 3.0 / snr       # a step in size: no alpha, beta gives it

    def field(seed):
        g = np.random.default_rng(seed).normal(0, 0.05, (n, 2))
        e = (1 + m_true)[:, None] * g + rng.normal(0, 1, (n, 2)) * 0.02
        meas = Table({"id": np.arange(n), "e1": e[:, 0], "e2": e[:, 1], "weight": np.ones(n),
                      "fitclass": np.zeros(n, int), "snr": snr, "scalelength": r})
        truth = Table({"id": np.arange(n), "g1": g[:, 0], "g2": g[:, 1], "e1_int": np.zeros(n),
                       "e2_int": np.zeros(n), "is_star": np.zeros(n, bool)})
        mp, tp = tmp_path / f"bm{seed}.fits", tmp_path / f"bt{seed}.fits"
        meas.write(mp)
        truth.write(tp)
        return mp, tp

    res, bins, tab = calibrate([field(1)], n_snr=6, n_size=6, n_boot=20)
    assert res["model"] == "binned" and np.asarray(res["binned"]["m"]).shape == (6, 6)
    test = matched_galaxies(*field(2))
    binned = calibrated_bias(test, CalibrationModel(res["alpha"], res["beta"], "binned", res["binned"]))
    form = calibrated_bias(test, (res["alpha"], res["beta"]))
    assert binned["m_raw"] < -0.1
    assert abs(binned["m_cal"]) < 3 * binned["m_cal_err"] + 2e-3
    assert abs(form["m_cal"]) > 5 * form["m_cal_err"]
    # written and read back, the model is the binned one, and its draws scatter within the errors
    out = tmp_path / "cal.yaml"
    write_calibration(res, out)
    model = load_calibration(out)
    assert model.kind == "binned"
    np.testing.assert_allclose(model.m(snr[:50], r[:50]), CalibrationModel(
        res["alpha"], res["beta"], "binned", res["binned"]).m(snr[:50], r[:50]))
    d = model.draws(200, np.random.default_rng(0))
    spread = np.std([x.m(np.array([30.0]), np.array([0.5]))[0] for x in d])
    assert 0.2 * np.median(np.asarray(res["binned"]["m_err"])) < spread < 5 * np.max(np.asarray(res["binned"]["m_err"]))


def _packaged_table(path, model):
    """A packaged calibration (benchmarks/calibration_closure.py --write-default) as the pipeline applies it:
    binned, its source the closure script, over 10 000 measurements, |calibrated m| on the held-out test set
    within 3 sigma of 0 and below the raw m, every bin's m finite and between -1 and 1. Returns the file's
    record and the bins' m."""
    assert model.kind == "binned"
    d = yaml.safe_load(open(path))
    assert "calibration_closure.py" in d["source"] and d["n_galaxies"] > 10000
    test = d["closure"]["test set, binned"]
    assert abs(test["m_cal"]) < 3 * test["m_cal_err"] < abs(test["m_raw"])
    m = np.asarray(d["binned"]["m"], float)
    assert np.all(np.isfinite(m)) and np.all(np.abs(m) < 1)
    return d, m


def test_the_default_calibration_is_the_packaged_binned_table():
    """Without a calibration file the pipeline applies the package's binned table, fitted on shearfit's own
    simulated fields, which records how it was made and what it leaves on held-out fields (_packaged_table)."""
    from shearfit.calib.calibrate import DEFAULT_CALIBRATION, default_calibration

    model = default_calibration()
    d, _ = _packaged_table(DEFAULT_CALIBRATION, model)
    # a table in resolution (scalelength / psf_fwhm) per range of seeing, three ranges fitted on fields of PSF FWHM
    # 0.55-0.85", 0.85-1.05" and 1.05-1.25": closing on held-out fields of each, and taking most of the bias away
    # on fields of a seeing beyond its own (1.25-1.45")
    assert model.size == "resolution" and d["size"] == "resolution" and len(d["seeing"]["tables"]) == 3
    for lo_hi in ("0.85-1.05", "1.05-1.25"):
        held = [v for k, v in d["closure"].items() if k.startswith(f"transfer-psf-{lo_hi} (")]
        assert held and abs(held[0]["m_cal"]) < 3 * held[0]["m_cal_err"] < abs(held[0]["m_raw"])
    beyond = [v for k, v in d["closure"].items() if k.startswith("transfer-psf-1.25-1.45 (")]
    assert beyond and abs(beyond[0]["m_cal"]) < 0.5 * abs(beyond[0]["m_raw"])
    # a faint small galaxy gets a larger correction than a bright large one
    faint, bright = model.m(np.array([9.0, 150.0]), np.array([0.15, 0.8]), np.array([0.75, 0.75]))
    assert faint < bright < 0.05


def test_self_calibrated_fits_have_their_own_packaged_calibration():
    """``default_calibration(self_calibration=True)`` is a second such table, fitted on the same simulated
    fields with ``self_calibration: true`` in force (its source says so); it differs from the plain fit's."""
    from shearfit.calib.calibrate import DEFAULT_CALIBRATION, DEFAULT_CALIBRATION_SELFCAL, default_calibration

    d, m = _packaged_table(DEFAULT_CALIBRATION_SELFCAL, default_calibration(self_calibration=True))
    assert "self_calibration=true" in d["source"]
    plain = np.asarray(yaml.safe_load(open(DEFAULT_CALIBRATION))["binned"]["m"], float)
    assert m.shape != plain.shape or not np.allclose(m, plain)
    # in resolution with a table per seeing range, as the plain fit's
    assert d["size"] == "resolution" and len(d["seeing"]["tables"]) == 3


def test_a_resolution_table_carries_to_another_seeing(tmp_path):
    """m that depends on the scalelength over the PSF size: a table in arcsec fitted under one seeing leaves a
    bias under another; a table in resolution (scalelength / psf_fwhm) does not."""
    cal = _paired_fields(tmp_path, n=20000, seed=5, psf_range=(0.55, 0.85))
    other = stack_matched(_paired_fields(tmp_path, n=20000, seed=6, psf_range=(0.85, 1.05)))
    res_r, _, _ = calibrate(cal, n_snr=8, n_size=8, n_boot=10, size="resolution")
    res_s, _, _ = calibrate(cal, n_snr=8, n_size=8, n_boot=10, size="scalelength")
    assert res_r["size"] == "resolution" and res_s["size"] == "scalelength"
    by_res = calibrated_bias(other, CalibrationModel(res_r["alpha"], res_r["beta"], "binned", res_r["binned"],
                                                     size="resolution"), n_boot=50)
    by_r = calibrated_bias(other, CalibrationModel(res_s["alpha"], res_s["beta"], "binned", res_s["binned"]), n_boot=50)
    assert by_res["m_raw"] < -0.05                      # the other seeing's galaxies are biased ...
    assert abs(by_res["m_cal"]) < 3 * by_res["m_cal_err"] + 0.003     # ... and the resolution table removes it
    assert by_r["m_cal"] < -0.01 and by_r["m_cal"] < -5 * by_r["m_cal_err"]   # the arcsec table leaves part
    # the written table records its axis and reads back as such
    write_calibration(res_r, tmp_path / "res.yaml")
    model = load_calibration(tmp_path / "res.yaml")
    assert model.size == "resolution"
    np.testing.assert_array_equal(model.m_of(other), CalibrationModel(
        res_r["alpha"], res_r["beta"], "binned", res_r["binned"], size="resolution").m_of(other))
    with pytest.raises(ShearfitValueError, match="psf_fwhm"):
        model.m(other["snr"], other["scalelength"])


def test_a_resolution_calibration_names_catalogues_without_psf_fwhm(tmp_path):
    mp, tp = _synthetic(tmp_path, n=2000)
    with pytest.raises(ShearfitIOError, match=f"{mp.name}: no column psf_fwhm"):
        calibrate([(mp, tp)], n_snr=2, n_size=2, size="resolution")


def test_the_table_closes_on_its_own_galaxies(tmp_path):
    """The bins' m (intercepts held at the whole table's) average to the whole table's m: calibrated with its own
    table, the calibration set's m is 0 to the precision of the look-up (a galaxy's copies looked up by their own
    SNR and size, binned by their mean)."""
    pairs = _paired_fields(tmp_path, n=20000, seed=8, psf_range=(0.6, 0.9))
    res, _, tab = calibrate(pairs, n_snr=12, n_size=12, n_boot=5, size="resolution")
    own = calibrated_bias(tab, CalibrationModel(res["alpha"], res["beta"], "binned", res["binned"],
                                                size="resolution"), n_boot=5)
    assert own["m_raw"] < -0.05 and abs(own["m_cal"]) < 1e-3


def test_tables_per_seeing_range(tmp_path):
    """m that depends on the PSF size beyond the resolution: a table per seeing range (calibrate seeing_bins=2)
    closes on held-out galaxies of both ranges, where one table over both leaves opposite biases."""
    def fields(seed, psf_range):
        pairs = _paired_fields(tmp_path, n=12000, seed=seed, psf_range=psf_range)
        for mp, _ in pairs:   # m grows by a further 3 % per 0.1" of PSF FWHM above 0.8"
            t = Table.read(mp)
            extra = -0.3 * (np.asarray(t["psf_fwhm"]) - 0.8)
            g = np.array([0.04, -0.03]) * (1 if "pmp" in str(mp) else -1)
            t["e1"] += extra * g[0]
            t["e2"] += extra * g[1]
            t.write(mp, overwrite=True)
        return pairs

    cal = fields(10, (0.55, 0.85)) + fields(11, (0.85, 1.05))
    small, large = stack_matched(fields(12, (0.55, 0.85))), stack_matched(fields(13, (0.85, 1.05)))
    res, _, _ = calibrate(cal, n_snr=8, n_size=8, n_boot=10, size="resolution", seeing_bins=2)
    assert len(res["seeing"]["tables"]) == 2 and 0.8 < res["seeing"]["psf_edges"][0] < 0.9
    split = CalibrationModel(res["alpha"], res["beta"], "binned", res["binned"], size="resolution",
                             seeing=res["seeing"])
    one = CalibrationModel(res["alpha"], res["beta"], "binned", res["binned"], size="resolution")
    for tab in (small, large):
        b = calibrated_bias(tab, split, n_boot=30)
        assert abs(b["m_cal"]) < 3 * b["m_cal_err"] + 0.003
    assert calibrated_bias(small, one, n_boot=5)["m_cal"] > 0.01 > -0.01 > calibrated_bias(large, one, n_boot=5)["m_cal"]
    write_calibration(res, tmp_path / "seeing.yaml")
    back = load_calibration(tmp_path / "seeing.yaml")
    np.testing.assert_array_equal(back.m_of(large), split.m_of(large))
    assert len(back.draws(2, np.random.default_rng(0))[0].seeing["tables"]) == 2


def test_a_bootstrap_over_seeds_sees_the_fields_own_scatter(tmp_path):
    """Each seed's fields have PSFs of their own, which move m from field to field by more than the galaxies'
    noise: here every seed's galaxies have an m offset of their own (rms 0.03). The bootstrap over galaxies does
    not see it; the one over seeds gives about the offsets' scatter over the root of their number, whole and in
    bins, and a single seed has no such error."""
    offsets = np.random.default_rng(11).normal(0.0, 0.03, 10)
    pairs = [p for k, off in enumerate(offsets) for p in _paired_fields(tmp_path, n=800, seed=100 + k, m_offset=off)]
    tab = stack_matched(pairs)
    cal = (ALPHA, BETA)
    gal = calibrated_bias(tab, cal, n_boot=300)
    by_seed = calibrated_bias(tab, cal, n_boot=300, resample="seeds")
    expected = np.std(offsets, ddof=1) / np.sqrt(offsets.size)
    assert gal["m_cal_err"] < 0.3 * expected
    assert 0.6 * expected < by_seed["m_cal_err"] < 1.5 * expected
    # the same estimate either way: only the errors differ
    assert by_seed["m_cal"] == gal["m_cal"]
    assert abs(gal["m_cal"] - np.mean(offsets)) < 3 * expected
    qg = quantity_bins(tab, "snr", cal, n=3, n_boot=200)
    qs = quantity_bins(tab, "snr", cal, n=3, n_boot=200, resample="seeds")
    assert np.all(np.asarray(qs["m_cal_err"]) > 2 * np.asarray(qg["m_cal_err"]))
    assert np.allclose(qs["m_cal"], qg["m_cal"])
    one = stack_matched(pairs[:2])
    assert np.isnan(calibrated_bias(one, cal, n_boot=20, resample="seeds")["m_cal_err"])
    with pytest.raises(ShearfitValueError, match="resample"):
        calibrated_bias(one, cal, resample="fields")

"""benchmarks/ring_test.py's checkpoint: a stopped run continued with --resume gives the uninterrupted run's table."""

import os
import re

import numpy as np
import pytest
from astropy.table import Table

from scripts import load_script


@pytest.fixture(scope="module")
def ring_test():
    return load_script("benchmarks/ring_test.py", "ring_test_bench")


def _args(out, seed=2):
    return ["--n-galaxies", "3", "--n-exposures", "1", "--n-rotations", "2", "--stamp-size", "32", "--processes", "1",
            "--seed", str(seed), "--n-bootstrap", "10", "--quiet", "--out", str(out)]


def test_resume_from_checkpoint_gives_the_whole_run(ring_test, tmp_path, capsys):
    whole = tmp_path / "whole.fits"
    assert ring_test.main(_args(whole)) == 0
    assert not os.path.exists(ring_test.checkpoint_path(str(whole)))
    ref = Table.read(whole)

    # a run stopped after galaxy 1: its checkpoint holds that galaxy's rows, with the run's signature
    out = tmp_path / "resumed.fits"
    ckpt = ring_test.checkpoint_path(str(out))
    assert ckpt == str(tmp_path / "resumed.partial.fits")
    part = ref[ref["galaxy"] == 1]
    sig = ring_test.run_signature(ring_test.parse_args(_args(out)))
    part.meta["RUNSIG"] = sig
    part.write(ckpt)

    # without --resume the checkpoint is not overwritten; under other options it is refused
    assert ring_test.main(_args(out)) == 2
    assert ckpt in capsys.readouterr().err
    assert ring_test.main(_args(out, seed=3) + ["--resume"]) == 2
    assert "checkpoint of another run" in capsys.readouterr().err
    assert os.path.exists(ckpt) and not os.path.exists(out)

    assert ring_test.main(_args(out) + ["--resume"]) == 0
    assert "1 galaxies from the checkpoint" in capsys.readouterr().out
    assert not os.path.exists(ckpt)
    got = Table.read(out)
    assert got.colnames == ref.colnames and len(got) == len(ref)
    for name in ref.colnames:
        if name != "time":   # the measuring time of each object is the one column a rerun changes
            a, b = np.asarray(ref[name]), np.asarray(got[name])
            assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), name


def test_an_option_added_at_its_default_keeps_the_checkpoints_of_earlier_runs(ring_test, tmp_path, monkeypatch):
    """A checkpoint's signature covers the options that decide a run, not the options a later version adds: one added
    at a default that keeps the earlier runs leaves the signature, and any other value of it changes it."""
    args = _args(tmp_path / "t.fits")
    before = ring_test.run_signature(ring_test.parse_args(args))
    parser = ring_test.build_parser

    def later_version():
        p = parser()
        p.add_argument("--added-later", type=float, default=None)
        return p

    monkeypatch.setattr(ring_test, "build_parser", later_version)
    assert ring_test.parse_args(args).added_later is None
    assert ring_test.run_signature(ring_test.parse_args(args)) == before
    assert ring_test.run_signature(ring_test.parse_args(args + ["--added-later", "2"])) != before
    # an option that decides a run changes it, given at any value other than its default
    assert ring_test.run_signature(ring_test.parse_args(args + ["--mag-min", "21"])) == before
    assert ring_test.run_signature(ring_test.parse_args(args + ["--mag-min", "22"])) != before


def test_galaxy_sums_report_as_the_tables(ring_test, tmp_path, capsys):
    """A metacal run kept as galaxy sums (--save-sums) reports the metacal m and c of its tables, alone and
    added to a table; sums of another shear are refused."""
    table = tmp_path / "mc.fits"
    assert ring_test.main(_args(table) + ["--metacal", "--population", "outside"]) == 0
    capsys.readouterr()
    sums = tmp_path / "mc_sums.fits"
    base = ["--metacal", "--n-bootstrap", "10", "--seed", "2", "--from-tables"]

    def metacal_lines(out):
        lines = out.splitlines()
        k = next(i for i, s in enumerate(lines) if s.startswith("metacal shear bias"))
        return lines[k:k + 7]

    assert ring_test.main(base + [str(table), "--save-sums", str(sums)]) == 0
    from_table = capsys.readouterr().out
    assert f"galaxy sums of 3 galaxies written to {sums}" in from_table
    assert ring_test.main(base + [str(sums)]) == 0
    from_sums = capsys.readouterr().out
    assert "1 file(s) of galaxy sums: 3 galaxies, 12 objects" in from_sums
    # the per-galaxy line's count of galaxies needed is rounded up from float32 sums: compare the m and c lines,
    # their words alike and their figures to the last printed digit (a float32 sum can move an error's fifth
    # decimal: 0.34141 against 0.34140 with the numpy loops)
    number = re.compile(r"[-+]?\d+\.\d+(?:e[-+]?\d+)?")
    a, b = metacal_lines(from_sums)[:6], metacal_lines(from_table)[:6]
    assert [number.sub("#", x) for x in a] == [number.sub("#", x) for x in b]
    for x, y in zip(a, b):
        assert np.allclose([float(v) for v in number.findall(x)], [float(v) for v in number.findall(y)], rtol=0,
                           atol=1.5e-5)
    assert ring_test.main(base + [str(table), str(sums)]) == 0
    assert "6 galaxies, 24 objects" in capsys.readouterr().out
    assert ring_test.main(base + [str(sums), "--shear", "0.02", "0.02"]) == 2
    assert f"{sums}: galaxy sums of g = (0.03, -0.02)" in capsys.readouterr().err
    # --all-objects re-selects a table's objects (no selection: R_S is zero); galaxy sums cannot be re-selected
    assert ring_test.main(base + [str(table), "--all-objects"]) == 0
    out = capsys.readouterr().out
    assert "every measured object, unit weights, no selection" in out
    assert "R_S = [[+0.0000, +0.0000], [+0.0000, +0.0000]]" in out
    assert ring_test.main(base + [str(sums), "--all-objects"]) == 2
    assert "--all-objects re-selects" in capsys.readouterr().err
    # --paired-with a run of the same galaxies at half the shear: each run's m at its own g
    half = tmp_path / "mc_half.fits"
    assert ring_test.main(_args(half) + ["--metacal", "--population", "outside", "--shear", "0.015", "-0.01"]) == 0
    capsys.readouterr()
    assert ring_test.main(base + [str(table), "--paired-with", str(half)]) == 0
    out = capsys.readouterr().out
    assert "m at g = (+0.03, -0.02) less m at g = (+0.015, -0.01)" in out
    from shearfit.calib.bias import metacal_bias_from_sums, metacal_ring_sums
    m = [metacal_bias_from_sums(metacal_ring_sums(Table.read(f), 3), g)[0][0]
         for f, g in ((table, (0.03, -0.02)), (half, (0.015, -0.01)))]
    line = next(s for s in out.splitlines() if s.strip().startswith("delta m1"))
    assert abs(float(line.split()[3]) - (m[0] - m[1])) < 1e-5, (line, m)
    # a table is reported at its own shear and its sums keep it (the default's would make its m about +1);
    # tables of two shears, or a --shear that is not the tables', are refused
    half_sums = tmp_path / "mc_half_sums.fits"
    assert ring_test.main(base + [str(half), "--save-sums", str(half_sums)]) == 0
    assert np.allclose(ring_test.MetacalRings.read(str(half_sums)).g, (0.015, -0.01))
    assert abs(_line_value(capsys.readouterr().out, "metacal shear bias", "m1 =") - m[1]) < 1e-5
    assert ring_test.main(base + [str(half_sums)]) == 0
    assert abs(_line_value(capsys.readouterr().out, "metacal shear bias", "m1 =") - m[1]) < 1e-5
    assert ring_test.main(base + [str(table), str(half)]) == 2
    assert f"{half}: objects of g = (+0.0150, -0.0100), not (+0.0300, -0.0200)" in capsys.readouterr().err
    assert ring_test.main(base + [str(half), "--shear", "0.03", "-0.02"]) == 2
    assert f"{half}: objects of g = (+0.0150, -0.0100)" in capsys.readouterr().err


def _synthetic_rings(ring_test, rng, n, g):
    """MetacalRings of ``n`` made-up galaxies: sums shaped like a run's (weights, e near +-g, R near 0.9, the
    versions' sums), each galaxy its own half-light radius and target SNR."""
    sums = np.empty((20, n, 2))
    w = rng.uniform(0.5, 2.0, (n, 2))
    sums[0] = sums[3] = w
    sums[1:3] = w * rng.normal(0.0, 0.3, (2, n, 2)) + w * np.array([1, -1])[None, None, :] * np.reshape(g, (2, 1, 1))
    sums[4] = sums[7] = w * rng.normal(0.9, 0.1, (n, 2))
    sums[5] = sums[6] = w * rng.normal(0.0, 0.05, (n, 2))
    for k in range(8, 20, 3):
        sums[k] = w * rng.uniform(0.9, 1.1, (n, 2))
        sums[k + 1:k + 3] = sums[k] * rng.normal(0.0, 0.3, (2, n, 2))
    return ring_test.MetacalRings(sums, rng.integers(0, 3, n), rng.uniform(0.1, 2.0, n), rng.uniform(10, 40, n),
                                  np.full(n, 16), np.zeros(n), g, True)


def _line_value(out, start, after):
    """The number that follows ``after`` on the first line of ``out`` that starts with ``start``."""
    lines = out.splitlines()
    k = next(i for i, s in enumerate(lines) if s.startswith(start))
    line = next(s for s in lines[k + 1:] if after in s)
    return float(line.split(after)[1].split()[0])


def test_galaxy_sums_pair_by_galaxy_and_extend_to_the_other_campaign(ring_test, tmp_path, capsys):
    """--paired-with files of galaxy sums: the galaxies of --from-tables are found among the other setting's by
    their family, size and SNR (in any order), their m difference is that of the matched galaxies, and A's m on
    B's whole population is m_B(all) + m_A(paired) - m_B(paired); with --hlr-log-uniform the paired galaxies carry
    A's own weights on both sides, and B's whole population its own; a galaxy missing from B is refused."""
    from shearfit.calib.bias import metacal_bias_from_sums

    rng = np.random.default_rng(11)
    g = (0.03, -0.02)
    b = _synthetic_rings(ring_test, rng, 40, g)
    pick = rng.permutation(40)[:15]
    a = b.subset(pick)
    a.sums = a.sums * rng.uniform(0.95, 1.05, a.sums.shape)   # another setting: the same galaxies, other sums
    a_path, b_path = tmp_path / "a.fits", tmp_path / "b.fits"
    a.write(str(a_path))
    b.write(str(b_path))
    a, b = ring_test.MetacalRings.read(str(a_path)), ring_test.MetacalRings.read(str(b_path))
    base = ["--metacal", "--n-bootstrap", "20", "--seed", "2", "--from-tables", str(a_path), "--paired-with"]
    assert ring_test.main(base + [str(b_path)]) == 0
    out = capsys.readouterr().out
    m_a, m_b_paired, m_b = (metacal_bias_from_sums(r.sums, g)[0] for r in (a, b.subset(pick), b))
    assert abs(_line_value(out, "metacal, these tables less", "delta m1 =") - (m_a[0] - m_b_paired[0])) < 2e-5
    assert "(40 galaxies, 15 of them paired)" in out
    assert abs(_line_value(out, "metacal of these tables' setting", "m2 =") - (m_b[1] + m_a[1] - m_b_paired[1])) < 2e-5
    # weighted to log-uniform sizes: B's population with its weights, the paired galaxies with A's
    edges = np.linspace(np.log(0.1), np.log(2.0), ring_test.HLR_WEIGHT_BINS + 1)
    centres = np.exp(0.5 * (edges[:-1] + edges[1:]))
    # each bin one galaxy, the 10 smallest bins two more: weights a third of the others' there
    order = rng.permutation(40)
    b.true_hlr = np.concatenate([centres, centres[:10] * 1.01, centres[:10] * 1.02])[order]
    b.write(str(b_path))
    a_w = b.subset(pick)
    a_w.sums = a.sums
    a_w.write(str(a_path))
    assert ring_test.main(base + [str(b_path), "--hlr-log-uniform", "0.1", "2.0"]) == 2   # A alone has empty bins
    assert "no galaxy of half-light radius" in capsys.readouterr().err
    pick = np.argsort(order)[:20]   # the first 20 of the concatenation: each bin holds one of A's
    a_w = b.subset(pick)
    a_w.sums = a_w.sums * rng.uniform(0.95, 1.05, a_w.sums.shape)
    a_w.write(str(a_path))
    assert ring_test.main(base + [str(b_path), "--hlr-log-uniform", "0.1", "2.0"]) == 0
    out = capsys.readouterr().out
    w = ring_test.hlr_log_uniform_weights(b.true_hlr, 0.1, 2.0)
    a_w = ring_test.MetacalRings.read(str(a_path))
    w_a = ring_test.hlr_log_uniform_weights(a_w.true_hlr, 0.1, 2.0)
    m_a, m_b_paired, m_b = (metacal_bias_from_sums(r.sums, g)[0] for r in
                            (a_w.weighted_by(w_a), b.subset(pick).weighted_by(w_a), b.weighted_by(w)))
    assert not np.allclose(w, 1.0)
    assert abs(_line_value(out, "metacal, these tables less", "delta m1 =") - (m_a[0] - m_b_paired[0])) < 2e-5
    assert abs(_line_value(out, "metacal of these tables' setting", "m1 =") - (m_b[0] + m_a[0] - m_b_paired[0])) < 2e-5
    # a galaxy of A that B lacks
    b.subset(np.setdiff1d(np.arange(40), pick[:1])).write(str(b_path))
    assert ring_test.main(base + [str(b_path)]) == 2
    assert "1 of the 20 galaxies of --from-tables are not among its galaxies" in capsys.readouterr().err


def test_runs_jackknife_leaves_each_run_out(ring_test):
    """The jackknife over runs of --from-tables: each left-out estimate is that of the other runs put together
    (made here by concatenating them, not by the zero counts the function uses), and the error is the
    delete-one formula of those estimates."""
    from shearfit.calib.bias import metacal_bias_from_sums

    rng = np.random.default_rng(5)
    g = (0.03, -0.02)
    parts = [_synthetic_rings(ring_test, rng, n, g) for n in (7, 9, 8, 11, 6, 10)]
    est, err, left_out = ring_test.runs_jackknife(parts, g)
    whole = ring_test.MetacalRings.concatenate(parts)
    assert np.allclose(est, metacal_bias_from_sums(whole.sums, g)[0], rtol=0, atol=1e-14)
    for i in range(len(parts)):
        others = ring_test.MetacalRings.concatenate(parts[:i] + parts[i + 1:])
        assert np.allclose(left_out[i], metacal_bias_from_sums(others.sums, g)[0], rtol=0, atol=1e-12)
    n = len(parts)
    want = np.sqrt((n - 1) / n * np.sum((left_out - left_out.mean(axis=0)) ** 2, axis=0))
    assert np.allclose(err, want, rtol=1e-12) and np.all(err[:2] > 0)


def test_hlr_log_uniform_weights_join_runs_of_different_sizes(ring_test):
    """Two runs, one of small galaxies sampled densely and one of large galaxies sampled thinly, overlapping at
    0.85-0.9": weighted, every bin of ln(hlr) over 0.1-2" holds the same weight, so the weighted sizes are
    log-uniform (mean ln hlr at the range's middle); galaxies outside weigh 0 and the rest average 1."""
    rng = np.random.default_rng(3)
    small = np.exp(rng.uniform(np.log(0.1), np.log(0.9), 6000))
    large = np.exp(rng.uniform(np.log(0.85), np.log(2.0), 800))
    hlr = np.concatenate([small, large, [0.05, 2.5]])
    w = ring_test.hlr_log_uniform_weights(hlr, 0.1, 2.0)
    assert w[-2] == w[-1] == 0 and np.all(w[:-2] > 0)
    assert np.isclose(w[:-2].mean(), 1.0, rtol=1e-12)
    edges = np.linspace(np.log(0.1), np.log(2.0), ring_test.HLR_WEIGHT_BINS + 1)
    per_bin = np.histogram(np.log(hlr[:-2]), edges, weights=w[:-2])[0]
    assert np.allclose(per_bin, per_bin.mean(), rtol=1e-12)
    # the galaxies above 1.2" (only large ones, 1/10 of the galaxies) stand for ln(2 / 1.2) / ln(20) = 17 % of
    # the population (to the scatter of the one bin that 1.2" splits)
    assert abs(w[hlr >= 1.2].sum() / w.sum() - np.log(2 / 1.2) / np.log(20)) < 0.01
    assert abs(np.average(np.log(hlr[:-2]), weights=w[:-2]) - 0.5 * np.log(0.2)) < 0.02
    with pytest.raises(ValueError, match="no galaxy of half-light radius"):
        ring_test.hlr_log_uniform_weights(small, 0.1, 2.0)


def test_a_galaxys_weight_counts_it_as_often(ring_test):
    """MetacalRings.weighted_by: every sum is linear in the objects' weights, so weight 2 is the galaxy twice."""
    from shearfit.calib.bias import metacal_bias_from_sums

    rng = np.random.default_rng(8)
    n, g = 6, (0.03, -0.02)
    sums = rng.uniform(0.5, 1.5, (20, n, 2))
    rings = ring_test.MetacalRings(sums, np.zeros(n), np.ones(n), np.full(n, 20.0), np.full(n, 16), np.zeros(n), g,
                                   True)
    w = np.array([1.0, 2.0, 1.0, 0.0, 3.0, 1.0])
    twice = np.repeat(sums, w.astype(int), axis=1)
    assert np.allclose(metacal_bias_from_sums(rings.weighted_by(w).sums, g)[0], metacal_bias_from_sums(twice, g)[0],
                       rtol=1e-12, atol=0)


def test_noise_free_metacal_is_refused(ring_test):
    """Without the images' own noise, metacal's symmetrising noise alone would be left unsymmetrised."""
    with pytest.raises(SystemExit):
        ring_test.parse_args(["--metacal", "--noise-free"])
    with pytest.raises(SystemExit):
        ring_test.parse_args(["--hlr-log-uniform", "0.1", "2"])   # needs --from-tables and --metacal
    with pytest.raises(SystemExit):
        ring_test.parse_args(["--metacal-fresh"])   # needs --metacal


def test_galaxy_sums_of_the_papers_population_pair(ring_test):
    """The paper's population keeps no half-light radius (NaN in its sums), and a NaN equals nothing: its
    galaxies must still be found in another setting's sums of the same seeds, and a galaxy missing there named."""
    n = 4
    snr = np.array([10.5, 11.25, 12.0, 13.5])

    def rings(order):
        return ring_test.MetacalRings(np.zeros((20, n, 2)), np.full(n, -1), np.full(n, np.nan), snr[order],
                                      np.full(n, 16), np.zeros(n, int), (0.03, -0.02), True)

    mine, theirs = rings([0, 1, 2, 3]), rings([2, 0, 3, 1])
    assert mine.match_in(theirs).tolist() == [1, 3, 0, 2]
    other = ring_test.MetacalRings(np.zeros((20, 1, 2)), [-1], [np.nan], [99.0], [16], [0], (0.03, -0.02), True)
    with pytest.raises(ValueError, match="4 of the 4 galaxies"):
        mine.match_in(other)


def test_galaxy_sums_with_coinciding_keys_pair_in_their_order(ring_test):
    """Among thousands of the paper's galaxies some target SNRs coincide in float32 (the key): those pair in their
    order of occurrence on both sides (12 seeds of 500 failed before on such a pair), and a galaxy whose key runs
    out on the other side is named as missing."""
    snr = np.array([10.5, 11.25, 10.5, 13.5, 10.5])

    def rings(values):
        n = len(values)
        sums = np.zeros((20, n, 2))
        sums[0, :, 0] = np.arange(n)   # which galaxy this is, to check the pairing
        return ring_test.MetacalRings(sums, np.full(n, -1), np.full(n, np.nan), np.asarray(values), np.full(n, 16),
                                      np.zeros(n, int), (0.03, -0.02), True)

    mine = rings(snr)
    theirs = rings(np.concatenate([[99.0], snr]))
    assert mine.match_in(theirs).tolist() == [1, 2, 3, 4, 5]
    with pytest.raises(ValueError, match="1 of the 5 galaxies"):
        mine.match_in(rings(snr[:4]))


def test_measuring_only_the_faint_galaxies_keeps_the_others_draws(ring_test, tmp_path):
    """--measure-snr-below leaves out the galaxies at or above that target SNR and measures the rest exactly as
    the whole run does (each galaxy has its own seed): their rows are the whole run's, so a change that acts only
    on faint galaxies pairs with the whole run at a fraction of its cost."""
    whole, faint = tmp_path / "whole.fits", tmp_path / "faint.fits"
    base = _args(whole, seed=5) + ["--n-galaxies", "6", "--snr-min", "10", "--snr-max", "40"]
    assert ring_test.main(base) == 0
    ref = Table.read(whole)
    snr = {int(g): float(s) for g, s in zip(ref["galaxy"], ref["snr_target"])}
    cut = float(np.median(list(snr.values())))
    assert ring_test.main(_args(faint, seed=5) + ["--n-galaxies", "6", "--snr-min", "10", "--snr-max", "40",
                                                  "--measure-snr-below", str(cut)]) == 0
    got = Table.read(faint)
    kept = sorted(g for g, s in snr.items() if s < cut)
    assert 0 < len(kept) < 6 and sorted(set(int(g) for g in got["galaxy"])) == kept
    sub = ref[np.isin(ref["galaxy"], kept)]
    for name in ("e1", "e2", "weight", "snr_target", "e1_int"):
        assert np.array_equal(np.asarray(sub[name]), np.asarray(got[name]), equal_nan=True), name


def test_galaxies_measures_those_of_the_whole_run(ring_test, tmp_path, capsys):
    """--galaxies measures only the galaxies named, each drawn and measured as in the whole run; a galaxy the run
    does not have is refused in one line."""
    whole, some = tmp_path / "whole.fits", tmp_path / "some.fits"
    assert ring_test.main(_args(whole, seed=6)) == 0
    ref = Table.read(whole)
    assert ring_test.main(_args(some, seed=6) + ["--galaxies", "2", "0"]) == 0
    got = Table.read(some)
    assert sorted(set(int(g) for g in got["galaxy"])) == [0, 2]
    sub = ref[np.isin(ref["galaxy"], [0, 2])]
    for name in ("e1", "e2", "weight", "snr_target", "e1_int"):
        assert np.array_equal(np.asarray(sub[name]), np.asarray(got[name]), equal_nan=True), name
    assert ring_test.main(_args(tmp_path / "bad.fits", seed=6) + ["--galaxies", "3"]) == 2
    err = capsys.readouterr().err
    assert "--galaxies 3" in err and len(err.strip().splitlines()) == 1


def test_paired_below_moves_the_faint_galaxies_and_scales_a_sample_of_them(ring_test, tmp_path, capsys):
    """--paired-below: a run that measured only galaxies below an SNR (--measure-snr-below) gives its setting's m on
    the other campaign's whole population, those galaxies moved to it and the others kept. With every faint galaxy
    measured that is B's sums with theirs replaced; with half of them, each moved by the same amount, the summed move
    scaled by two is the same population. A's galaxies above the limit are not used."""
    from shearfit.calib.bias import metacal_bias_from_sums

    rng = np.random.default_rng(12)
    g = (0.03, -0.02)
    b = _synthetic_rings(ring_test, rng, 60, g)
    b.snr_target = np.repeat([12.0, 30.0], 30) + rng.uniform(0, 5, 60)
    faint = np.flatnonzero(b.snr_target < 20)
    b_path, a_path = tmp_path / "b.fits", tmp_path / "a.fits"
    b.write(str(b_path))
    b = ring_test.MetacalRings.read(str(b_path))
    move = np.zeros_like(b.sums[:, :1])
    move[1:3] = 0.05 * b.sums[0, :1].mean()      # every faint galaxy's e sums moved alike
    a = b.subset(faint)
    a.sums = a.sums + move
    a.write(str(a_path))
    base = ["--metacal", "--n-bootstrap", "20", "--seed", "2", "--from-tables", str(a_path), "--paired-with",
            str(b_path), "--paired-below", "20"]
    expected = b.sums.copy()
    expected[:, faint] += move
    m_all = metacal_bias_from_sums(expected, g)[0]
    assert ring_test.main(base) == 0
    out = capsys.readouterr().out
    assert "its 30 below target SNR 20 moved to this setting (30 measured here, their move scaled by 1.000)" in out
    assert abs(_line_value(out, "metacal of these tables' setting", "m1 =") - m_all[0]) < 2e-5
    assert abs(metacal_bias_from_sums(b.sums, g)[0][0] - m_all[0]) > 1e-2   # the move matters
    # half the faint galaxies, with two bright ones whose sums differ (ignored): the same population
    half = b.subset(np.concatenate([faint[:15], np.flatnonzero(b.snr_target > 20)[:2]]))
    half.sums = half.sums + move
    half.write(str(a_path))
    assert ring_test.main(base) == 0
    out = capsys.readouterr().out
    assert "(15 measured here, their move scaled by 2.000)" in out
    assert abs(_line_value(out, "metacal of these tables' setting", "m2 =") - m_all[1]) < 2e-5
    assert ring_test.main(base[:-4] + base[-2:]) == 2   # no --paired-with
    assert "--paired-below moves --paired-with's galaxies" in capsys.readouterr().err
    # sizes made log-uniform: the move scaled within each size bin, so that small galaxies rerun in a larger share
    # than large ones (two campaigns) give the same population; each faint galaxy of the bins below moved by
    # `move`, of the bins above by twice it, a third of the small ones and two thirds of the large ones measured
    edges = np.linspace(np.log(0.1), np.log(2.0), ring_test.HLR_WEIGHT_BINS + 1)
    centres = np.exp(0.5 * (edges[:-1] + edges[1:]))
    b.true_hlr = np.resize(centres, 60)[rng.permutation(60)]
    b.write(str(b_path))
    large = b.true_hlr > centres[ring_test.HLR_WEIGHT_BINS // 2]
    w = ring_test.hlr_log_uniform_weights(b.true_hlr, 0.1, 2.0)
    expected = b.sums.copy()
    expected[:, faint] += move * np.where(large[faint], 2.0, 1.0)[None, :, None]
    m_all = metacal_bias_from_sums(expected * w[None, :, None], g)[0]
    k, _, _ = ring_test.hlr_bins(b.true_hlr, 0.1, 2.0)
    bright = np.flatnonzero(b.snr_target > 20)   # A holds them too (every size bin has galaxies), moved but not used

    def write_a(faint_picked):
        picked = np.concatenate([faint_picked, bright])
        part = b.subset(picked)
        part.sums = part.sums + move * np.where(large[picked], 2.0, 1.0)[None, :, None]
        part.write(str(a_path))

    gap = next(c for c in np.unique(k[faint]) if np.any(k[bright] == c))   # a bin of faint and bright galaxies
    write_a(faint[k[faint] != gap])
    assert ring_test.main(base + ["--hlr-log-uniform", "0.1", "2.0"]) == 2
    assert "1 size bin(s) have none measured here" in capsys.readouterr().err
    first = np.array([faint[k[faint] == c][0] for c in np.unique(k[faint])])   # one of each bin's faint galaxies
    picked = np.union1d(first[~large[first]], faint[large[faint]])
    write_a(picked)
    assert ring_test.main(base + ["--hlr-log-uniform", "0.1", "2.0"]) == 0
    out = capsys.readouterr().out
    assert f"({picked.size} measured here, their move scaled by 1.000-" in out
    assert abs(_line_value(out, "metacal of these tables' setting", "m1 =") - m_all[0]) < 2e-5
    assert abs(_line_value(out, "metacal of these tables' setting", "m2 =") - m_all[1]) < 2e-5


def test_e_range_redraws_only_the_ellipticities(ring_test):
    """--e-range: the paper's galaxies with |e| uniform over the range, their position angles and everything else
    as drawn without it (the rings of the high-|e| tail)."""
    from shearfit.config import FitConfig

    cfg = FitConfig()
    mags = np.linspace(21.0, 24.0, 400)
    base = ring_test._paper_population(mags, np.random.default_rng(5), cfg)
    got = ring_test.e_ranged_population(mags, np.random.default_rng(5), cfg, None, (0.7, 0.8))
    a = np.hypot(got["e1"], got["e2"])
    assert np.all((a >= 0.7) & (a < 0.8)) and a.std() > 0.02
    assert np.allclose(np.arctan2(got["e2"], got["e1"]), np.arctan2(base["e2"], base["e1"]))
    for name in ("scalelength", "bulge_fraction", "mag"):
        assert np.array_equal(got[name], base[name])
    with pytest.raises(SystemExit):
        ring_test.parse_args(["--e-range", "0.7", "0.8", "--population", "odd"])
    with pytest.raises(SystemExit):
        ring_test.parse_args(["--e-range", "0.8", "0.7"])


def test_population_set_draws_the_population_without_the_fits_setting(ring_test, tmp_path):
    """--population-set: the galaxies are drawn with its settings in place of --set's, so that a fit with a prior of
    its own (here a disk_e_max of 0.3) meets the galaxies the paper's prior draws."""
    def drawn(*extra):
        out = tmp_path / f"t{len(list(tmp_path.iterdir()))}.fits"
        args = ["--n-galaxies", "40", "--n-exposures", "1", "--n-rotations", "2", "--stamp-size", "32",
                "--processes", "1", "--seed", "4", "--quiet", "--dry-run", "--out", str(out)]
        assert ring_test.main(args + list(extra)) == 0
        t = Table.read(out)
        disk = ~np.asarray(t["is_bulge"], bool)   # the bulges' prior has no disk_e_max
        return np.hypot(np.asarray(t["e1_int"]), np.asarray(t["e2_int"]))[disk]

    paper = drawn()
    own = drawn("--set", "disk_e_max=0.3")
    apart = drawn("--set", "disk_e_max=0.3", "--population-set", "disk_e_max=0.804")
    assert paper.size > 20 and paper.max() > 0.45 and own.max() <= 0.3 + 1e-12
    assert np.array_equal(apart, paper)

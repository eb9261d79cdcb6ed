"""benchmarks/ring_split.py --paired-with: two runs of the same galaxies compared object by object."""

import re

import numpy as np
from astropy.table import Table

from scripts import load_script

ring_split = load_script("benchmarks/ring_split.py")

G = (0.03, -0.02)


def _run(m, n_gal=40, twins=True, drop=(), seed=5):
    """A ring-test-like table whose estimates respond to the shear by 1 + m exactly: e = e_int + (1 + m) g sign
    + n, with n the same at +g and -g (a twin has -n)."""
    rng = np.random.default_rng(seed)
    rows = []
    for k in range(n_gal):
        if k in drop:
            continue
        e0 = rng.uniform(0.05, 0.6) * np.exp(2j * np.pi * rng.uniform())
        for j in range(8 if twins else 4):
            ej = e0 * np.exp(2j * np.pi * (j % 4) / 4)
            noise = complex(*np.random.default_rng([seed, k, j % 4]).normal(0, 0.05, 2)) * (-1 if j >= 4 else 1)
            for sign in (1, -1):
                e = ej + (1 + m) * sign * complex(*G) + noise
                rows.append((k, sign, j, G[0] * sign, G[1] * sign, ej.real, ej.imag, 0.11, e.real, e.imag, 0.01,
                             1.0, 0, 100.0))
    names = ("galaxy", "sign", "rotation", "g1", "g2", "e1_int", "e2_int", "true_scalelength", "e1", "e2", "e_var",
             "weight", "fitclass", "flux_snr")
    return Table(rows=rows, names=names)


def _pairs(out):
    """m1, m2 of the "all" lines: the first run, the paired run, the first less the paired."""
    lines = [ln for ln in out.splitlines() if ln.startswith("all")]
    return [tuple(float(x) for x in re.findall(r"m[12]=([+-][0-9.]+)", ln)) for ln in lines], lines


def test_paired_with_is_the_difference_object_by_object(tmp_path, capsys):
    a, b = tmp_path / "a.fits", tmp_path / "b.fits"
    _run(0.004).write(a)
    # the other run: noise-free-like, without twins, and a stopped run's table lacking galaxy 3 (as written: the
    # galaxies keep their numbers)
    _run(-0.002, twins=False, drop=(3,)).write(b)
    ring_split.main([str(a)], r_bins=(0.1, 0.125), unweighted=True, paired_with=[str(b)])
    (first, other, diff), lines = _pairs(capsys.readouterr().out)
    assert "rings=  39" in lines[2]
    assert np.allclose(first, 0.004, atol=1e-4)
    assert np.allclose(other, -0.002, atol=1e-4)
    assert np.allclose(diff, 0.006, atol=1e-4)


def test_paired_with_leaves_out_a_ring_that_failed_in_one_run_only(tmp_path, capsys):
    """An object that failed in one run only: its whole galaxy is left out of both runs. Counted as failed in
    the other run too, it would break that run's ring there (its intrinsic shapes no longer cancel)."""
    a, b = tmp_path / "a.fits", tmp_path / "b.fits"
    ta, tb = _run(0.004), _run(-0.002)
    # galaxy 5 fails at rotation 1, +g, in the second run only; galaxy 9 at rotation 2, -g, in both
    tb["fitclass"][(tb["galaxy"] == 5) & (tb["rotation"] == 1) & (tb["sign"] > 0)] = -1
    for t in (ta, tb):
        t["fitclass"][(t["galaxy"] == 9) & (t["rotation"] == 2) & (t["sign"] < 0)] = -1
    ta.write(a)
    tb.write(b)
    ring_split.main([str(a)], r_bins=(0.1, 0.125), unweighted=True, paired_with=[str(b)])
    out = capsys.readouterr().out
    assert "1 galaxies left out of both" in out
    (first, other, diff), lines = _pairs(out)
    assert all("rings=  39" in ln for ln in lines)
    # galaxy 9's ring is broken alike in both runs: it moves each run's m, and cancels in the difference
    assert np.allclose(diff, 0.006, atol=1e-4)
    # the first run read as the pairing does (galaxy 5 left out) against the same run without the pairing
    ta.remove_rows(np.flatnonzero(ta["galaxy"] == 5))
    ta.write(a, overwrite=True)
    ring_split.main([str(a)], r_bins=(0.1, 0.125), unweighted=True)
    (alone,), _ = _pairs(capsys.readouterr().out)
    assert np.allclose(first, alone, atol=1e-4)


def test_whole_rings_leaves_out_the_galaxies_of_flagged_objects(tmp_path, capsys):
    """One flagged object breaks its ring (the other objects' intrinsic shapes no longer cancel): m moves by
    several 1e-3 on 40 rings. --whole-rings leaves that galaxy out and says what it lost at +g and at -g."""
    a = tmp_path / "a.fits"
    t = _run(0.004)
    t["fitclass"][(t["galaxy"] == 5) & (t["rotation"] == 1) & (t["sign"] > 0)] = -3
    t.write(a)
    ring_split.main([str(a)], r_bins=(0.1, 0.125), unweighted=True)
    (broken,), _ = _pairs(capsys.readouterr().out)
    assert np.max(np.abs(np.subtract(broken, 0.004))) > 2e-3
    ring_split.main([str(a)], r_bins=(0.1, 0.125), unweighted=True, whole_rings=True)
    out = capsys.readouterr().out
    assert "1 of 40 galaxies left out (objects not measured as galaxies: 1 at +g, 0 at -g)" in out
    (whole,), lines = _pairs(out)
    assert "rings=  39" in lines[0]
    assert np.allclose(whole, 0.004, atol=1e-4)


def test_paired_with_pairs_several_tables_table_by_table(tmp_path, capsys):
    """A1 A2 --paired-with B1 B2: A1 with B1 and A2 with B2, both runs numbered on alike (the two seeds' galaxy
    numbers overlap, 0-39 and 0-29): 39 + 30 rings, and m the rings' mean (each ring responds by its run's 1 + m)."""
    a1, b1, a2, b2 = (tmp_path / f"{n}.fits" for n in ("a1", "b1", "a2", "b2"))
    _run(0.004).write(a1)
    _run(-0.002, twins=False, drop=(3,)).write(b1)
    _run(0.010, n_gal=30, seed=7).write(a2)
    _run(0.002, n_gal=30, seed=7).write(b2)
    ring_split.main([str(a1), str(a2)], r_bins=(0.1, 0.125), unweighted=True, paired_with=[str(b1), str(b2)])
    (first, other, diff), lines = _pairs(capsys.readouterr().out)
    assert all("rings=  69" in ln for ln in lines)
    assert np.allclose(first, (39 * 0.004 + 30 * 0.010) / 69, atol=1e-4)
    assert np.allclose(other, (39 * -0.002 + 30 * 0.002) / 69, atol=1e-4)
    assert np.allclose(diff, (39 * 0.006 + 30 * 0.008) / 69, atol=1e-4)
    # one paired run for two tables is refused, with what to give
    try:
        ring_split.main([str(a1), str(a2)], unweighted=True, paired_with=[str(b1)])
    except SystemExit as exc:
        assert "1 table(s) for 2" in str(exc)
    else:
        raise AssertionError("--paired-with with fewer tables than runs was accepted")


def _two_pair(m_two, m_one, **kw):
    """A two-pair run's table: estimates responding by 1 + m_two, and the one-pair correction (nb1_de) such that
    the one pair alone would have left 1 + m_one (nb_de, the correction applied, is 0)."""
    t = _run(m_two, **kw)
    sign = np.asarray(t["sign"], float)
    t["nb_de1"] = np.zeros(len(t))
    t["nb_de2"] = np.zeros(len(t))
    t["nb1_de1"] = -(m_one - m_two) * G[0] * sign
    t["nb1_de2"] = -(m_one - m_two) * G[1] * sign
    return t


def _control_lines(out):
    return {ln.split(": ", 1)[1].split("  rings=")[0].strip(): (int(re.search(r"rings=\s*(\d+)", ln).group(1)),
                                                                 tuple(float(x) for x in re.findall(
                                                                     r"m[12]=([+-][0-9.]+)", ln)))
            for ln in out.splitlines() if ln.startswith("all: ")}


def test_control_is_the_two_pairs_m_with_the_one_pairs_galaxies_added(tmp_path, capsys):
    """--control: m_two(S2) - m_one(S2) + m_one(S). The one-pair run B of the two-pair run A's seed holds A's 40
    galaxies and 40 more; A's are left out of B (80 galaxies in S, not 120), and a run of other galaxies adds its own.
    B's galaxies respond by as much as A's one-pair estimates, so the control's m is A's two-pair m exactly."""
    a, b, c = tmp_path / "a.fits", tmp_path / "b.fits", tmp_path / "c.fits"
    _two_pair(0.004, 0.011).write(a)
    _run(0.011, n_gal=80).write(b)
    _run(0.011, n_gal=20, seed=9).write(c)
    ring_split.control_main([str(a)], [f"{a}={b}", str(c)], r_bins=(0.1, 0.125), unweighted=True)
    lines = _control_lines(capsys.readouterr().out)
    assert lines["two pairs"][0] == 40 and lines["one pair, all"][0] == 100
    assert np.allclose(lines["two pairs"][1], 0.004, atol=1e-4)
    assert np.allclose(lines["one pair, same galaxies"][1], 0.011, atol=1e-4)
    assert np.allclose(lines["two pairs, one-pair control"][1], 0.004, atol=1e-4)
    # where B's extra galaxies respond otherwise, the control moves by their share of S: (40 / 80) x 0.01
    _run(0.011, n_gal=40).write(b, overwrite=True)
    _run(0.021, n_gal=80).write(c, overwrite=True)
    ring_split.control_main([str(a)], [f"{a}={b}", f"{a}={c}"], r_bins=(0.1, 0.125), unweighted=True)
    lines = _control_lines(capsys.readouterr().out)
    assert lines["one pair, all"][0] == 80
    assert np.allclose(lines["two pairs, one-pair control"][1], 0.004 + 0.005, atol=1e-4)


def test_noise_level_reads_the_fits_of_each_pair_back(tmp_path, capsys):
    """--noise-level V: a two-pair run (a = sqrt(3)) whose fits at V times the data's noise variance respond by
    1 + m(V), m(V) = m0 + B V + C V^2: the table holds the extrapolated e(0) and the corrections nb_de = e(1) - e(0)
    and nb1_de = D(1) = e(2) - e(1), from which V = 1, 2 and 4 give m(1), m(2) and m(4) back, and the table itself
    m0 (the extrapolation is exact on a quadratic)."""
    m0, B, C = 0.002, 0.02, -0.003

    def m(v):
        return m0 + B * v + C * v * v

    t = _run(m(1.0))
    sign = np.asarray(t["sign"], float)
    for i, g in ((1, G[0]), (2, G[1])):
        e1 = np.asarray(t[f"e{i}"])                              # the data's fit, e(1)
        e2, e4 = e1 + (m(2.0) - m(1.0)) * g * sign, e1 + (m(4.0) - m(1.0)) * g * sign
        d1, da = e2 - e1, (e4 - e1) / 3.0
        b = d1 - 2.0 * (da - d1) / 2.0
        t[f"e{i}"] = e1 - b
        t[f"nb_de{i}"] = b
        t[f"nb1_de{i}"] = d1
    path = tmp_path / "t.fits"
    t.write(path)
    for v in (None, 1.0, 2.0, 4.0):
        ring_split.main([str(path)], r_bins=(0.1, 0.125), unweighted=True, noise_level=v)
        (first,), _ = _pairs(capsys.readouterr().out)
        assert np.allclose(first, m0 if v is None else m(v), atol=1e-6), (v, first)


def test_radial_report_measures_the_response_along_e(capsys):
    """--radial: an estimator that returns the true sheared ellipticity has a radial slope of 1 and no tangential
    part; one that shrinks |e| by a factor 0.7 has a slope of 0.7."""
    t = _run(0.0, twins=False)
    ei = np.asarray(t["e1_int"]) + 1j * np.asarray(t["e2_int"])
    g = np.asarray(t["g1"]) + 1j * np.asarray(t["g2"])
    es = (ei + g) / (1 + np.conj(g) * ei)
    for factor in (1.0, 0.7):
        t["e1"], t["e2"] = factor * es.real, factor * es.imag
        ring_split.radial_report(t)
        out = capsys.readouterr().out
        slope = float(re.search(r"\|e_s\| ([0-9.]+)$", out.splitlines()[0]).group(1))
        assert abs(slope - factor) < 1e-3
        tangential = re.findall(r"tangential rms ([0-9.]+)", out)
        assert tangential and all(float(x) == 0.0 for x in tangential)

#!/usr/bin/env python
"""m and c of a ring-test table (benchmarks/ring_test.py --out) split by true scalelength and by sigma_e.

    python benchmarks/ring_split.py ring.fits [ring2.fits ...] [--r-bins 0,0.15,0.3,10] [--unweighted |
                                              --paired-weights | --isotropic-weights] [--uncorrected | --one-pair
                                              | --noise-level V]
                                              [--e-bins 0,0.3,0.5,0.6,0.7,1] [--paired-with B.fits ...] [--keep-stars]
                                              [--whole-rings]
                                              [--control [A.fits=]B.fits ...]

Several tables (runs of the same shear) are read as one, their galaxies numbered on.

``--uncorrected``: for a run with ``--set noise_bias_correction=true``, each estimate with the noise bias it had
subtracted added back (its ``nb_de1``, ``nb_de2``): the same fits without the correction. ``--one-pair``: for a
run with ``noise_bias_second_amplitude`` as well, each estimate as the one pair at the full amplitude alone would
have corrected it (``nb1_de1``, ``nb1_de2``): the same fits with the one-pair extrapolation. ``--noise-level V``:
for such a run, each estimate as the fits at V times the data's noise variance made it: 1 the data's (as
``--uncorrected``), 2 the first pair's mean, 1 + a^2 the second pair's (4 for a = sqrt(3)). m against V is the
noise bias the extrapolation fits with a polynomial in V.

``--paired-weights``: each object's weight replaced by the mean over its pair (the same galaxy, orientation and
noise at +g and at -g; ``shearfit.calib.bias.paired_weights``), so that no weight responds to the shear while
each keeps its dependence on the galaxy, its orientation and its noise. m with lensfit's weights less m with
paired weights is the part of m that comes from the weights' response to shear.

``--paired-with B``: the same split for another run of the same galaxies (the same ``--seed``, ``--n-galaxies``
and population; another setting, or ``--noise-free``), and the first run less it object by object, the galaxies
resampled together: only objects both runs have enter either, and a galaxy of which an object failed (was not
measured as a galaxy) in one run and not in the other is left out of both, whole (its ring would not cancel in
the run where it was measured; the number left out is printed). A run without
``--antithetic`` (a noise-free one, whose twins would be copies) stands for the twins too. The weight options apply
to both runs, ``--uncorrected`` to the first only: ``A --uncorrected --paired-with NF`` (NF the same galaxies without
noise) is the noise bias that ``noise_bias_correction`` removes, ``A --paired-with NF`` what it leaves. Several runs
pair table by table: ``A1 A2 --paired-with B1 B2`` (A1 with B1, A2 with B2; each pair's galaxies numbered on alike).

``--whole-rings``: a galaxy of which any object was not measured as a galaxy (a failure, a flag, a star unless
``--keep-stars``) is left out whole, in both runs where paired. Counted with zero weight, as a catalogue would, such
an object breaks its ring: the intrinsic shapes of the others no longer cancel, and one flagged object of a 0.3"
galaxy can move m by a few 1e-3. The line printed says how many were left out, and how many of their objects
were lost at +g and at -g (a shear-dependent selection would show there, and is not in m with this option).

``--control [A=]B``: the tables given are runs with ``noise_bias_second_amplitude`` (two pairs), B a run with the one
pair (any run of the same shear and population; a two-pair run's estimates are read as ``--one-pair``'s), ``A=B``
one of the given runs A and a one-pair run B of the same ``--seed`` (its galaxies that A has are left out of B). m
of the two pairs with the one pair as a control variate: m_two(S2) - m_one(S2) + m_one(S), S2 the galaxies with
two pairs, S those and B's; a two-pair run's own one-pair estimates are in it. Unbiased for the two pairs' m, whose
error it lowers where B adds galaxies: the difference of the two corrections on the same objects scatters less than
either (the objects' own responses cancel in it). The bootstrap resamples S, S2 with it.

``--radial``: the estimates split along and across each object's true sheared ellipticity, in bins of its |e|: the
radial part's mean and scatter and the slope of its mean against |e| (1 without bias along |e|), with a
self-calibrated run's radial responses (``sc_rrad``) and steps.

``--keep-stars``: the objects classified as stars (fitclass 1) counted as galaxies, at the weight of their e_var
(unit weight with ``--unweighted``). The star/galaxy classification selects on shape (an elongated small galaxy
beats a point source by more), so it responds to the shear; an object classified at +g and not at -g also leaves
its ring's intrinsic shapes uncancelled, which dominates the error of m where only a few rings have one. With the
option m is the measurement's alone, without that selection.

``--isotropic-weights``: each weight the mean weight of its bin of ``flux_snr``
(``shearfit.calib.weights.isotropic_weights``, 10 equal-number bins; tables from session 57 on): the weights a
catalogue without ring pairs has (its ``iso_weight``), which do not respond to shear either.
"""

import argparse
import os
import sys

import numpy as np
from astropy.table import Table, vstack

from shearfit.calib.bias import bias_from_sums, bootstrap_counts, paired_weights, ring_sums, shear_bias
from shearfit.calib.calibrate import sheared_ellipticity
from shearfit.calib.weights import isotropic_weights

# benchmarks/ring_test.py, beside this script: several runs' tables read as one
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from ring_test import read_tables, stars_kept  # noqa: E402


def _weighted(t, unweighted, paired, isotropic):
    if unweighted:   # unit weights for the galaxies (fitclass 0), none for the rest
        t["weight"] = np.where(t["fitclass"] == 0, 1.0, 0.0)
    elif paired:
        t["weight"] = paired_weights(t)
    elif isotropic:
        t["weight"] = isotropic_weights(t)
    return t


def _without_galaxies_of(objects, t, other=None):
    """``t`` and ``other`` (matched with it row by row, or None) without every galaxy (whole ring) of which an object
    of ``objects`` (a mask over the rows) is, and how many galaxies that left out."""
    gal = np.asarray(t["galaxy"])
    out = np.unique(gal[objects])
    keep = ~np.isin(gal, out)
    return t[keep], (None if other is None else other[keep]), out.size


def _matched(t, other):
    """``t`` and ``other`` on their common objects (galaxy, rotation, sign) in one order, without the galaxies
    (whole rings) of which an object failed in one run and not in the other, and how many galaxies that left out;
    ``other`` without twins (rotations 4-7) standing for them where ``t`` has them."""
    if np.max(other["rotation"]) < 4 <= np.max(t["rotation"]):
        twins = other.copy()
        twins["rotation"] = twins["rotation"] + 4
        other = Table(np.concatenate([np.asarray(other), np.asarray(twins)]))

    def key(x):
        return (np.asarray(x["galaxy"], np.int64) * 64 + np.asarray(x["rotation"])) * 2 + (np.asarray(x["sign"]) > 0)

    ka, kb = key(t), key(other)
    if np.unique(ka).size != ka.size or np.unique(kb).size != kb.size:
        raise SystemExit("ring_split.py: --paired-with: an object (galaxy, rotation, sign) occurs twice in a run")
    common = np.intersect1d(ka, kb)
    t = t[np.isin(ka, common)]
    other = other[np.isin(kb, common)]
    t, other = t[np.argsort(key(t))], other[np.argsort(key(other))]
    # a galaxy with an object that failed in one run only is left out of both: marking the object failed in the
    # other run too would break that run's ring (its intrinsic shapes no longer cancel), a bias of its own
    fa, fb = np.asarray(t["fitclass"]) != 0, np.asarray(other["fitclass"]) != 0
    return _without_galaxies_of(fa != fb, t, other)


def _galaxy_columns(t, n):
    """Per galaxy of ``t`` (numbers below n): its true scalelength, intrinsic |e| and sigma_e (the rms of its
    objects' e_var; NaN for a galaxy a stopped run lacks)."""
    rgal, egal = np.zeros(n), np.zeros(n)
    rgal[t["galaxy"]] = t["true_scalelength"]
    egal[t["galaxy"]] = np.hypot(t["e1_int"], t["e2_int"])
    ev, gal = np.asarray(t["e_var"], float), np.asarray(t["galaxy"])
    ok = np.isfinite(ev)
    with np.errstate(invalid="ignore", divide="ignore"):
        sdg = np.sqrt(np.bincount(gal[ok], ev[ok], n) / np.bincount(gal[ok], None, n))
    return rgal, egal, sdg


def _subset_sums(x, idx, n):
    """Ring sums of the objects of ``x`` whose galaxies are ``idx`` (of n), the galaxies numbered as in idx."""
    remap = -np.ones(n, int)
    remap[idx] = np.arange(idx.size)
    xx = x[np.isin(x["galaxy"], idx)]
    tab = {c: np.array(xx[c]) for c in ("sign", "e1", "e2", "weight", "fitclass")}
    tab["galaxy"] = remap[np.array(xx["galaxy"])]
    return ring_sums(tab, idx.size)


def _splits(sub, columns, r_bins, e_bins, r_unit=""):
    """``sub(selection, label)`` for all galaxies and each bin of scalelength, intrinsic |e| and sigma_e."""
    rgal, egal, sdg = columns
    sub(np.ones(rgal.size, bool), "all")
    for lo, hi in zip(r_bins[:-1], r_bins[1:]):
        sub((rgal >= lo) & (rgal < hi), f"r in [{lo}, {hi}){r_unit}")
    for lo, hi in zip((e_bins or [])[:-1], (e_bins or [])[1:]):
        sub((egal >= lo) & (egal < hi), f"|e_int| in [{lo}, {hi})")
    for lo, hi in [(0, 0.02), (0.02, 0.05), (0.05, 1)]:
        sub((sdg >= lo) & (sdg < hi), f"sigma_e in [{lo}, {hi})")


def _one_pair(t):
    """A two-pair run's table with each estimate as the one pair alone would have corrected it (``--one-pair``)."""
    if "nb1_de1" not in t.colnames:
        raise SystemExit("ring_split.py: --one-pair and --control need runs with noise_bias_second_amplitude "
                         "(columns nb1_de1, nb1_de2)")
    t = t.copy()
    for i in (1, 2):
        t[f"e{i}"] = (np.asarray(t[f"e{i}"]) + np.nan_to_num(np.asarray(t[f"nb_de{i}"]))
                      - np.nan_to_num(np.asarray(t[f"nb1_de{i}"])))
    return t


def _at_noise_level(t, level):
    """A two-pair run's table with each estimate as the fits at ``level`` times the data's noise variance made it
    (``--noise-level``): 1 the data's own (``--uncorrected``), 2 the first pair's mean e(y; 2) = e(y) + D(1), and
    1 + a^2 the second pair's, e(y) + a^2 D(a), with D(a) = D(1) + (D(1) - b) (a^2 - 1) / 2 from the correction b
    subtracted (``nb_de``) and the one pair's D(1) (``nb1_de``). Exact where the corrected estimate was not scaled
    back onto corrected_e_limit."""
    if "nb1_de1" not in t.colnames:
        raise SystemExit("ring_split.py: --noise-level needs runs with noise_bias_second_amplitude (columns nb1_de1, "
                         "nb1_de2)")
    a2 = level - 1.0
    t = t.copy()
    for i in (1, 2):
        b = np.nan_to_num(np.asarray(t[f"nb_de{i}"]))
        d1 = np.nan_to_num(np.asarray(t[f"nb1_de{i}"]))
        # e(y) + a^2 D(a): at a^2 = 0 the data's fit, at a^2 = 1 the first pair's
        t[f"e{i}"] = np.asarray(t[f"e{i}"]) + b + a2 * (d1 + (d1 - b) * (a2 - 1.0) / 2.0)
    return t


def _plus_shear(t):
    plus = t[t["sign"] > 0]
    return np.array([plus["g1"][0], plus["g2"][0]])


def control_main(paths, controls, r_bins=(0, 0.15, 0.3, 10), unweighted=False, paired=False, isotropic=False,
                 e_bins=None, n_boot=500):
    """m and c of two-pair runs ``paths`` with the one-pair estimates (theirs and those of ``controls``: "B" or
    "A=B") as a control variate (``--control``)."""
    two, one, offset, first = [], [], 0, {}
    for path in paths:
        t = Table.read(path)
        t["galaxy"] = np.asarray(t["galaxy"], np.int64) + offset
        first[path] = offset
        b = _one_pair(t)
        two.append(t)
        one.append(b)
        offset = int(np.max(t["galaxy"])) + 1
    for spec in controls:
        a_path, _, b_path = spec.rpartition("=")
        b = Table.read(b_path)
        if "nb1_de1" in b.colnames:
            b = _one_pair(b)
        gal = np.asarray(b["galaxy"], np.int64)
        if a_path:
            if a_path not in first:
                raise SystemExit(f"ring_split.py: --control {spec}: {a_path} is not one of the tables given")
            a = next(t for p, t in zip(paths, two) if p == a_path)
            b = b[~np.isin(gal + first[a_path], np.asarray(a["galaxy"]))]   # A's galaxies are A's
            gal = np.asarray(b["galaxy"], np.int64)
        if len(b) == 0:
            continue
        _, b["galaxy"] = np.unique(gal, return_inverse=True)
        b["galaxy"] = np.asarray(b["galaxy"], np.int64) + offset
        offset = int(np.max(b["galaxy"])) + 1
        one.append(b)
    g = _plus_shear(two[0])
    if any(not np.allclose(_plus_shear(t), g) for t in two + one):
        raise SystemExit("ring_split.py: --control: the runs have different shears")
    keep = ("galaxy", "sign", "e1", "e2", "weight", "fitclass", "e_var", "true_scalelength", "e1_int", "e2_int",
            "flux_snr")
    ta = _weighted(Table(np.concatenate([np.asarray(t[keep]) for t in two])), unweighted, paired, isotropic)
    tb = _weighted(Table(np.concatenate([np.asarray(t[keep]) for t in one])), unweighted, paired, isotropic)
    n = offset
    in2 = np.zeros(n)
    in2[np.asarray(ta["galaxy"])] = 1.0
    present = np.zeros(n, bool)
    present[np.asarray(tb["galaxy"])] = True
    columns = _galaxy_columns(tb, n)
    rng = np.random.default_rng(0)
    print(f"two-pair runs: {len(paths)} ({int(in2.sum())} galaxies); with the one-pair control: {int(present.sum())} "
          f"galaxies")

    def sub(sel, label):
        idx = np.flatnonzero(sel & present)
        if idx.size < 2 or not np.any(in2[idx]):
            return
        sa, sb, w2 = _subset_sums(ta, idx, n), _subset_sums(tb, idx, n), in2[idx]
        counts = bootstrap_counts(idx.size, n_boot, rng)
        rows = (("two pairs", bias_from_sums(sa, g, w2), bias_from_sums(sa, g, counts * w2), int(w2.sum())),
                ("one pair, same galaxies", bias_from_sums(sb, g, w2), bias_from_sums(sb, g, counts * w2),
                 int(w2.sum())),
                ("one pair, all", bias_from_sums(sb, g), bias_from_sums(sb, g, counts), idx.size))
        cv = rows[0][1] - rows[1][1] + rows[2][1]
        cv_boot = rows[0][2] - rows[1][2] + rows[2][2]
        for name, est, boot, k in rows + (("two pairs, one-pair control", cv, cv_boot, idx.size),):
            err = np.nanstd(boot, axis=0)
            print(f"{label + ': ' + name:58s} rings={k:5d}  m1={est[0]:+.4f}+-{err[0]:.4f}  "
                  f"m2={est[1]:+.4f}+-{err[1]:.4f}  c1={est[2]:+.5f}+-{err[2]:.5f}")

    _splits(sub, columns, r_bins, e_bins)


def radial_report(t, edges=(0.0, 0.3, 0.5, 0.6, 0.7, 0.76, 0.82, 1.0)):
    """The galaxies' estimates split along and across their true sheared ellipticity e_s (each object's shear applied
    to its intrinsic shape): per bin of |e_s| the mean and scatter of the radial part, the scatter of the tangential
    part, and the slope of the radial part's mean against |e_s| over all of them (1 for an estimator without bias
    along |e|); with a self-calibrated run, the radial responses its solve found (``sc_rrad``) and its steps."""
    t = t[(np.asarray(t["fitclass"]) == 0) & np.isfinite(np.asarray(t["e1"], float))]
    if len(t) < 2:
        return
    ei = np.asarray(t["e1_int"], float) + 1j * np.asarray(t["e2_int"], float)
    g = np.asarray(t["g1"], float) + 1j * np.asarray(t["g2"], float)
    es = sheared_ellipticity(ei, g)
    a = np.abs(es)
    u = np.where(a > 0, es / np.where(a > 0, a, 1.0), 1.0)
    z = (np.asarray(t["e1"], float) + 1j * np.asarray(t["e2"], float)) * np.conj(u)
    rad, tan = z.real, z.imag
    slope = np.polyfit(a, rad, 1)[0] if np.ptp(a) > 0 else np.nan
    print(f"estimates along and across the true sheared e ({len(t)} objects): slope of the radial part's mean against "
          f"|e_s| {slope:.3f}")
    k = np.digitize(a, edges) - 1
    for b in range(len(edges) - 1):
        sel = k == b
        if sel.sum() >= 2:
            print(f"  |e_s| {edges[b]:.2f}-{edges[b + 1]:.2f}  n={sel.sum():5d}  mean |e_s| {a[sel].mean():.4f}  radial "
                  f"{rad[sel].mean():.4f} (rms {rad[sel].std():.3f})  tangential rms {tan[sel].std():.3f}")
    if "sc_rrad" in t.colnames:
        r = np.asarray(t["sc_rrad"], float)
        r = r[np.isfinite(r)]
        if r.size:
            q = np.percentile(r, [10, 50, 90])
            print(f"  self-calibration: radial response found, 10/50/90 %: {q[0]:.3f} {q[1]:.3f} {q[2]:.3f}; below "
                  f"0.25: {np.mean(r < 0.25):.2f}, below 0.1: {np.mean(r < 0.1):.2f}; mean steps "
                  f"{np.nanmean(np.asarray(t['sc_steps'], float)):.2f}")


def _prepared(t, uncorrected, one_pair, keep_stars, noise_level=None):
    """The first run's table as the options read it: the noise bias added back, the one pair's estimates, the
    objects classified as stars counted as galaxies."""
    if uncorrected:
        if "nb_de1" not in t.colnames:
            raise SystemExit("ring_split.py: --uncorrected needs a run with noise_bias_correction (columns nb_de1, "
                             "nb_de2)")
        for i in (1, 2):
            t[f"e{i}"] = np.asarray(t[f"e{i}"]) + np.nan_to_num(np.asarray(t[f"nb_de{i}"]))
    if one_pair:
        t = _one_pair(t)
    if noise_level is not None:
        t = _at_noise_level(t, noise_level)
    if keep_stars:
        t = stars_kept(t)
    return t


def _paired_tables(paths, paired_with, uncorrected, one_pair, keep_stars, noise_level=None):
    """The first runs (``paths``) and the paired ones (``paired_with``, one per first run, in the same order)
    matched table by table, then each side read as one with the galaxies of every pair numbered on alike; and
    the first runs before the matching (for ``--radial``)."""
    if len(paths) != len(paired_with):
        raise SystemExit(f"ring_split.py: --paired-with: {len(paired_with)} table(s) for {len(paths)}: give one paired "
                         "run per table, in the same order")
    firsts, seconds, whole = [], [], []
    off = 0
    for pa, pb in zip(paths, paired_with):
        # a paired run is read as written: its galaxy numbers are the seed's (a stopped run's table may lack some)
        ta = _prepared(Table.read(pa), uncorrected, one_pair, keep_stars, noise_level)
        whole.append(ta)
        tb = Table.read(pb)
        # stars counted as galaxies before the matching, which compares the two runs' failures object by object
        ta, tb, n_split = _matched(ta, stars_kept(tb) if keep_stars else tb)
        if len(ta) == 0:
            raise SystemExit(f"ring_split.py: --paired-with: {pb} has no object (galaxy, rotation, sign) of {pa}")
        if n_split:
            print(f"{pa} with {pb}: {n_split} galaxies left out of both (an object failed in one run only)")
        n_here = int(np.max(ta["galaxy"])) + 1
        ta["galaxy"] = np.asarray(ta["galaxy"]) + off
        tb["galaxy"] = np.asarray(tb["galaxy"]) + off
        off += n_here
        firsts.append(ta)
        seconds.append(tb)

    def one(ts):
        return ts[0] if len(ts) == 1 else vstack(ts, join_type="inner", metadata_conflicts="silent")

    return one(firsts), one(seconds), one(whole)


def _whole_rings(t, other=None):
    """``t`` (and ``other``, paired with it object by object) without the galaxies of which an object was not
    measured as a galaxy in either; prints how many were left out and their lost objects at +g and at -g."""
    lost = np.asarray(t["fitclass"]) != 0
    if other is not None:
        lost |= np.asarray(other["fitclass"]) != 0
    sign = np.asarray(t["sign"])
    n_all = np.unique(np.asarray(t["galaxy"])).size
    t, other, n_out = _without_galaxies_of(lost, t, other)
    print(f"--whole-rings: {n_out} of {n_all} galaxies left out (objects not measured as galaxies: "
          f"{int(np.sum(lost & (sign > 0)))} at +g, {int(np.sum(lost & (sign < 0)))} at -g)")
    return t, other


def main(paths, r_bins=(0, 0.15, 0.3, 10), unweighted=False, paired=False, isotropic=False, uncorrected=False,
         paired_with=None, e_bins=None, one_pair=False, keep_stars=False, radial=False, noise_level=None,
         whole_rings=False):
    other = None
    if paired_with:
        t, other, whole = _paired_tables(paths, paired_with, uncorrected, one_pair, keep_stars, noise_level)
        if radial:
            radial_report(whole)
        other = _weighted(other, unweighted, paired, isotropic)
    else:
        t = _prepared(Table(read_tables(paths)[0]), uncorrected, one_pair, keep_stars, noise_level)
        if radial:
            radial_report(t)
    if whole_rings:
        t, other = _whole_rings(t, other)
    t = _weighted(t, unweighted, paired, isotropic)
    plus = t[t["sign"] > 0]
    g = np.array([plus["g1"][0], plus["g2"][0]])   # the shear of the +g set
    n = int(t["galaxy"].max()) + 1
    columns = _galaxy_columns(t, n)
    rng = np.random.default_rng(0)

    present = np.zeros(n, bool)
    present[t["galaxy"]] = True

    def sub(sel, label):
        idx = np.flatnonzero(sel & present)
        if idx.size < 2:
            return
        sa = _subset_sums(t, idx, n)
        if other is None:
            est, err = shear_bias(sa, g, 500, rng)
            print(f"{label:26s} rings={idx.size:4d}  m1={est[0]:+.4f}+-{err[0]:.4f}  m2={est[1]:+.4f}+-{err[1]:.4f}  "
                  f"c1={est[2]:+.5f}+-{err[2]:.5f}  c2={est[3]:+.5f}+-{err[3]:.5f}")
            return
        sb = _subset_sums(other, idx, n)
        counts = bootstrap_counts(idx.size, 500, rng)
        ba, bb = bias_from_sums(sa, g, counts), bias_from_sums(sb, g, counts)
        for name, est, boot in (("", bias_from_sums(sa, g), ba), (" paired run", bias_from_sums(sb, g), bb),
                                (" first less paired", bias_from_sums(sa, g) - bias_from_sums(sb, g), ba - bb)):
            err = np.nanstd(boot, axis=0)
            print(f"{(label + name):44s} rings={idx.size:4d}  m1={est[0]:+.4f}+-{err[0]:.4f}  "
                  f"m2={est[1]:+.4f}+-{err[1]:.4f}  c1={est[2]:+.5f}+-{err[2]:.5f}")

    _splits(sub, columns, r_bins, e_bins, " arcsec")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("table", nargs="+")
    ap.add_argument("--r-bins", default="0,0.15,0.3,10", help="edges of the true-scalelength bins, arcsec")
    ap.add_argument("--unweighted", action="store_true", help="unit weights for fitclass 0 instead of lensfit's")
    ap.add_argument("--paired-weights", action="store_true",
                    help="each weight the mean over its +g / -g pair: weights that do not respond to the shear")
    ap.add_argument("--isotropic-weights", action="store_true",
                    help="each weight the mean of its bin of flux_snr (the catalogue's iso_weight)")
    ap.add_argument("--uncorrected", action="store_true",
                    help="add back the noise bias that noise_bias_correction subtracted")
    ap.add_argument("--one-pair", action="store_true",
                    help="the estimates as the one-pair extrapolation corrected them (runs with "
                         "noise_bias_second_amplitude)")
    ap.add_argument("--noise-level", type=float, default=None, metavar="V",
                    help="the estimates of the fits at V times the data's noise variance, taken from a two-pair "
                         "run's corrections: 1 (as --uncorrected), 2 (the first pair) or 1 + a^2 (the second pair, "
                         "a its noise_bias_second_amplitude: 4 for sqrt(3))")
    ap.add_argument("--keep-stars", action="store_true",
                    help="count the objects classified as stars (fitclass 1) as galaxies: m without the star/galaxy "
                         "selection's response to the shear")
    ap.add_argument("--e-bins", default=None,
                    help="edges of bins of the galaxies' intrinsic |e| (e.g. 0,0.3,0.5,0.6,0.7,1), each split too")
    ap.add_argument("--paired-with", metavar="TABLE", nargs="+", default=None,
                    help="another run of the same galaxies for each table given (in the same order): its m and c, "
                         "and the first runs' less its, object by object with the galaxies resampled together")
    ap.add_argument("--radial", action="store_true",
                    help="also the estimates along and across the true sheared ellipticity, in bins of its |e|, and "
                         "a self-calibrated run's radial responses")
    ap.add_argument("--whole-rings", action="store_true",
                    help="leave out, whole, every galaxy of which an object was not measured as a galaxy (in either "
                         "run where paired)")
    ap.add_argument("--control", action="append", default=[], metavar="[A=]B",
                    help="a one-pair run B (A=B: of table A's seed) as a control variate for the two-pair tables given")
    a = ap.parse_args()
    if a.uncorrected + a.one_pair + (a.noise_level is not None) > 1:
        ap.error("--uncorrected, --one-pair and --noise-level exclude each other")
    if a.noise_level is not None and not a.noise_level >= 1:
        ap.error("--noise-level V needs V >= 1")
    if a.unweighted + a.paired_weights + a.isotropic_weights > 1:
        ap.error("--unweighted, --paired-weights and --isotropic-weights exclude each other")
    e_edges = [float(x) for x in a.e_bins.split(",")] if a.e_bins else None
    for path in [*a.table, *(a.paired_with or []), *(x for c in a.control for x in c.split("=", 1))]:
        if not os.path.isfile(path):
            ap.error(f"{path}: no such table")
    if a.control:
        if a.uncorrected or a.one_pair or a.paired_with or a.keep_stars or a.whole_rings or a.noise_level is not None:
            ap.error("--control excludes --uncorrected, --one-pair, --noise-level, --paired-with, --keep-stars and "
                     "--whole-rings")
        control_main(a.table, a.control, [float(x) for x in a.r_bins.split(",")], a.unweighted, a.paired_weights,
                     a.isotropic_weights, e_edges)
        sys.exit(0)
    main(a.table, [float(x) for x in a.r_bins.split(",")], a.unweighted, a.paired_weights, a.isotropic_weights,
         a.uncorrected, a.paired_with, e_edges, a.one_pair, a.keep_stars, a.radial, a.noise_level, a.whole_rings)

#!/usr/bin/env python
"""m and c of a ring-test table (benchmarks/ring_test.py --out) split by true scalelength and by sigma_e.

    python benchmarks/ring_split.py ring.fits [ring2.fits ...] [--r-bins 0,0.15,0.3,10] [--unweighted |
                                              --paired-weights | --isotropic-weights] [--uncorrected]

Several tables (runs of the same shear) are read as one, their galaxies numbered on.

``--uncorrected``: for a run with ``--set noise_bias_correction=true``, each estimate with the noise bias it had
subtracted added back (its ``nb_de1``, ``nb_de2``): the same fits without the correction.

``--paired-weights``: each object's weight replaced by the mean over its pair (the same galaxy, orientation and
noise at +g and at -g; ``shearfit.calib.bias.paired_weights``), so that no weight responds to the shear while
each keeps its dependence on the galaxy, its orientation and its noise. m with lensfit's weights less m with
paired weights is the part of m that comes from the weights' response to shear.

``--isotropic-weights``: each weight the mean weight of its bin of ``flux_snr``
(``shearfit.calib.weights.isotropic_weights``, 10 equal-number bins; tables from session 57 on): the weights a
catalogue without ring pairs has (its ``iso_weight``), which do not respond to shear either.
"""

import argparse

import numpy as np
from astropy.table import Table

from shearfit.calib.bias import paired_weights, ring_sums, shear_bias
from shearfit.calib.weights import isotropic_weights

# benchmarks/ring_test.py, beside this script: several runs' tables read as one
from ring_test import read_tables


def main(paths, r_bins=(0, 0.15, 0.3, 10), unweighted=False, paired=False, isotropic=False, uncorrected=False):
    t = Table(read_tables(paths)[0])
    if uncorrected:
        if "nb_de1" not in t.colnames:
            raise SystemExit("ring_split.py: --uncorrected needs a run with noise_bias_correction (columns nb_de1, "
                             "nb_de2)")
        for i in (1, 2):
            t[f"e{i}"] = np.asarray(t[f"e{i}"]) + np.nan_to_num(np.asarray(t[f"nb_de{i}"]))
    if unweighted:   # unit weights for the galaxies (fitclass 0), none for the rest
        t["weight"] = np.where(t["fitclass"] == 0, 1.0, 0.0)
    elif paired:
        t["weight"] = paired_weights(t)
    elif isotropic:
        t["weight"] = isotropic_weights(t)
    plus = t[t["sign"] > 0]
    g = np.array([plus["g1"][0], plus["g2"][0]])   # the shear of the +g set
    n = int(t["galaxy"].max()) + 1
    rgal = np.zeros(n)
    rgal[t["galaxy"]] = t["true_scalelength"]
    sdg = np.array([np.sqrt(np.nanmean(t["e_var"][t["galaxy"] == k])) for k in range(n)])
    rng = np.random.default_rng(0)

    def sub(sel, label):
        idx = np.flatnonzero(sel)
        if idx.size < 2:
            return
        remap = -np.ones(n, int)
        remap[idx] = np.arange(idx.size)
        tt = t[np.isin(t["galaxy"], idx)]
        tab = {c: np.array(tt[c]) for c in ("sign", "e1", "e2", "weight", "fitclass")}
        tab["galaxy"] = remap[np.array(tt["galaxy"])]
        est, err = shear_bias(ring_sums(tab, idx.size), g, 500, rng)
        print(f"{label:26s} rings={idx.size:4d}  m1={est[0]:+.4f}+-{err[0]:.4f}  m2={est[1]:+.4f}+-{err[1]:.4f}  "
              f"c1={est[2]:+.5f}+-{err[2]:.5f}  c2={est[3]:+.5f}+-{err[3]:.5f}")

    sub(np.ones(n, bool), "all")
    for lo, hi in zip(r_bins[:-1], r_bins[1:]):
        sub((rgal >= lo) & (rgal < hi), f"r in [{lo}, {hi}) arcsec")
    for lo, hi in [(0, 0.02), (0.02, 0.05), (0.05, 1)]:
        sub((sdg >= lo) & (sdg < hi), f"sigma_e in [{lo}, {hi})")


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
    a = ap.parse_args()
    if a.unweighted + a.paired_weights + a.isotropic_weights > 1:
        ap.error("--unweighted, --paired-weights and --isotropic-weights exclude each other")
    main(a.table, [float(x) for x in a.r_bins.split(",")], a.unweighted, a.paired_weights, a.isotropic_weights,
         a.uncorrected)

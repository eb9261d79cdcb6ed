#!/usr/bin/env python
"""Calibrated xi+- of a simulated field with a shear field from a power spectrum, against the input's (issue 6, item 1).

Simulates one field (preset ``cfhtlens`` by default: 4 CCDs of 2048 x 4096, 7 dithered exposures with their
own Moffat PSFs, stars at a survey's density, the paper's galaxy population in 90-degree pairs) whose shear
is a Gaussian E-mode field from ``galsim.PowerSpectrum`` (P(k) ~ k^-1.5, scaled to ``--shear-rms`` per
component), measures it with ``shearfit measure`` (PSF models fitted from the field's stars unless
``--psf true``), and computes with ``shearfit.stats.twopoint.xipm`` (TreeCorr) the measured xi+ and xi-, calibrated
by 1 + K from ``--calibration`` (a ``shearfit calibrate`` file; the paper's default alpha, beta without it).

The input's xi+- is TreeCorr's of the true reduced shear at the same galaxies with the same weights, so the
comparison is free of cosmic variance; its errors are jackknife over ``--npatch`` sky patches of the
difference (measured - input), which holds the shape and measurement noise. A chi^2 of the difference over the
bins (jackknife covariance, Hartlap-corrected) says whether the measurement agrees with the input.

    python benchmarks/shear_field_xi.py --out /tmp/psxi -j 2 --calibration /tmp/closure/calibration.yaml

The amplitude (0.04 per component) is above the cosmological one so that one field measures it: a
CFHTLenS-sized field has too few pairs to see xi+ ~ 1e-4.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import treecorr
from astropy.table import Table, join

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from calibration_closure import measure   # noqa: E402  the resumable measure step
from shearfit.simulate.field import simulate_missing   # noqa: E402
from shearfit.stats.twopoint import measured, xipm   # noqa: E402


def input_and_measured(shear_path, truth_path):
    """The measured galaxies joined with their true reduced shear."""
    cat = measured(Table.read(shear_path))
    truth = Table.read(truth_path)[["id", "g1", "g2"]]
    return join(cat, truth, keys="id")


def jackknife_difference(tab, one_plus_k, bins, npatch, seed=1):
    """Jackknife covariance of (xi+_cal - xi+_in, xi-_cal - xi-_in) over sky patches, and of xi+_cal alone."""
    pos = dict(ra=np.asarray(tab["ra"], float), dec=np.asarray(tab["dec"], float), ra_units="deg",
               dec_units="deg", w=np.asarray(tab["weight"], float))
    cm = treecorr.Catalog(g1=np.asarray(tab["e1"], float), g2=np.asarray(tab["e2"], float), npatch=npatch,
                          rng=np.random.default_rng(seed), **pos)
    ct = treecorr.Catalog(g1=np.asarray(tab["g1"], float), g2=np.asarray(tab["g2"], float),
                          patch_centers=cm.patch_centers, **pos)
    gm = treecorr.GGCorrelation(var_method="jackknife", cross_patch_weight="match", **bins)
    gt = treecorr.GGCorrelation(var_method="jackknife", cross_patch_weight="match", **bins)
    gm.process(cm)
    gt.process(ct)

    def diff(c):
        return np.concatenate([c[0].xip / one_plus_k - c[1].xip, c[0].xim / one_plus_k - c[1].xim])

    cov_d = treecorr.estimate_multi_cov([gm, gt], "jackknife", func=diff)
    cov_m = treecorr.estimate_multi_cov([gm], "jackknife", func=lambda c: c[0].xip / one_plus_k)
    return gt, cov_d, cov_m


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--preset", default="cfhtlens")
    ap.add_argument("--seed", type=int, default=101)
    ap.add_argument("--shear-rms", type=float, default=0.04)
    ap.add_argument("--psf", choices=("fitted", "true"), default="fitted")
    ap.add_argument("--calibration", default=None, help="a shearfit calibrate file (default: the paper's alpha, beta)")
    ap.add_argument("--min-sep", type=float, default=0.5, help="arcmin")
    ap.add_argument("--max-sep", type=float, default=12.0, help="arcmin")
    ap.add_argument("--nbins", type=int, default=8)
    ap.add_argument("--npatch", type=int, default=32)
    ap.add_argument("-j", "--processes", type=int, default=os.cpu_count() or 1)
    args = ap.parse_args(argv)
    d = os.path.abspath(args.out)
    t0 = time.time()
    simulate_missing((d, dict(preset=args.preset, seed=args.seed, shear_rms=args.shear_rms)))
    t1 = time.time()
    shear_path, truth_path = measure(d, args.processes, args.psf)
    t2 = time.time()
    tab = input_and_measured(shear_path, truth_path)
    print(f"field: preset {args.preset}, seed {args.seed}, shear rms {args.shear_rms} per component; "
          f"{len(tab)} measured galaxies (simulated in {t1 - t0:.0f} s, measured in {t2 - t1:.0f} s; "
          f"PSF {args.psf})")
    print(f"calibration: {args.calibration or 'the paper default (alpha 0.057, beta -0.37)'}")

    bins = dict(min_sep=args.min_sep, max_sep=args.max_sep, nbins=args.nbins, sep_units="arcmin")
    res, _ = xipm(tab, min_sep=args.min_sep, max_sep=args.max_sep, nbins=args.nbins,
                  calibration=args.calibration, n_sys=0)
    opk = np.asarray(res["one_plus_k"], float)
    gt, cov_d, cov_m = jackknife_difference(tab, opk, bins, args.npatch)
    nb = args.nbins
    sig_d = np.sqrt(np.diag(cov_d))
    sig_m = np.sqrt(np.diag(cov_m))
    print(f"errors: jackknife over {args.npatch} patches; TreeCorr's shot-noise sigma(xi+) of the measured "
          f"catalogue for comparison: {' '.join(f'{v:.1e}' for v in np.asarray(res['sigma_xip']))}")
    print("\n  theta'   xi+ input   xi+ raw    xi+ cal   +/- (cal)   (cal-in)/sigma_diff  |  xi- input   xi- cal   "
          "(cal-in)/sigma_diff")
    for i in range(nb):
        print(f"  {res['theta'][i]:6.2f}  {gt.xip[i]:+.3e}  {res['xip_raw'][i]:+.3e}  {res['xip'][i]:+.3e}  "
              f"{sig_m[i]:.1e}   {(res['xip'][i] - gt.xip[i]) / sig_d[i]:+6.2f}               |  "
              f"{gt.xim[i]:+.3e}  {res['xim'][i]:+.3e}  {(res['xim'][i] - gt.xim[i]) / sig_d[nb + i]:+6.2f}")
    d_vec = np.concatenate([res["xip"] - gt.xip, res["xim"] - gt.xim])
    for name, sl in (("xi+", slice(0, nb)), ("xi-", slice(nb, 2 * nb)), ("xi+ and xi-", slice(0, 2 * nb))):
        n = sl.stop - sl.start
        h = (args.npatch - n - 2) / (args.npatch - 1)
        chi2 = float(d_vec[sl] @ np.linalg.solve(cov_d[sl, sl], d_vec[sl])) * h if h > 0 else np.nan
        print(f"  {name}: chi^2 of calibrated - input = {chi2:.1f} for {n} bins (jackknife covariance, "
              f"Hartlap factor {h:.2f})")
    ratio = np.sum(res["xip"] / sig_d[:nb] ** 2 * gt.xip) / np.sum(gt.xip ** 2 / sig_d[:nb] ** 2)
    ratio_raw = np.sum(res["xip_raw"] / sig_d[:nb] ** 2 * gt.xip) / np.sum(gt.xip ** 2 / sig_d[:nb] ** 2)
    amp_err = 1.0 / np.sqrt(np.sum(gt.xip ** 2 / sig_d[:nb] ** 2))
    print(f"  amplitude xi+ measured / input (diagonal weights): calibrated {ratio:.3f}, raw {ratio_raw:.3f}, "
          f"+/- {amp_err:.3f}; mean 1 + K = {np.mean(opk):.3f}")
    plot(os.path.join(d, "xipm.png"), res, gt, sig_d, sig_m, nb)
    Table({"theta": res["theta"], "xip_in": gt.xip, "xim_in": gt.xim, "xip": res["xip"], "xim": res["xim"],
           "xip_raw": res["xip_raw"], "xim_raw": res["xim_raw"], "one_plus_k": opk, "sigma_diff_xip": sig_d[:nb],
           "sigma_diff_xim": sig_d[nb:], "sigma_xip": sig_m}).write(os.path.join(d, "xipm_vs_input.fits"),
                                                                      overwrite=True)
    print(f"\nplot: {os.path.join(d, 'xipm.png')}; numbers: {os.path.join(d, 'xipm_vs_input.fits')}")
    return 0


def plot(path, res, gt, sig_d, sig_m, nb):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    th = np.asarray(res["theta"])
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    ax[0].plot(th, gt.xip, "k-", label="input (true shear, same galaxies)")
    ax[0].errorbar(th, res["xip"], sig_m, fmt="o", label="measured, calibrated (jackknife)")
    ax[0].plot(th, res["xip_raw"], "x", color="0.5", label="measured, raw")
    ax[0].set_xscale("log")
    ax[0].set_xlabel("theta (arcmin)")
    ax[0].set_ylabel("xi+")
    ax[0].legend(fontsize=8)
    ax[1].axhline(0, color="k", lw=0.8)
    ax[1].errorbar(th, res["xip"] - gt.xip, sig_d[:nb], fmt="o", label="xi+ calibrated - input")
    ax[1].errorbar(th * 1.04, res["xim"] - gt.xim, sig_d[nb:], fmt="s", label="xi- calibrated - input")
    ax[1].set_xscale("log")
    ax[1].set_xlabel("theta (arcmin)")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())

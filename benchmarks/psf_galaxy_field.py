"""PSF-galaxy cross-correlation on simulated fields with a coherent PSF anisotropy and no shear (issue 6, item 2).

Simulates ``--seeds`` GREAT-like fields (the paper's population, 7 dithered exposures, 2 CCDs) whose
exposures all have PSF ellipticity ``--psf-e`` (along e1; ``psf_e_fixed``) and zero shear, with
90-degree galaxy pairs so that shape noise cancels, measures them with the true PSF given, and runs
``shearfit systematics`` on the catalogues: <e . e_psf> against SNR and size, with errors from
subsamples. Reuses what is already under ``--out``.

    python benchmarks/psf_galaxy_field.py --out /tmp/psfgal --seeds 8 -j 2
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np
from astropy.io import fits
from astropy.table import vstack

from calibration_closure import measure   # the same resumable measure step (benchmarks/ is on sys.path)
from shearfit.app.cli import main as cli_main
from shearfit.simulate.field import simulate_missing
from shearfit.stats.systematics import equal_number_edges, psf_galaxy_xcorr, read_catalogs


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--psf-e", type=float, default=0.1)
    ap.add_argument("--ccd", type=int, default=1024)
    ap.add_argument("-j", "--processes", type=int, default=os.cpu_count() or 1)
    args = ap.parse_args(argv)
    out = os.path.abspath(args.out)
    t0 = time.time()
    base = dict(preset="small", ccd_nx=args.ccd, ccd_ny=args.ccd, grid_spacing=48.0, star_density=1.5,
                shear=[0.0, 0.0], psf_e_fixed=[args.psf_e, 0.0])
    jobs = [(os.path.join(out, f"s{seed}"), dict(base, seed=seed)) for seed in range(4000, 4000 + args.seeds)]
    with ProcessPoolExecutor(args.processes) as pool:
        list(pool.map(simulate_missing, jobs))
    measured = [measure(d, args.processes, "true") for d, _ in jobs]   # (catalogue, truth) per field
    cats = [cat for cat, _ in measured]
    print(f"{len(cats)} fields simulated and measured in {time.time() - t0:.0f} s")
    if cli_main(["systematics", *cats, "--out", os.path.join(out, "systematics")]) != 0:
        raise SystemExit("shearfit systematics failed")
    with fits.open(os.path.join(out, "systematics", "systematics.fits")) as h:
        for ext, col in (("PSFGAL_SNR", "SNR"), ("PSFGAL_SIZE", "scalelength")):
            t = h[ext].data
            t = t[t["field"] == "all"]
            print(f"\n<e . e_psf> against {col} (all fields; e_psf = {args.psf_e}, so <e . e_psf> / e_psf^2 is "
                  f"the leakage alpha):")
            for row in t:
                a = row["xi_psf_gal"] / args.psf_e ** 2
                ea = row["xi_err"] / args.psf_e ** 2
                print(f"  {row['lo']:8.3f} - {row['hi']:8.3f}: {row['xi_psf_gal']:+.2e} +/- {row['xi_err']:.1e}   "
                      f"alpha = {a:+.4f} +/- {ea:.4f}   ({row['n']} galaxies)")
    residual_leakage(cats, [truth for _, truth in measured], args.psf_e)
    return 0


def residual_leakage(cats, truths, psf_e, n_bins=8):
    """<(e - e_int) . e_psf> against SNR: the same leakage with the known intrinsic shapes taken out.

    With zero shear e - e_int holds the measurement's noise and biases only: no shape noise, so the
    errors (10 random subsamples, as ``shearfit systematics``) are smaller than those of <e . e_psf>.
    """
    tab = vstack([read_catalogs([cat], truth=truth)[0] for cat, truth in zip(cats, truths)],
                 metadata_conflicts="silent")
    tab["e1"] = tab["e1"] - tab["e1_int"]
    tab["e2"] = tab["e2"] - tab["e2_int"]
    xc = psf_galaxy_xcorr(tab, "snr", equal_number_edges(np.asarray(tab["snr"], float), n_bins),
                          rng=np.random.default_rng(0))
    print("\n<(e - e_int) . e_psf> against SNR (all fields, the intrinsic shapes taken out; alpha as above):")
    for row in xc:
        print(f"  {row['lo']:8.3f} - {row['hi']:8.3f}: {row['xi_psf_gal']:+.2e} +/- {row['xi_err']:.1e}   "
              f"alpha = {row['xi_psf_gal'] / psf_e ** 2:+.4f} +/- {row['xi_err'] / psf_e ** 2:.4f}   "
              f"({row['n']} galaxies)")


if __name__ == "__main__":
    sys.exit(main())

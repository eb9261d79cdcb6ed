#!/usr/bin/env python
"""The estimator's noise-free response along |e| for one small galaxy, and what the self-calibration makes of it.

For galaxies of one scalelength and bulge fraction at several intrinsic ellipticities (along e1; the paper's
population otherwise, GalSim-rendered, 7 exposures, no noise but the weights of the drawn SNR), prints the
likelihood-mean estimate e_hat, sigma_e, then f(e): the estimate on noise-free images of the fitted model at
ellipticities along the same axis, measured as the data were (what ``self_calibration`` solves f(e) = e_hat on),
with its slope between grid points; and the self-calibrated estimate with the responses found on the model.

    python benchmarks/selfcal_response.py                       # scalelength 0.11", bulge fraction 0.1
    python benchmarks/selfcal_response.py --scalelength 0.2
    python benchmarks/selfcal_response.py --set self_calibration_min_response=0.25 --set self_calibration_steps=4

Where f's slope falls below ``self_calibration_min_response`` (default 0.5) the bound cuts the response the
correction divides by, and the correction falls short of the galaxy's ellipticity.
"""

import argparse
import os
import sys

import numpy as np

import shearfit
from shearfit.config import settings_from_items
from shearfit.engine import measure as M
from shearfit.simulate.stamps import ring_set

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from ring_test import _paper_population  # noqa: E402


def fixed_population(e, r, bulge_fraction):
    def draw(mags, rng, cfg):
        p = _paper_population(mags, rng, cfg)
        p["scalelength"][:] = r
        p["e1"][:] = e
        p["e2"][:] = 0.0
        p["bulge_fraction"][:] = bulge_fraction
        p["is_bulge"][:] = bulge_fraction > 0.5
        return p
    return draw


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scalelength", type=float, default=0.11, help="arcsec (default 0.11)")
    ap.add_argument("--bulge-fraction", type=float, default=0.1)
    ap.add_argument("--e", type=float, nargs="+", default=[0.3, 0.5, 0.6, 0.7, 0.75, 0.8],
                    help="the galaxies' intrinsic |e| (each one galaxy)")
    ap.add_argument("--grid", type=float, nargs="+", default=[0.5, 0.6, 0.7, 0.75, 0.8, 0.85, 0.9],
                    help="the ellipticities at which f is evaluated")
    ap.add_argument("--seed", type=int, default=7, help="the draw of the PSFs, dithers and SNR")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="engine setting")
    args = ap.parse_args(argv)
    cfg = shearfit.fit_config_from_mapping({"self_calibration": True, **settings_from_items(args.set)})
    print(f"scalelength {args.scalelength}\", bulge fraction {args.bulge_fraction}, no noise; "
          f"self_calibration_min_response {cfg.self_calibration_min_response}, steps {cfg.self_calibration_steps}")
    print("f(e) at e = " + " ".join(f"{x:.3f}" for x in args.grid))
    for e in args.e:
        gal = ring_set(1, (0.0, 0.0), np.random.default_rng(args.seed), n_rotations=1, add_noise=False, cfg=cfg,
                       population=fixed_population(e, args.scalelength, args.bulge_fraction))
        obs, truth = gal[0]
        res, plan = M._measure(obs, truth["mag"], cfg, False)
        e_hat = res.e1

        def f(x):
            models = M.model_observations(obs, plan, (x, 0.0, res.scalelength, res.bulge_fraction, res.model_flux),
                                          cfg)
            ref, _ = M._measure(models, truth["mag"], cfg, False, plan=plan, margin=10.0)
            return ref.e1

        fg = np.array([f(x) for x in args.grid])
        slope = np.diff(fg) / np.diff(args.grid)
        sigma = float(np.sqrt(res.e_var))
        M._self_calibrate(obs, truth["mag"], cfg, res, plan)
        print(f"|e| {e:.3f} (SNR {truth['snr']:.0f}): e_hat {e_hat:+.4f}, sigma_e {sigma:.3f}; self-calibrated "
              f"{res.e1:+.4f} (radial response found {res.selfcal_response[0]:.3f}, tangential "
              f"{res.selfcal_response[1]:.3f}, {res.selfcal_steps} step(s))")
        print("    f(e):  " + " ".join(f"{v:.4f}" for v in fg))
        print("    slope: " + " ".join(f"{v:.3f}" for v in slope))
    return 0


if __name__ == "__main__":
    sys.exit(main())

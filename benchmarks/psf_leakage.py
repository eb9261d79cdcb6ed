#!/usr/bin/env python
"""PSF leakage alpha = c / e_psf: rings of the paper's population under one fixed elliptical PSF.

The ring test of ring_test.py draws new PSFs for every galaxy, so leakage
averages away there; here every galaxy sees the same PSF (ellipticity
--psf-e along e1), at --n-exposures exposures, noise-free images with the
weights of the SNR range (the expected likelihood), rings of 4 with +-g.
Prints m, c and alpha = c1 / e_psf overall and split by scalelength. With noise, antithetic twins and metacal,
``ring_test.py --psf-e-fixed E1 E2`` measures the same leakage.

    python benchmarks/psf_leakage.py --n-galaxies 24 --psf-e 0.08
"""

from __future__ import annotations

import argparse
import os

import numpy as np

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import shearfit  # noqa: E402
from shearfit.engine import priors  # noqa: E402
from shearfit.calib.bias import ring_sums, shear_bias  # noqa: E402
from shearfit.simulate.stamps import draw_psf_image, draw_stamp, galaxy_profile, moffat_psf, noise_for_snr  # noqa: E402

PIX = 0.187
J = PIX * np.eye(2)


def one_ring(args_tuple):
    i, gal, psf_e, n_exp, seed, g = args_tuple
    rng = np.random.default_rng([seed, i])
    psf = moffat_psf(0.65, 3.0, psf_e, 0.0)
    pim = draw_psf_image(psf, J, size=64)
    offs = rng.uniform(-0.5, 0.5, (n_exp, 2))
    rows = []
    sigma = None
    for sign in (1, -1):
        for k in range(4):
            ej = complex(gal["e1"], gal["e2"]) * np.exp(1j * np.pi * k / 2)
            prof = galaxy_profile(gal["r"], gal["B"], ej.real, ej.imag, flux=1000.0, g1=sign * g[0], g2=sign * g[1],
                                  is_bulge=gal["is_bulge"])
            ims = [draw_stamp(prof, psf, J, o) for o in offs]
            if sigma is None:
                sigma = noise_for_snr(ims, gal["snr"])
            obs = [shearfit.Observation(image=im, weight=np.full(im.shape, 1 / sigma ** 2), psf=pim, jacobian=J,
                                        offset=tuple(o)) for im, o in zip(ims, offs)]
            res = shearfit.measure_object(obs, mag=gal["mag"])
            rows.append((i, sign, res.e1, res.e2, res.weight, res.fitclass))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n-galaxies", type=int, default=24)
    ap.add_argument("--psf-e", type=float, default=0.08)
    ap.add_argument("--n-exposures", type=int, default=3)
    ap.add_argument("--snr-min", type=float, default=100.0)
    ap.add_argument("--snr-max", type=float, default=200.0)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--processes", type=int, default=os.cpu_count())
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    gals = []
    while len(gals) < args.n_galaxies:
        p = priors.sample_population(rng.uniform(21.0, 24.5, 1), rng)[0]
        if 4.5 * p["scalelength"] / PIX > 20:
            continue
        gals.append(dict(r=float(p["scalelength"]), B=float(p["bulge_fraction"]), is_bulge=bool(p["is_bulge"]),
                         e1=float(p["e1"]), e2=float(p["e2"]), mag=float(p["mag"]),
                         snr=rng.uniform(args.snr_min, args.snr_max)))
    g = (0.03, -0.02)
    tasks = [(i, gal, args.psf_e, args.n_exposures, args.seed, g) for i, gal in enumerate(gals)]
    if args.processes > 1:
        import multiprocessing
        with multiprocessing.get_context("fork").Pool(args.processes) as pool:
            out = pool.map(one_ring, tasks)
    else:
        out = [one_ring(t) for t in tasks]
    rows = np.array([r for ring in out for r in ring])
    tab = {"galaxy": rows[:, 0].astype(int), "sign": rows[:, 1], "e1": rows[:, 2], "e2": rows[:, 3],
           "weight": rows[:, 4], "fitclass": rows[:, 5].astype(int)}
    r = np.array([gal["r"] for gal in gals])
    brng = np.random.default_rng(0)
    print(f"{args.n_galaxies} rings, one PSF (Moffat 0.65\", e_psf = ({args.psf_e}, 0)), {args.n_exposures} exposures, "
          f"noise-free, SNR {args.snr_min:.0f}-{args.snr_max:.0f}")
    for label, sel in [("all", np.ones(r.size, bool)), ("r < 0.2\"", r < 0.2), ("r >= 0.2\"", r >= 0.2)]:
        idx = np.flatnonzero(sel)
        if idx.size < 2:
            continue
        remap = -np.ones(r.size, int)
        remap[idx] = np.arange(idx.size)
        keep = np.isin(tab["galaxy"], idx)
        sub = {k: v[keep] for k, v in tab.items()}
        sub["galaxy"] = remap[sub["galaxy"]]
        est, err = shear_bias(ring_sums(sub, idx.size), np.array(g), 500, brng)
        print(f"  {label:10s} rings={idx.size:3d}  m1={est[0]:+.4f}+-{err[0]:.4f}  c1={est[2]:+.5f}+-{err[2]:.5f}  "
              f"c2={est[3]:+.5f}+-{err[3]:.5f}   alpha = c1/e_psf = {est[2] / args.psf_e:+.4f} +- "
              f"{err[2] / args.psf_e:.4f}")


if __name__ == "__main__":
    main()

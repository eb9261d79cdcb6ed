#!/usr/bin/env python
"""Why unresolved galaxies have m > 0 without noise: the likelihood-mean estimator's own response.

1. For a noise-free r = 0.1" galaxy (weights of SNR 150), print the likelihood's maximum,
   the posterior's maximum and the likelihood mean, and log L along e1: the surface peaks at
   the truth but is skewed towards high |e| (size-ellipticity degeneracy), so its mean is not.
2. m and c of one 4-orientation +-g ring of such galaxies with each numerical ingredient
   switched in turn (posterior cut, grid resolution, bulge population, size nodes, alias
   correction): the bias does not come from any of them.
3. The same ring with the size prior evaluated at the semi-major scalelength (the paper's), at the
   round model of the same area, r sqrt(q), and at the semi-minor one, r q: where the prior lies on
   its rising side, the axis it is evaluated at weighs the ellipticities of the size-marginalised
   likelihood by a power of q, which moves the likelihood mean's response.

    python benchmarks/small_galaxy_bias.py [--r 0.1] [--snr 150]
"""

import argparse

import numpy as np

import shearfit
from shearfit.simulate.stamps import draw_psf_image, draw_stamp, galaxy_profile, moffat_psf, noise_for_snr

PIX = 0.187
J = PIX * np.eye(2)


def setup(seed=7):
    rng = np.random.default_rng(seed)
    psfs = [moffat_psf(rng.uniform(0.55, 0.75), rng.uniform(2.5, 4.5), *rng.uniform(-0.07, 0.07, 2)) for _ in range(7)]
    offs = rng.uniform(-0.5, 0.5, (7, 2))
    return psfs, offs, [draw_psf_image(p, J, size=48) for p in psfs]


def observations(r, e, g, snr, psfs, offs, pims, sigma=None):
    gal = galaxy_profile(r, 0.05, e.real, e.imag, flux=1000.0, g1=g[0], g2=g[1])
    ims = [draw_stamp(gal, p, J, o) for p, o in zip(psfs, offs)]
    sigma = sigma or noise_for_snr(ims, snr)
    obs = [shearfit.Observation(image=im, weight=np.full(im.shape, 1 / sigma ** 2), psf=pi, jacobian=J, offset=o)
           for im, pi, o in zip(ims, pims, offs)]
    return obs, sigma


def ring_bias(args, g, cfg, psfs, offs, pims):
    """m and c of one noise-free 4-orientation ring of the galaxy at shear +-g (weighted means)."""
    mean = {}
    sigma = None
    for sign in (1, -1):
        es = []
        for k in range(4):
            obs, sigma = observations(args.r, args.e * np.exp(1j * np.pi * k / 2), sign * g, args.snr, psfs, offs,
                                      pims, sigma)
            res = shearfit.measure_object(obs, mag=24.0, config=cfg)
            es.append((res.e1, res.e2, res.weight))
        es = np.array(es)
        mean[sign] = np.array([np.average(es[:, 0], weights=es[:, 2]), np.average(es[:, 1], weights=es[:, 2])])
    return (mean[1] - mean[-1]) / (2 * g) - 1, (mean[1] + mean[-1]) / 2


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--r", type=float, default=0.1)
    ap.add_argument("--snr", type=float, default=150.0)
    ap.add_argument("--e", type=float, default=0.35)
    args = ap.parse_args(argv)
    psfs, offs, pims = setup()
    print(f"1. noise-free galaxy r = {args.r}\", weights of SNR {args.snr}, 7 exposures")
    for e_true in (args.e, 0.0):
        obs, _ = observations(args.r, complex(e_true), (0, 0), args.snr, psfs, offs, pims)
        res = shearfit.measure_object(obs, mag=24.0, return_samples=True, config={"e_grid_min": 0.005})
        s = res.samples
        i, j = np.argmax(s["logl"]), np.argmax(s["logpost"])
        print(f"   truth e1 = {e_true:+.3f}: max likelihood at ({s['e1'][i]:+.3f}, {s['e2'][i]:+.3f}), max posterior at "
              f"({s['e1'][j]:+.3f}, {s['e2'][j]:+.3f}), likelihood mean ({res.e1:+.3f}, {res.e2:+.3f}), "
              f"sigma_e {np.sqrt(res.e_var):.3f}")
        on = np.abs(s["e2"]) < 1e-9
        o = np.argsort(s["e1"][on])
        prof = " ".join(f"{a:+.2f}:{b - s['logl'].max():.1f}" for a, b in zip(s["e1"][on][o][::3], s["logl"][on][o][::3]))
        print(f"     log L along e1 (e2 = 0): {prof}")
    print(f"2. a ring of 4 orientations, |e| = {args.e}, shear +-(0.03, -0.02), same galaxy, noise-free:")
    g = np.array([0.03, -0.02])
    for label, cfg in [("default", {}), ("no posterior cut", {"posterior_cut": 1e-9}),
                       ("grid down to 0.005", {"e_grid_min": 0.005}),
                       ("no bulge population", {"bulge_population_fraction": 0.0}),
                       ("15 size nodes", {"n_size": 15}), ("no alias correction", {"alias_correction": "none"})]:
        m, c = ring_bias(args, g, cfg, psfs, offs, pims)
        print(f"   {label:22s} m = ({m[0]:+.4f}, {m[1]:+.4f})   c = ({c[0]:+.5f}, {c[1]:+.5f})")
    print("3. the same ring with the size prior evaluated at another scalelength of the elliptical model "
          "(size_prior_axis):")
    for axis in ("major", "area", "minor"):
        cfg = {"size_prior_axis": axis}
        obs, _ = observations(args.r, complex(args.e), (0, 0), args.snr, psfs, offs, pims)
        mean_e = shearfit.measure_object(obs, mag=24.0, config=cfg).e1
        m, _ = ring_bias(args, g, cfg, psfs, offs, pims)
        print(f"   {axis:6s} likelihood mean of the unsheared e1 = {args.e}: {mean_e:+.3f};   m = ({m[0]:+.4f}, {m[1]:+.4f})")


if __name__ == "__main__":
    main()

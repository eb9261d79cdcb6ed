#!/usr/bin/env python
"""Each model's position: what the marginalisation credits against the cross-correlation's true peak.

The likelihood of a model (e, r) is marginalised over position from one reference position (the round model's
cross-correlation peak) by a second-order expansion: the cross-correlation's value, gradient and curvature there,
a Newton step of at most ``position_max_step`` pixels to the model's own peak, and a Gaussian volume. The best
value the step credits, -chi^2 / 2 at the best flux and position (``Marginal.chi2_disk``), should not exceed the
model's true peak. Here each fit's models (its ellipticity samples within 12 nats of the posterior's peak, each at
its posterior-mean size) are evaluated three ways:

- credited: -chi^2 / 2 from the marginalisation, as the fit computes it (binned sums, the setting in use);
- peak: the largest value of the cross-correlation (h^2 / 2 ff, the exact model sums of the data moved by each
  shift) on a grid of positions, +-0.4" in steps of 0.1", then +-0.05" around the best in steps of 0.025": a lower
  bound of the true peak;
- with ``--galsim N``, for the N models credited most beyond their peak, the same value from pixels: the model
  drawn by GalSim (a truncated exponential disk with the semi-major axis kept, convolved with each exposure's PSF
  image and drawn on its pixels), its best flux against the stamps with their weights, at the reference position
  and at the best of a grid of shifts: independent of the engine's Fourier-space sums.

    python benchmarks/position_step.py --n-galaxies 150 --snr-min 10 --snr-max 14 --metacal --galsim 3
    python benchmarks/position_step.py --n-galaxies 150 --snr-min 10 --snr-max 14 --metacal \\
        --set position_max_step=4 --galsim 3

``--metacal`` measures metacal's noshear images (about twice the image's noise, where the pathology is commonest).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
from multiprocessing import Pool  # noqa: E402

import numpy as np  # noqa: E402

import shearfit  # noqa: E402
from shearfit.config import settings_from_items  # noqa: E402
from shearfit.engine.likelihood import flux_position_marginal, model_sums, shift_joint  # noqa: E402
from shearfit.engine.measure import _measure  # noqa: E402
from shearfit.engine.profiles import fast_pair  # noqa: E402
from shearfit.simulate import ring_set  # noqa: E402

COARSE = np.arange(-0.4, 0.401, 0.1)
FINE = np.arange(-0.05, 0.051, 0.025)
#: samples within this many nats of the posterior's peak are evaluated
WITHIN = 12.0


def _peak(jm, e1, e2, r, cfg, fast):
    """The best h^2 / 2 ff of each model over the coarse grid of shifts, then the fine one around its best."""
    def values(du, dv, idx):
        s = model_sums(shift_joint(jm, du, dv), e1[idx], e2[idx], r[idx], fast, cfg.bulge_size_ratio,
                       bins_per_octave=0)
        return 0.5 * s.hf ** 2 / s.ff
    n = e1.size
    best = np.full(n, -np.inf)
    at = np.zeros((n, 2))
    allm = np.arange(n)
    for a in COARSE:
        for b in COARSE:
            v = values(a, b, allm)
            up = v > best
            best[up], at[up] = v[up], (a, b)
    for i in range(n):
        for a in FINE:
            for b in FINE:
                v = values(at[i, 0] + a, at[i, 1] + b, [i])[0]
                if v > best[i]:
                    best[i] = v
    return best, at


def _observations(seed, opts):
    """One galaxy's exposures and truth, drawn from ``seed`` (metacal's noshear images of them with
    ``opts["metacal"]``): the same each time, for the fit and for the GalSim check."""
    rng = np.random.default_rng(seed)
    (obs, truth), = ring_set(1, (0.0, 0.0), rng, n_rotations=1, snr_range=opts["snr"], rotate_exposures=True,
                             cfg=opts["cfg"])
    if opts["metacal"]:
        from shearfit.calib.metacal import metacal_observations
        obs = [metacal_observations(o, 0.01, rng, versions=("noshear",))["noshear"] for o in obs]
    return obs, truth


def _galaxy(task):
    index, seed, opts = task
    cfg = opts["cfg"]
    fast = fast_pair(cfg.truncation)
    obs, truth = _observations(seed, opts)
    _, plan = _measure(obs, truth["mag"], cfg, False)
    if plan is None:
        return None
    s = plan.samples
    ok = np.isfinite(s.logpost)
    sel = ok & (s.logpost > np.max(s.logpost[ok]) - WITHIN)
    e1, e2, r = s.e1[sel], s.e2[sel], np.asarray(s.point.mean_r, float)[sel]
    jm = plan.joint
    credited = -0.5 * flux_position_marginal(model_sums(jm, e1, e2, r, fast, cfg.bulge_size_ratio,
                                                        bins_per_octave=cfg.mode_bins_per_octave),
                                             cfg, jm.pixel_scale).chi2_disk
    ref = model_sums(jm, e1, e2, r, fast, cfg.bulge_size_ratio, bins_per_octave=0)
    peak, at = _peak(jm, e1, e2, r, cfg, fast)
    return dict(index=index, seed=seed, e1=e1, e2=e2, r=r, credited=credited, ref=0.5 * ref.hf ** 2 / ref.ff,
                peak=peak, at=at, shift=plan.shift, snr=truth["snr"])


def _galsim_value(obs, shift, e1, e2, r, cfg, shifts):
    """The best flux's value (sum w d m)^2 / (2 sum w m^2) of the GalSim-drawn model at each sky shift."""
    import galsim

    from shearfit.simulate.stamps import galaxy_profile, jacobian_wcs
    out = []
    for du, dv in shifts:
        num = den = 0.0
        for o in obs:
            k = o.psf_oversampling
            psf = galsim.InterpolatedImage(galsim.Image(np.ascontiguousarray(o.psf),
                                                        wcs=jacobian_wcs(np.asarray(o.jacobian) / k)))
            gal = galaxy_profile(r, 0.0, e1, e2, truncation=cfg.truncation).shift(shift[0] + du, shift[1] + dv)
            ny, nx = o.image.shape
            m = galsim.Convolve([gal, psf]).drawImage(nx=nx, ny=ny, wcs=jacobian_wcs(o.jacobian), method="no_pixel",
                                                      use_true_center=False, offset=tuple(map(float, o.offset))).array
            num += np.sum(o.weight * o.image * m)
            den += np.sum(o.weight * m * m)
        out.append(0.5 * num * num / den)
    return np.array(out)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--n-galaxies", type=int, default=100)
    p.add_argument("--snr-min", type=float, default=10.0)
    p.add_argument("--snr-max", type=float, default=14.0)
    p.add_argument("--seed", type=int, default=52)
    p.add_argument("--metacal", action="store_true", help="fit metacal's noshear images instead of the stamps")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="engine setting")
    p.add_argument("--galsim", type=int, default=0, metavar="N",
                   help="check the N models credited most beyond their peak against GalSim-drawn pixels")
    p.add_argument("--processes", type=int, default=2)
    args = p.parse_args(argv)
    cfg = shearfit.fit_config_from_mapping(settings_from_items(args.set))
    opts = dict(cfg=cfg, snr=(args.snr_min, args.snr_max), metacal=args.metacal)
    seeds = np.random.SeedSequence(args.seed).spawn(args.n_galaxies)
    tasks = [(i, s, opts) for i, s in enumerate(seeds)]
    with Pool(args.processes) as pool:
        fits = [f for f in pool.map(_galaxy, tasks, chunksize=1) if f is not None]
    over = np.concatenate([f["credited"] - f["peak"] for f in fits])
    emod = np.concatenate([np.hypot(f["e1"], f["e2"]) for f in fits])
    print(f"{len(fits)} fits ({'metacal noshear images' if args.metacal else 'stamps'}, target SNR "
          f"{args.snr_min:g}-{args.snr_max:g}), {over.size} models within {WITHIN:g} nats of each posterior's peak; "
          f"position_max_step = {cfg.position_max_step:g} pixels")
    print(f"  credited - peak (nats): median {np.median(over):+.2f}, 99 % {np.percentile(over, 99):+.2f}, "
          f"largest {over.max():+.2f}; models above +1: {np.sum(over > 1)}, above +2: {np.sum(over > 2)}, "
          f"above +5: {np.sum(over > 5)}; below -1: {np.sum(over < -1)}")
    if np.any(emod > 0.8):
        print(f"  |e| > 0.8 ({np.sum(emod > 0.8)} models): largest credited - peak {over[emod > 0.8].max():+.2f}")
    if args.galsim:
        flat = [(f["credited"][i] - f["peak"][i], k, i) for k, f in enumerate(fits) for i in range(f["e1"].size)]
        for _, k, i in sorted(flat, reverse=True)[:args.galsim]:
            f = fits[k]
            obs, _ = _observations(f["seed"], opts)
            grid = [(a, b) for a in COARSE for b in COARSE]
            g = _galsim_value(obs, f["shift"], f["e1"][i], f["e2"][i], f["r"][i], cfg, [(0.0, 0.0)] + grid)
            print(f"  galaxy {f['index']} (target SNR {f['snr']:.1f}), e = ({f['e1'][i]:+.3f}, {f['e2'][i]:+.3f}), "
                  f"r = {f['r'][i]:.2f}\": credited {f['credited'][i]:.2f}, engine at the reference {f['ref'][i]:.2f}, "
                  f"peak {f['peak'][i]:.2f}; GalSim pixels at the reference {g[0]:.2f}, best on the 0.1\" grid "
                  f"{g[1:].max():.2f}")


if __name__ == "__main__":
    main()

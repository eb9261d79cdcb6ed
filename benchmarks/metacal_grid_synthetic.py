#!/usr/bin/env python
"""Metacal's replays against own grids, on synthetic likelihoods: what a grid fixed from the noshear fit misses.

Metacal's sheared versions replay the noshear fit's ellipticity samples and cells
(:func:`shearfit.engine.sampling.replay_samples`), so that their estimates follow the pixels smoothly. A true shear
moves the noshear fit's own adaptive grid too: its step (halved until ``n_above`` samples lie above
``above_fraction`` of the peak), the regions it refines and the cells at the posterior cut. The response of the
estimate through those choices is in the derivative of its mean, d<e>/dg, but not in the replays' R. This script
measures the difference on likelihoods made up for it, where thousands of objects take seconds: the estimator,
the grids, the priors and the cut are the package's own (``adaptive_samples``, ``replay_samples``, ``estimate``,
metacal's finest step ``E_GRID_MIN``), only the likelihood is not an image's.

Each object has an intrinsic ellipticity of modulus ``--e-int`` at a random angle; its likelihood peaks at that
plus a noise offset of the likelihood's width (drawn per object), and is a Gaussian of that width either in e
(``--likelihood e``) or in the moments' ellipticity chi = 2 e / (1 + |e|^2) (``chi``: long tails towards |e| = 1,
as a small or faint galaxy's). The bulge and disk populations share it, so that the posterior is it times the
mixture of the paper's ellipticity priors. A shear moves the peak by +-``--delta`` along e1 (to first order, as a
small shear moves an ellipticity). Per object:

- ``R replay``: (e(+delta) - e(-delta)) / (2 delta) with the noshear fit's samples replayed (metacal's default);
- ``R own``: the same with each version's own adaptive grid, whose mean over objects is d<e>/dg to O(delta^2)
  (the grids' jumps counted as often as a shear of 2 delta makes them).

``<R replay> - <R own>`` (paired per object) over ``<R replay>`` is the m that the replays' fixed choices would
give metacal with this estimator; ``--set KEY=VALUE`` changes the fit's settings (e.g. ``posterior_cut``,
``n_above``).

    python benchmarks/metacal_grid_synthetic.py --widths 0.05,0.1,0.2 --n-objects 3000
    python benchmarks/metacal_grid_synthetic.py --log-uniform 0.03 0.3 --n-objects 20000
    python benchmarks/metacal_grid_synthetic.py --log-uniform 0.03 0.3 --likelihood chi --n-objects 20000
    python benchmarks/metacal_grid_synthetic.py --widths 0.05,0.1 --set posterior_cut=0.001
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from shearfit.calib.metacal import E_GRID_MIN, REPLAY_FIRST_MARGIN  # noqa: E402
from shearfit.config import fit_config_from_mapping, settings_from_items  # noqa: E402
from shearfit.errors import ShearfitKeyError, ShearfitValueError  # noqa: E402
from shearfit.engine.sampling import EPoint, adaptive_samples, estimate, replay_samples  # noqa: E402
from shearfit.workers import process_pool  # noqa: E402

#: the replays' margin (nats below the posterior cut), measure_metacal's default
REPLAY_MARGIN = 10.0


def _chi(e1, e2):
    f = 2.0 / (1.0 + e1 * e1 + e2 * e2)
    return f * e1, f * e2


def synthetic_likelihood(peak, width, kind):
    """A likelihood ``like(e1, e2) -> EPoint`` Gaussian of ``width`` around ``peak`` in e or in chi."""
    p1, p2 = (float(peak[0]), float(peak[1])) if kind == "e" else _chi(float(peak[0]), float(peak[1]))

    def like(e1, e2):
        e1 = np.atleast_1d(np.asarray(e1, float))
        e2 = np.atleast_1d(np.asarray(e2, float))
        x1, x2 = (e1, e2) if kind == "e" else _chi(e1, e2)
        ll = -((x1 - p1) ** 2 + (x2 - p2) ** 2) / (2.0 * width * width)
        z = np.zeros_like(e1)
        return EPoint(logl_disk=ll, logl_bulge=ll.copy(), mean_r=z, mean_b=z, mean_flux=z)
    return like


def responses(job):
    """(R replay, R own, width) of the objects of one job: (seed, n, widths spec, kind, e_int, delta, cfg)."""
    seed, n, widths, kind, e_int, delta, cfg = job
    rng = np.random.default_rng(seed)
    out = []
    step = np.array([delta, 0.0])
    for _ in range(n):
        if widths[0] == "log-uniform":
            w = float(np.exp(rng.uniform(np.log(widths[1]), np.log(widths[2]))))
        else:
            w = float(widths[1])
        phi = rng.uniform(0.0, np.pi)
        peak = e_int * np.array([np.cos(2 * phi), np.sin(2 * phi)]) + w * rng.standard_normal(2)
        if np.hypot(*peak) > 0.9:   # no model reaches |e| = 1: such a peak is not a galaxy's
            continue
        ref = adaptive_samples(synthetic_likelihood(peak, w, kind), cfg)
        rep, own = [], []
        for s in (+1, -1):
            like = synthetic_likelihood(peak + s * step, w, kind)
            rep.append(estimate(replay_samples(like, ref, cfg, REPLAY_MARGIN, REPLAY_FIRST_MARGIN), cfg).e1)
            own.append(estimate(adaptive_samples(like, cfg), cfg).e1)
        out.append(((rep[0] - rep[1]) / (2 * delta), (own[0] - own[1]) / (2 * delta), w))
    return out


def _settings(items):
    """metacal's fit settings (its finest ellipticity step) with the KEY=VALUE items of ``--set``, read as
    ``ring_test.py --set`` reads them (YAML values, :func:`shearfit.config.fit_config_from_mapping`'s checks)."""
    try:
        return fit_config_from_mapping({"e_grid_min": E_GRID_MIN, **settings_from_items(items)})
    except (ShearfitKeyError, ShearfitValueError) as exc:
        raise SystemExit(f"--set: {exc}") from None


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n-objects", type=int, default=3000, help="objects per width (or in all, --log-uniform)")
    ap.add_argument("--widths", default="0.02,0.05,0.1,0.15,0.2,0.3", help="likelihood widths, comma-separated")
    ap.add_argument("--log-uniform", nargs=2, type=float, metavar=("WMIN", "WMAX"),
                    help="each object's width drawn log-uniform over [WMIN, WMAX] instead of --widths")
    ap.add_argument("--likelihood", choices=("e", "chi"), default="e")
    ap.add_argument("--e-int", type=float, default=0.3)
    ap.add_argument("--delta", type=float, default=0.01, help="metacal's shear step")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--processes", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a FitConfig setting")
    args = ap.parse_args(argv)
    cfg = _settings(args.set)
    try:
        widths = [float(w) for w in args.widths.split(",")]
    except ValueError:
        ap.error(f"--widths {args.widths}: give widths as numbers separated by commas")
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from speed import cpu_name   # benchmarks/speed.py, beside this script

    specs = ([("log-uniform", *args.log_uniform)] if args.log_uniform else
             [("fixed", w) for w in widths])
    print(f"CPU: {cpu_name()}; {args.processes} process(es); likelihood Gaussian in "
          f"{args.likelihood}, |e_int| = {args.e_int}, delta = {args.delta}; e_grid_min {cfg.e_grid_min}, n_above "
          f"{cfg.n_above}, above_fraction {cfg.above_fraction}, posterior_cut {cfg.posterior_cut}")
    chunks = max(4 * args.processes, 1)
    with process_pool(args.processes) as pool:
        for k, spec in enumerate(specs):
            t0 = time.time()
            seeds = np.random.SeedSequence([args.seed, k]).spawn(chunks)
            sizes = [args.n_objects // chunks + (i < args.n_objects % chunks) for i in range(chunks)]
            jobs = [(s, n, spec, args.likelihood, args.e_int, args.delta, cfg) for s, n in zip(seeds, sizes)]
            got = np.array([r for part in pool.map(responses, jobs) for r in part]).reshape(-1, 3)
            rr, ro = got[:, 0], got[:, 1]
            d = rr - ro
            n = d.size
            label = (f"widths log-uniform {spec[1]:g}-{spec[2]:g}" if spec[0] == "log-uniform"
                     else f"width {spec[1]:g}")
            print(f"{label}: {n} objects; <R replay> {rr.mean():.4f}, <R own> {ro.mean():.4f} +- "
                  f"{ro.std() / np.sqrt(n):.4f}; replay - own (paired) {d.mean():+.5f} +- {d.std() / np.sqrt(n):.5f}: "
                  f"m of the replays {-d.mean() / rr.mean():+.5f} +- {d.std() / np.sqrt(n) / rr.mean():.5f} "
                  f"({time.time() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main()

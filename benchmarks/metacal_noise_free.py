#!/usr/bin/env python
"""Metacalibration's own accuracy, without noise: the metacal response against GalSim's true shear response.

Each galaxy (the paper's population, or ``--population odd``) is rendered by GalSim without noise on 7
dithered exposures with elliptical Moffat PSFs, unsheared and with true shears of +-h in each component
(the same galaxy, PSFs and dithers). Every stamp goes through metacal's operations (deconvolution, shear,
dilated PSF); the symmetrising noise is scaled down by 1e-9 and the weights scaled back, so that the fits
see the noise level of the galaxy's target SNR on noise-free images (as ``ring_test.py --noise-free``).

One joint fit chooses the samples (the noshear version of the unsheared stamps) and every other image is
fitted with those choices replayed (:func:`shearfit.engine.measure.measure_versions`): the metacal versions give
``R_ii = (e_i[i+] - e_i[i-]) / (2 delta)`` and the noshear images of the truly sheared galaxy give
``A_ii = (e_i[+h] - e_i[-h]) / (2 h)``. At fixed samples both are smooth in the pixels, so per galaxy they
agree as closely as metacal's images reproduce a true shear; ``m = <A> / <R> - 1`` is the multiplicative
bias metacal would leave with no noise, measured to about 1e-5 with tens of galaxies (noise is what makes
the ring tests of ``ring_test.py --metacal`` need a million objects).

    python benchmarks/metacal_noise_free.py --n-galaxies 60
    python benchmarks/metacal_noise_free.py --n-galaxies 60 --population odd
    python benchmarks/metacal_noise_free.py --n-galaxies 120 --population outside --stamp-size 64 --rotate-exposures
    python benchmarks/metacal_noise_free.py --n-galaxies 40 --population outside --hlr-range 0.9 2 --stamp-size 128
    python benchmarks/metacal_noise_free.py --n-galaxies 60 --metacal-psf round
    python benchmarks/metacal_noise_free.py --n-galaxies 60 --variants 2:quintic:cubic,0:quintic:cubic
    python benchmarks/metacal_noise_free.py --n-galaxies 60 --variants 1.333:quintic:quintic:own,1.333:quintic:quintic:galsim
    python benchmarks/metacal_noise_free.py --n-galaxies 60 --psf-oversampling 3 --pad-factor 3

``--variants`` compares image settings, each ``WRAP:STAMP_INTERPOLANT:PSF_INTERPOLANT[:own|galsim]``: the FFT
grid in stamp widths (0: GalSim's own grid), GalSim's k-interpolants of the stamp (and its noise) and of the PSF
(``shearfit.calib.metacal.WRAP_STAMPS``, ``K_INTERPOLANT``, ``PSF_K_INTERPOLANT``), and whether the images come
from shearfit's own k-space operations (``own``, the default where both interpolants are quintic and the grid is
not GalSim's: ``metacal.OWN_KSPACE``) or from GalSim's objects (``galsim``); the default is the shipped one.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import functools  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402

import numpy as np  # noqa: E402

from shearfit.calib import kspace, metacal  # noqa: E402
from shearfit.engine.measure import as_config  # noqa: E402
from shearfit.simulate.metacal_check import fixed_sample_responses, shear_sets  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n-galaxies", type=int, default=60)
    ap.add_argument("--seed", type=int, default=12)
    ap.add_argument("--snr-min", type=float, default=10.0)
    ap.add_argument("--snr-max", type=float, default=40.0)
    ap.add_argument("--mag-min", type=float, default=21.0)
    ap.add_argument("--mag-max", type=float, default=24.7)
    ap.add_argument("--h", type=float, default=0.01, help="the true shear of the +-h renders")
    ap.add_argument("--delta", type=float, default=0.01, help="metacal's shear")
    ap.add_argument("--population", choices=["paper", "odd", "outside"], default="paper",
                    help="outside: galaxies outside the model family (shearfit.simulate.outside: Sersic, bulge + disk "
                         "of their own shapes, disk + knots), with m per family")
    ap.add_argument("--hlr-range", type=float, nargs=2, metavar=("MIN", "MAX"), default=None,
                    help="with --population outside: half-light radii log-uniform from MIN to MAX arcsec instead of "
                         "0.1-2\" (a galaxy that would not fit its stamp is redrawn: 64-pixel stamps hold up to "
                         "about 0.9\")")
    ap.add_argument("--stamp-size", type=int, default=48)
    ap.add_argument("--psf-oversampling", type=int, default=1, metavar="K",
                    help="the PSF images drawn K times finer than the stamps (a PSFEx-like model's)")
    ap.add_argument("--rotate-exposures", action="store_true",
                    help="give each exposure's pixel grid its own rotation (as ring_test.py --rotate-exposures)")
    ap.add_argument("--noisy", action="store_true",
                    help="keep the stamps' noise (the same at 0 and +-h) and metacal's symmetrising noise: the "
                         "per-galaxy scatter of A - R and of A_free - A then shows what limits the noisy ring tests")
    ap.add_argument("--antithetic", action="store_true", help="with --noisy: also each galaxy's antithetic twin")
    ap.add_argument("--metacal-psf", choices=["dilated", "round"], default="dilated",
                    help="metacal's new PSF (shearfit.calib.metacal.metacal_observations' psf)")
    ap.add_argument("--own-fits", action="store_true",
                    help="fit every image on its own (its own modes, position, sizes and samples) instead of replaying "
                         "the unsheared noshear fit's choices: metacal as measure_metacal(replay=False) and the "
                         "pipeline's metacal_replay: false measure it")
    ap.add_argument("--own-position", action="store_true",
                    help="the replays find their own position (measure_metacal's own_position=True)")
    ap.add_argument("--own-samples", action="store_true",
                    help="the replays run the adaptive ellipticity grid on their own likelihoods (measure_metacal's "
                         "own_samples=True)")
    ap.add_argument("--variants", default=None,
                    help="comma-separated WRAP:STAMP_INTERPOLANT:PSF_INTERPOLANT image settings to compare")
    ap.add_argument("--pad-factor", type=int, default=None, metavar="P",
                    help="shearfit's own operations' padded transforms P stamp (and PSF image) widths wide instead "
                         f"of {kspace.PAD_FACTOR} (shearfit.calib.kspace.PAD_FACTOR; fewer: faster images, coarser "
                         "k-space interpolation)")
    args = ap.parse_args(argv)
    if args.pad_factor is not None:
        if args.pad_factor < 2:
            ap.error("--pad-factor must be at least 2")
        kspace.PAD_FACTOR = args.pad_factor
    if args.hlr_range is not None and (args.population != "outside" or not 0 < args.hlr_range[0] < args.hlr_range[1]):
        ap.error("--hlr-range needs --population outside and 0 < MIN < MAX")

    population = profile = None
    if args.population == "odd":
        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        from ring_test import odd_population
        population = odd_population
    elif args.population == "outside":
        from shearfit.simulate.outside import outside_population, outside_profile
        population, profile = outside_population, outside_profile
        if args.hlr_range is not None:
            population = functools.partial(outside_population, hlr_range=tuple(args.hlr_range))
    cfg = as_config(None)
    cfg = replace(cfg, e_grid_min=min(cfg.e_grid_min, metacal.E_GRID_MIN))
    kw = dict(n_exposures=7, snr_range=(args.snr_min, args.snr_max),
              mag_range=(args.mag_min, args.mag_max), stamp_size=args.stamp_size, add_noise=args.noisy,
              population=population, profile=profile, rotate_exposures=args.rotate_exposures,
              psf_oversampling=args.psf_oversampling)
    h = args.h
    t0 = time.perf_counter()
    twins = (False, True) if (args.noisy and args.antithetic) else (False,)
    shows_free = args.noisy and not args.own_fits
    sets = {tw: shear_sets(args.n_galaxies, h, args.seed, noise_sign=-1 if tw else 1, **kw) for tw in twins}
    print(f"{args.n_galaxies} {'noisy' if args.noisy else 'noise-free'} galaxies"
          f"{' and their antithetic twins' if len(twins) > 1 else ''} ({args.population} population, SNR "
          f"{args.snr_min:g}-{args.snr_max:g}{'' if args.noisy else ' weights'}, mag {args.mag_min:g}-{args.mag_max:g}), "
          f"7 exposures, {args.stamp_size}-pixel stamps{', rotated pixel grids' if args.rotate_exposures else ''}"
          f"{f', PSFs oversampled {args.psf_oversampling} times' if args.psf_oversampling > 1 else ''}"
          f"{f', padded transforms {kspace.PAD_FACTOR} widths wide' if args.pad_factor is not None else ''}; "
          f"true shears +-{h:g}, metacal delta {args.delta:g}, new PSF {args.metacal_psf}; rendered in "
          f"{time.perf_counter() - t0:.0f} s")
    shipped = (f"{metacal.WRAP_STAMPS:g}:{metacal.K_INTERPOLANT}:{metacal.PSF_K_INTERPOLANT}:"
               f"{'own' if metacal.OWN_KSPACE else 'galsim'}")
    for variant in (args.variants.split(",") if args.variants else [shipped]):
        parts = variant.split(":")
        if len(parts) not in (3, 4) or (len(parts) == 4 and parts[3] not in ("own", "galsim")):
            ap.error(f"--variants: {variant!r} is not WRAP:STAMP_INTERPOLANT:PSF_INTERPOLANT[:own|galsim]")
        wrap, kint, pkint = parts[:3]
        saved = metacal.WRAP_STAMPS, metacal.K_INTERPOLANT, metacal.PSF_K_INTERPOLANT, metacal.OWN_KSPACE
        metacal.WRAP_STAMPS, metacal.K_INTERPOLANT, metacal.PSF_K_INTERPOLANT = float(wrap), kint, pkint
        metacal.OWN_KSPACE = len(parts) == 3 or parts[3] == "own"
        try:
            t0 = time.perf_counter()
            rows = [[fixed_sample_responses(sets[twin], i, h, args.delta, cfg, args.seed, args.noisy, twin,
                                            free=args.noisy and not args.own_fits, psf=args.metacal_psf,
                                            own=args.own_fits, own_position=args.own_position,
                                            own_samples=args.own_samples) for twin in twins]
                    for i in range(args.n_galaxies)]
        finally:
            metacal.WRAP_STAMPS, metacal.K_INTERPOLANT, metacal.PSF_K_INTERPOLANT, metacal.OWN_KSPACE = saved
        # a galaxy (with its twin) counts where every fit of it measured a galaxy; twins averaged
        # (A_free is measured only with --noisy: A stands in for it, unprinted)
        measured = [all(c == 0 for r in rs for c in r[3]) for rs in rows]
        ok = [np.mean([(R, A, A if F is None else F) for R, A, F, _ in rs], axis=0)
              for rs, good in zip(rows, measured) if good]
        R, A, F = (np.array([o[k] for o in ok]) for k in range(3))
        label = variant + (" (shipped)" if variant == shipped else "") + (", every image fitted on its own"
                                                                           if args.own_fits else "") + (
            ", the replays at their own positions" if args.own_position and not args.own_fits else "") + (
            ", the replays on their own ellipticity grids" if args.own_samples and not args.own_fits else "")
        print(f"\n{label}: {len(ok)} of {len(rows)} galaxies measured ({time.perf_counter() - t0:.0f} s)")
        print(f"  <R> = ({R[:, 0].mean():.4f}, {R[:, 1].mean():.4f}), <A> = ({A[:, 0].mean():.4f}, {A[:, 1].mean():.4f})"
              + (f", <A_free> = ({F[:, 0].mean():.4f}, {F[:, 1].mean():.4f})" if shows_free else ""))
        for name, X in (("A", A),) + ((("A_free", F),) if shows_free else ()):
            _report(name, X, R)
        if args.population == "outside":
            from shearfit.simulate.outside import FAMILIES
            family = np.array([int(sets[False][(0.0, 0.0)][i][1]["fields"]["family"])
                               for i, good in enumerate(measured) if good])
            for f, fam in enumerate(FAMILIES):
                sel = family == f
                if sel.sum() > 1:
                    _report(f"A, {fam} ({sel.sum()})", A[sel], R[sel])
        if shows_free:
            d = F - A
            print(f"  A_free - A (the samples' own choices): rms ({np.sqrt(np.mean(d[:, 0] ** 2)):.1e}, "
                  f"{np.sqrt(np.mean(d[:, 1] ** 2)):.1e}), mean ({d[:, 0].mean():+.1e}, {d[:, 1].mean():+.1e})")


def _report(name, X, R):
    """m = <X> / <R> - 1 per component with its error over the galaxies, and the spread of X - R."""
    m = X.mean(axis=0) / R.mean(axis=0) - 1
    err = (X - (1 + m) * R).std(axis=0, ddof=1) / np.sqrt(len(X)) / R.mean(axis=0)
    q = np.percentile(np.abs(X - R), [50, 90, 99], axis=0)
    rms = np.sqrt(np.mean((X - R) ** 2, axis=0))
    print(f"  {name}: m1 = {m[0]:+.1e} +/- {err[0]:.1e}    m2 = {m[1]:+.1e} +/- {err[1]:.1e}; per galaxy "
          f"rms of X - R ({rms[0]:.1e}, {rms[1]:.1e}); |X - R| 50/90/99 %: component 1 "
          f"{q[0, 0]:.1e} / {q[1, 0]:.1e} / {q[2, 0]:.1e}, component 2 {q[0, 1]:.1e} / {q[1, 1]:.1e} / {q[2, 1]:.1e}")


if __name__ == "__main__":
    main()

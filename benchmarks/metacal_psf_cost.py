#!/usr/bin/env python
"""Metacal's cost of an exposure's images when every object brings a PSF image of its own.

``shearfit measure`` given one PSF image per CCD (the field benchmark's case) lets metacal make what it derives
from an oversampled PSF image once per CCD: the image's padded transform, its band, its dilated image. A PSFEx or
Piff model evaluated at each object's position gives every object its own image, and all of that is made again
for every exposure of every object. This script times ``metacal_observations`` (the five versions' images of one
exposure) on 48-pixel stamps with a 3-times oversampled elliptical Moffat PSF, each exposure its own rotation of the
pixel grid, in turn with one PSF image per exposure that all its objects share and with an image of its own for
every object (the same PSF, its FWHM moved by up to 1e-3" at random), and prints the CPU time of each per exposure and the
difference, with the CPU and the compiled loops' instruction set.

    python benchmarks/metacal_psf_cost.py                  # 7 exposures, 40 objects, 3 alternated passes
    python benchmarks/metacal_psf_cost.py --oversampling 1 # native PSF images
    python benchmarks/metacal_psf_cost.py --fits 40        # also whole measurements: metacal against the plain fit
    python benchmarks/metacal_psf_cost.py --fwhm 0.3       # undersampled PSFs (1.6 pixels), as from space
    python benchmarks/metacal_psf_cost.py --psf-size 25    # PSF images 25 stamp pixels wide (a PSFEx model's 25
                                                           # samples), 75 samples at 3 times, not the stamp's 48

``--fits N`` then measures N new galaxies of each case (7 exposures, SNR 20) with ``measure_object`` and with
``measure_metacal``, one after the other for each galaxy (so that the machine's drift meets both alike), and prints
the ratio of their summed CPU times with its bootstrap error: metacal's cost per galaxy in units of the plain fit's,
with one PSF image per exposure and with an image of its own per galaxy.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

import shearfit  # noqa: E402
from shearfit.calib.metacal import metacal_observations  # noqa: E402
from shearfit.engine.kernel import kernel_info  # noqa: E402
from shearfit.simulate import draw_psf_image, draw_stamp, galaxy_profile, moffat_psf, noise_for_snr  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from speed import cpu_name  # noqa: E402  (benchmarks/speed.py, beside this script)

PIX = 0.187   # arcsec (CFHT MegaCam)
STAMP = 48


def _exposures(n_exp, rng, fwhm=0.6):
    """Per exposure its Jacobian (its own rotation of the pixel grid) and its Moffat PSF (FWHM ``fwhm`` arcsec, 0.03"
    more for each next exposure)."""
    out = []
    for i in range(n_exp):
        a = rng.uniform(-np.pi, np.pi)
        J = PIX * np.array([[-np.cos(a), np.sin(a)], [np.sin(a), np.cos(a)]])
        out.append((J, (fwhm + 0.03 * i, 3.0, 0.04 * (-1) ** i, 0.02)))
    return out


def _objects(exposures, n_obj, k, own, rng, psf_size=STAMP):
    """Observations of n_obj galaxies on every exposure; with ``own`` each object its own PSF image (``psf_size`` stamp
    pixels wide, ``psf_size`` k samples)."""
    shared = [draw_psf_image(moffat_psf(*p), J, size=psf_size * k, oversampling=k) for J, p in exposures]
    objs = []
    for m in range(n_obj):
        gal = galaxy_profile(rng.uniform(0.2, 0.6), 0.1, *rng.uniform(-0.3, 0.3, 2), flux=1000.0)
        obs = []
        for (J, p), psf in zip(exposures, shared):
            if own:
                fwhm, beta, e1, e2 = p
                psf = draw_psf_image(moffat_psf(fwhm + rng.uniform(1e-5, 1e-3), beta, e1, e2), J,
                                     size=psf_size * k, oversampling=k)
            im = draw_stamp(gal, moffat_psf(*p), J, (0.0, 0.0), stamp_size=STAMP)
            sig = noise_for_snr([im], 20.0)
            obs.append(shearfit.Observation(image=im + rng.normal(0.0, sig, im.shape),
                                            weight=np.full(im.shape, 1 / sig ** 2), psf=psf, psf_oversampling=k,
                                            jacobian=J))
        objs.append(obs)
    return objs


def _cpu_per_exposure(objs, rng):
    n = sum(len(o) for o in objs)
    t0 = time.process_time()
    for obs in objs:
        for o in obs:
            metacal_observations(o, 0.01, rng, fit_moffat=False)
    return (time.process_time() - t0) / n


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--exposures", type=int, default=7)
    ap.add_argument("--objects", type=int, default=40)
    ap.add_argument("--passes", type=int, default=3)
    ap.add_argument("--oversampling", type=int, default=3, help="the PSF images' oversampling k")
    ap.add_argument("--psf-size", type=int, default=STAMP,
                    help="the PSF images' width in stamp pixels (default the stamp's, 48; a PSFEx model: its samples)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--fwhm", type=float, default=0.6,
                    help="the first exposure's PSF FWHM in arcsec (0.187\" pixels; 0.3: undersampled, as from space)")
    ap.add_argument("--fits", type=int, default=0, metavar="N",
                    help="also measure N galaxies of each case whole, plain and metacal (the ratio per galaxy)")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    info = kernel_info()
    print(f"CPU: {cpu_name()}; inner loops: {info['path']} ({info['isa']})")
    exposures = _exposures(args.exposures, rng, args.fwhm)
    k = args.oversampling
    cases = {"one PSF image per exposure": False, "a PSF image of its own per object": True}
    times = {name: [] for name in cases}
    for p in range(args.passes):
        for name, own in cases.items():   # (new objects every pass: no image is remembered from the last)
            objs = _objects(exposures, args.objects, k, own, np.random.default_rng(args.seed + 100 * p + own),
                            args.psf_size)
            if p == 0 and not own:
                _cpu_per_exposure(objs[:2], rng)   # (imports and one-off tables)
            times[name].append(_cpu_per_exposure(objs, rng))
    print(f"metacal_observations, {args.objects} objects x {args.exposures} exposures, {STAMP}-pixel stamps, PSF images "
          f"{args.psf_size} pixels wide oversampled {k} times ({args.psf_size * k} samples), FWHM {args.fwhm:.2f}\"+, "
          f"{args.passes} passes (CPU ms an exposure, median; the passes):")
    med = {}
    for name, t in times.items():
        med[name] = float(np.median(t))
        print(f"  {name:36s} {1e3 * med[name]:6.2f}   ({', '.join(f'{1e3 * x:.2f}' for x in t)})")
    d = med["a PSF image of its own per object"] - med["one PSF image per exposure"]
    print(f"  a PSF image of its own costs {1e3 * d:.2f} ms an exposure more: {1e3 * d * args.exposures:.1f} ms an "
          f"object of {args.exposures} exposures")
    if args.fits:
        _fits(exposures, args, cases)


def _fits(exposures, args, cases):
    """metacal's cost per galaxy against the plain fit's, each galaxy measured both ways in turn."""
    from shearfit.calib.metacal import measure_metacal
    from shearfit.engine.measure import measure_object

    print(f"measure_metacal against measure_object, {args.fits} galaxies x {args.exposures} exposures (CPU ms a "
          "galaxy; ratio of the sums, +- bootstrap over the galaxies):")
    boot = np.random.default_rng(0)
    for name, own in cases.items():
        objs = _objects(exposures, args.fits + 2, args.oversampling, own, np.random.default_rng(args.seed + 7 + own),
                        args.psf_size)
        times = []
        for i, obs in enumerate(objs):
            t0 = time.process_time()
            measure_object(obs, 22.0)
            t1 = time.process_time()
            measure_metacal(obs, 22.0, rng=np.random.default_rng(i))
            t2 = time.process_time()
            if i >= 2:   # (the first two: one-off tables)
                times.append((t1 - t0, t2 - t1))
        p, m = np.array(times).T
        err = np.std([m[j].sum() / p[j].sum() for j in boot.integers(0, p.size, (400, p.size))])
        print(f"  {name:36s} plain {1e3 * p.mean():5.1f}, metacal {1e3 * m.mean():5.1f}: **x{m.sum() / p.sum():.2f}** "
              f"+- {err:.2f}")


if __name__ == "__main__":
    main()

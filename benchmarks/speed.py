#!/usr/bin/env python
"""Throughput of the single-object engine: galaxies per second per core, and where the time goes.

Simulates CFHTLenS-like galaxies with GalSim (the paper's population,
magnitudes 21-24.7, SNR 10-40, 48-pixel stamps) and times
``shearfit.measure_object`` on one core (BLAS limited to one thread). The
default is the realistic case of a camera: 7 exposures, each with its own
Jacobian (its own rotation of the pixel grid, and 1 % rms distortion) and its
own elliptical Moffat PSF image, the App. A Moffat fitted to each, and new
galaxies in every timed pass. GalSim's HSM (REGAUSS) measures the same stamps
in the same process, as a peer, each galaxy right after shearfit (the ratio of
their times is the passes' median). Prints the CPU, the instruction-set level of
the compiled loops (``SHEARFIT_ISA=avx2``, ``baseline`` or ``numpy`` forces
one), a profile grouped by stage and the process's peak memory.

    python benchmarks/speed.py                     # the realistic case
    SHEARFIT_ISA=baseline python benchmarks/speed.py   # the portable loops on the same CPU
    python benchmarks/speed.py --one-jacobian      # exposures sharing one Jacobian (modes merge exactly)
    python benchmarks/speed.py --moffat-per-exposure   # one App. A Moffat per exposure, as the pipeline fits one per CCD
    python benchmarks/speed.py --constant-psf      # one PSF image for all (a Moffat fitted once, remembered)
    python benchmarks/speed.py --same-galaxies     # every pass on the same galaxies (warm caches)
    python benchmarks/speed.py --scaling           # growth with exposures and stamp size
    python benchmarks/speed.py --workers 2         # 2 worker processes against one
    python benchmarks/speed.py --isa-ab baseline   # the loops in use against the portable ones, interleaved
    python benchmarks/speed.py --moffat-ab         # the compiled App. A Moffat fits against the numpy ones
    python benchmarks/speed.py --setting-ab pair_chi2_tolerance=0   # a setting's cost, interleaved
    python benchmarks/speed.py --census            # where the ellipticity samples lie against the posterior cut
    python benchmarks/speed.py --check             # how far the speed settings (and the mode cut) move the estimates
    python benchmarks/speed.py --check --check-each   # and each setting's own effect
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import cProfile  # noqa: E402
import pstats  # noqa: E402
import resource  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

import shearfit  # noqa: E402
from shearfit.engine.model import psf_moffat  # noqa: E402
from shearfit.observation import Observation  # noqa: E402
from shearfit.simulate.stamps import ring_set  # noqa: E402

STAGES = {
    "model sums (compiled kernel or numpy)": ("likelihood.py", "model_sums"),
    "mode binning per ellipticity (compiled)": ("likelihood.py", "mode_bins"),
    "flux/position marginalisation": ("likelihood.py", "flux_position_marginal"),
    "size marginalisation (splines)": ("sampling.py", "_size_marginal"),
    "exposure preparation (FFTs, PSF, alias)": ("model.py", "prepare_exposure"),
    "peak search": ("likelihood.py", "find_position"),
    "coarse peak": ("likelihood.py", "coarse_peak"),
    "join exposures + mode cut": ("likelihood.py", "join_exposures"),
}


SNR_RANGE = (10, 40)


def simulate(n, n_exp, stamp, seed, rotate=False, jitter=0.0, constant_psf=False):
    rng = np.random.default_rng(seed)
    # a constant PSF: one round Moffat (FWHM 0.65", beta 3) for every exposure of every galaxy
    psf = dict(psf_fwhm_range=(0.65, 0.65), psf_beta_range=(3.0, 3.0), psf_e_max=0.0) if constant_psf else {}
    return ring_set(n, (0.0, 0.0), rng, n_rotations=1, n_exposures=n_exp, snr_range=SNR_RANGE,
                    mag_range=(21.0, 24.7), stamp_size=stamp, rotate_exposures=rotate, jacobian_jitter=jitter, **psf)


def cpu_name():
    """The CPU's model name with its family and model numbers (Linux: /proc/cpuinfo; a virtual machine may name
    only the vendor's line, "AMD EPYC", and the numbers tell its generation: AMD family 25 is Zen 3 and 4, 26 Zen
    5), else what platform says."""
    import platform

    fields = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if not line.strip():
                    break   # the first processor's entry
                key, _, value = line.partition(":")
                fields[key.strip().lower()] = value.strip()
    except OSError:
        pass
    name = fields.get("model name")
    if not name:
        return platform.processor() or platform.machine()
    if "cpu family" in fields and "model" in fields:
        name += f" (family {fields['cpu family']}, model {fields['model']})"
    return name


def hsm_galaxy(obs):
    """GalSim's HSM REGAUSS on one galaxy's stamps (every exposure): the number of its failures."""
    import galsim

    fails = 0
    for o in obs:
        scale = float(np.sqrt(abs(np.linalg.det(o.jacobian))))
        res = galsim.hsm.EstimateShear(galsim.Image(np.asarray(o.image, np.float64), scale=scale),
                                       galsim.Image(np.asarray(o.psf, np.float64), scale=scale),
                                       weight=galsim.Image((np.asarray(o.weight) > 0).astype(np.int32)),
                                       shear_est="REGAUSS", strict=False)
        fails += bool(res.error_message)
    return fails


def hsm_time(objs):
    """Seconds per galaxy of GalSim's HSM REGAUSS on the same stamps (every exposure), and its failures."""
    t0 = time.perf_counter()
    fails = sum(hsm_galaxy(obs) for obs, _ in objs)
    return (time.perf_counter() - t0) / len(objs), fails


def timed_with_peer(objs, cfg):
    """Each galaxy measured by shearfit and then by HSM (hsm_galaxy), alternately, so that both see the same
    moment of a machine whose speed drifts by 10-30 % from minute to minute: (shearfit's seconds, HSM's seconds,
    HSM's failures), summed over the galaxies."""
    ts = th = 0.0
    fails = 0
    for o, t in objs:
        t0 = time.perf_counter()
        shearfit.measure_object(o, mag=t["mag"], config=cfg)
        t1 = time.perf_counter()
        fails += hsm_galaxy(o)
        ts += t1 - t0
        th += time.perf_counter() - t1
    return ts, th, fails


def use_kernel(mod):
    """Point the engine's modules at the compiled module ``mod`` (their KERNEL) and give it scipy's special
    functions, as shearfit.engine.kernel does at import for the level it loads."""
    from shearfit.engine import likelihood, model, moffat, sampling

    likelihood.KERNEL = sampling.KERNEL = model.KERNEL = moffat.KERNEL = mod
    likelihood._load_special()
    moffat._load_bessel()


def alternate(galaxies, variants, clock=time.perf_counter):
    """Each galaxy fitted under every variant in turn, the order alternating galaxy by galaxy (so that all see
    the same machine: a shared machine's speed drifts by 10-30 % from minute to minute), the App. A Moffat
    caches emptied before each fit so that no variant finds another's work. ``variants``: name -> a function
    that sets the variant up and returns the config to fit with. Returns ({name: seconds}, the largest
    |delta e| between the first two variants, the number of galaxies)."""
    from shearfit.engine import model

    names = list(variants)
    t = dict.fromkeys(names, 0.0)
    de = 0.0
    n = 0
    for o, tr in galaxies:
        e = {}
        for name in (names if n % 2 == 0 else names[::-1]):
            cfg = variants[name]()
            model._OWN_MOFFAT.clear()          # no fit or table remembered from the other variant
            model._moffat_aliases.cache_clear()
            t0 = clock()
            r = shearfit.measure_object(o, mag=tr["mag"], config=cfg)
            t[name] += clock() - t0
            e[name] = (r.e1, r.e2)
        de = max(de, float(np.nanmax(np.abs(np.subtract(e[names[0]], e[names[1]])))))
        n += 1
    return t, de, n


def isa_ab_report(sets, cfg, level):
    """The loops in use against those of another instruction-set level, galaxy by galaxy in one process
    (alternating, so that both see the same machine: a shared machine's speed drifts by 10-30 % from minute
    to minute, more than the levels differ)."""
    import importlib

    from shearfit.engine import kernel

    module = next(m for name, m, keys in kernel.LEVELS if level in keys or level == name)
    other = importlib.import_module(f"shearfit.engine.{module}")
    mine = kernel.KERNEL
    if mine is None or other is mine:
        print(f"\n--isa-ab {level}: nothing to compare (the loops in use are {kernel.kernel_info()['isa']})")
        return
    t = {mine: 0.0, other: 0.0}
    n = 0
    try:
        for s in sets[1:] or sets:
            for o, tr in s:
                for mod in ((mine, other) if n % 2 == 0 else (other, mine)):
                    use_kernel(mod)
                    t0 = time.perf_counter()
                    shearfit.measure_object(o, mag=tr["mag"], config=cfg)
                    t[mod] += time.perf_counter() - t0
                n += 1
    finally:
        use_kernel(mine)
    print(f"\n{mine.kernel_isa()} against {other.kernel_isa()}, {n} galaxies timed alternately in one process: "
          f"{1e3 * t[mine] / n:.1f} against {1e3 * t[other] / n:.1f} ms per galaxy, x{t[other] / t[mine]:.2f}")


def moffat_ab_report(sets, cfg):
    """The App. A Moffat's fits and tables (one per exposure of every object here) made by the compiled kernel
    against the numpy lines they replaced (moffat_lm, moffat_table), galaxy by galaxy in one process, and
    the largest difference in e between the two."""
    from shearfit.engine import moffat

    if not moffat.USE_KERNEL_BESSEL:
        print("\n--moffat-ab: the compiled Moffat fit is not in use (no kernel, or scipy's kv not found)")
        return

    def flag(value):
        def setup():
            moffat.USE_KERNEL_BESSEL = value
            return cfg
        return setup

    try:
        t, de, n = alternate([g for s in sets[1:] or sets for g in s], {True: flag(True), False: flag(False)})
    finally:
        moffat.USE_KERNEL_BESSEL = True
    print(f"\nApp. A Moffat fits and tables compiled against numpy, {n} galaxies timed alternately in one process: "
          f"{1e3 * t[True] / n:.1f} against {1e3 * t[False] / n:.1f} ms per galaxy, x{t[False] / t[True]:.3f}; "
          f"largest |delta e| {de:.1e}")


def setting_ab_report(sets, cfg, change):
    """The settings in use against the same with ``change`` (a dict of settings), galaxy by galaxy in one process
    (:func:`alternate`); the largest difference in e."""
    from dataclasses import replace

    other = replace(cfg, **change)
    t, de, n = alternate([g for s in sets[1:] or sets for g in s], {0: lambda: cfg, 1: lambda: other})
    what = ", ".join(f"{k}={v}" for k, v in change.items())
    print(f"\nthe settings in use against {what}, {n} galaxies timed alternately in one process: "
          f"{1e3 * t[0] / n:.2f} against {1e3 * t[1] / n:.2f} ms per galaxy, x{t[1] / t[0]:.3f}; largest |delta e| "
          f"{de:.1e}")


def workers_report(objs, cfg, n_workers, rounds=3):
    """Galaxies per second with ``n_workers`` worker processes against one, on the same galaxies: ``rounds`` times,
    one process then the pool, so that a drift of the machine's speed shows in the spread, not in the median."""
    ratios = []
    for k in range(max(rounds, 1)):
        t0 = time.perf_counter()
        shearfit.measure_objects([o for o, _ in objs], [t["mag"] for _, t in objs], config=cfg, processes=1)
        one = time.perf_counter() - t0
        t0 = time.perf_counter()
        shearfit.measure_objects([o for o, _ in objs], [t["mag"] for _, t in objs], config=cfg, processes=n_workers)
        many = time.perf_counter() - t0
        ratios.append(one / many)
        print(f"\n{n_workers} worker processes against one, {len(objs)} galaxies (pool start-up included), round "
              f"{k + 1}: {len(objs) / one:.2f} -> {len(objs) / many:.2f} galaxies / s, x{one / many:.2f}")
    print(f"  median of {len(ratios)} rounds: x{float(np.median(ratios)):.2f} "
          f"({', '.join(f'{r:.2f}' for r in ratios)})")


def one_moffat_per_exposure(objs):
    """The same objects with each exposure's Moffat fitted once, to its first object's PSF."""
    moffats = [psf_moffat(o.psf) for o in objs[0][0]]
    return [([Observation(o.image, o.psf, o.jacobian, weight=o.weight, psf_oversampling=o.psf_oversampling,
                          offset=o.offset, flux_scale=o.flux_scale, psf_moffat=m) for o, m in zip(obs, moffats)], t)
            for obs, t in objs]


def timed(objs, cfg):
    t0 = time.perf_counter()
    res = [shearfit.measure_object(o, mag=t["mag"], config=cfg) for o, t in objs]
    dt = time.perf_counter() - t0
    return dt, res


def stage_report(stats):
    st = stats.stats
    total = sum(v[2] for v in st.values())   # total internal time
    print(f"\n  where the time goes (cumulative per stage, % of {total:.2f} s profiled):")
    for name, (fname, func) in STAGES.items():
        cum = sum(v[3] for k, v in st.items() if k[0].endswith(fname) and k[2] == func)
        if cum > 0:
            print(f"    {name:42s} {cum:7.3f} s  {100 * cum / total:5.1f} %")


def metacal_report(objs, cfg, passes, psf="dilated", own_position=False, own_samples=False):
    """Metacal (the images of five versions, five joint fits) against the plain engine, same objects.

    The plain fit, the metacal images alone (shearfit's own k-space operations, and GalSim's objects as
    before them) and the whole metacal measurement of each galaxy are timed one after the other, galaxy by
    galaxy, so that they see the same machine (whose speed drifts by 10-30 %% from minute to minute here);
    the ratio is taken per pass and its median reported.
    """
    from shearfit.calib import metacal
    from shearfit.engine import measure as engine_measure
    from shearfit.engine.kernel import KERNEL

    # inside measure_metacal: the noshear fit, the four sheared versions' replays, and the replays' mode binning
    split = {"noshear": 0.0, "replays": 0.0, "binning": 0.0, "on": False, "replay": False}
    plain_measure = engine_measure._measure
    plain_replays = engine_measure._replay_all
    plain_bins = getattr(KERNEL, "make_bins", None)

    def timed_as(fn, replay):
        def run(*a, **k):
            if not split["on"] or split["replay"]:   # (a replay's own fallback, already counted)
                return fn(*a, **k)
            split["replay"] = replay
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                split["replays" if replay else "noshear"] += time.perf_counter() - t0
                split["replay"] = False
        return run

    def binned(*a):
        t0 = time.perf_counter()
        try:
            return plain_bins(*a)
        finally:
            if split["on"] and split["replay"]:
                split["binning"] += time.perf_counter() - t0

    rng = np.random.default_rng(0)
    rows = []
    engine_measure._measure = timed_as(plain_measure, False)
    engine_measure._replay_all = timed_as(plain_replays, True)
    if plain_bins is not None:
        KERNEL.make_bins = binned
    try:
        rows = _metacal_passes(objs, cfg, passes, metacal, rng, split, psf, own_position, own_samples)
    finally:
        engine_measure._measure = plain_measure
        engine_measure._replay_all = plain_replays
        if plain_bins is not None:
            KERNEL.make_bins = plain_bins
    rows = np.array(rows) / len(objs)
    ratio = rows[:, 3] / rows[:, 0]
    k = int(np.argsort(ratio)[len(ratio) // 2])
    tp, ti, tg, tm = rows[k, :4]
    where = "their own" if own_position else "the noshear fit's"
    grid = "their own" if own_samples else "the noshear fit's"
    print(f"\nmetacal ({psf} new PSF; the sheared versions at {where} position, on {grid} ellipticity grid), "
          f"{len(objs)} galaxies, plain and "
          f"metacal fits timed galaxy by galaxy, {len(rows)} passes:")
    print(f"  {1 / tm:.2f} galaxies / s / core ({1e3 * tm:.1f} ms per galaxy) against {1 / tp:.2f} plain "
          f"({1e3 * tp:.1f} ms): {tm / tp:.2f} x the plain engine (median pass; passes "
          f"{ratio.min():.2f}-{ratio.max():.2f} x)")
    print(f"  of which the images of the five versions and their symmetrising noise {1e3 * ti:.1f} ms "
          f"({ti / tp:.2f} x a plain fit), the five fits and the new PSFs' Moffats {1e3 * (tm - ti):.1f} ms "
          f"({(tm - ti) / tp:.2f} x)")
    ns, rp, bn = rows[k, 4:7]
    print(f"  the fits: noshear {1e3 * ns:.1f} ms ({ns / tp:.2f} x), the four replays {1e3 * rp:.1f} ms ({rp / tp:.2f} x; "
          f"their mode binning {1e3 * bn:.1f} ms)")
    n_plain, n_noshear, n_replays = rows[:, 7:10].mean(axis=0)
    print(f"  ellipticity samples a galaxy: the plain fit {n_plain:.0f}, the noshear fit {n_noshear:.0f}, the four "
          f"replays {n_replays:.0f} together ({n_replays / 4:.0f} each: every sample above the noshear fit's "
          f"posterior cut, and those its change could lift there)")
    print(f"  the same images by GalSim's objects (metacal.OWN_KSPACE = False): {1e3 * tg:.1f} ms "
          f"({tg / tp:.2f} x a plain fit, {tg / ti:.2f} x shearfit's own)")


def _metacal_passes(objs, cfg, passes, metacal, rng, split, psf="dilated", own_position=False, own_samples=False):
    """metacal_report's timed passes: per pass (plain, images, GalSim's images, metacal, noshear fit, replays,
    replays' binning) summed over the galaxies."""
    rows = []
    for _ in range(max(passes, 1)):
        split.update(noshear=0.0, replays=0.0, binning=0.0)
        tp = ti = tg = tm = 0.0
        counts = np.zeros(3)
        for o, t in objs:
            t0 = time.perf_counter()
            plain = shearfit.measure_object(o, mag=t["mag"], config=cfg)
            t1 = time.perf_counter()
            # the images as measure_metacal makes them (the new PSFs' App. A Moffats are fitted there, as one
            # batch per object: counted with the fits)
            for ob in o:
                metacal.metacal_observations(ob, 0.01, rng, fit_moffat=False, psf=psf)
            t2 = time.perf_counter()
            metacal.OWN_KSPACE = False
            try:
                for ob in o:
                    metacal.metacal_observations(ob, 0.01, rng, fit_moffat=False, psf=psf)
            finally:
                metacal.OWN_KSPACE = True
            t3 = time.perf_counter()
            split["on"] = True
            try:
                mc = metacal.measure_metacal(o, t["mag"], cfg, rng=rng, psf=psf, own_position=own_position,
                                             own_samples=own_samples)
            finally:
                split["on"] = False
            t4 = time.perf_counter()
            tp, ti, tg, tm = tp + t1 - t0, ti + t2 - t1, tg + t3 - t2, tm + t4 - t3
            # the ellipticity samples each fit evaluated: the plain one's, the noshear one's, the replays' together
            counts += (plain.n_samples, mc.noshear.n_samples,
                       sum(mc.results[v].n_samples for v in metacal.SHEARED))
        rows.append((tp, ti, tg, tm, split["noshear"], split["replays"], split["binning"]) + tuple(counts))
    return rows


def metacal_image_profile(objs):
    """Where the metacal images' time goes, per galaxy: shearfit's own k-space operations (the padded
    transforms of the stamp, its noise and the PSF; the PSF's band; the new PSF's transform; the versions'
    bands, interpolated at their sheared wavevectors; the inverse transforms onto the stamps) and the rest of
    the per-exposure work."""
    from shearfit.calib import kspace, metacal

    acc = {}

    def timed(name, fn):
        def wrap(*a, **k):
            t0 = time.perf_counter()
            out = fn(*a, **k)
            acc[name] = acc.get(name, 0.0) + time.perf_counter() - t0
            return out
        return wrap

    class Kernel:   # the compiled module, its versions' bands timed
        def __init__(self, real):
            self.real = real
            self.quintic_band = timed("the versions' bands (compiled)", real.quintic_band)

        def __getattr__(self, name):
            return getattr(self.real, name)

    saved = (kspace.padded_transforms, kspace.kvalues, kspace.band_edge, metacal.band_images, kspace.KERNEL)
    kspace.padded_transforms = timed("padded transforms (rfft, 4 x padding)", saved[0])
    kspace.kvalues = timed("the new PSF's quintic interpolation", saved[1])
    kspace.band_edge = timed("the PSF's band", saved[2])
    metacal.band_images = timed("inverse transforms onto the stamps", saved[3])
    if saved[4] is not None:
        kspace.KERNEL = Kernel(saved[4])
    rng = np.random.default_rng(1)
    try:
        t0 = time.perf_counter()
        for o, _ in objs:
            for ob in o:
                metacal.metacal_observations(ob, 0.01, rng, fit_moffat=False)
        total = time.perf_counter() - t0
    finally:
        kspace.padded_transforms, kspace.kvalues, kspace.band_edge, metacal.band_images, kspace.KERNEL = saved
    n = len(objs)
    print(f"\n  metacal images: {1e3 * total / n:.1f} ms per galaxy, of which:")
    for name, dt in acc.items():
        print(f"    {name:40s} {1e3 * dt / n:6.1f} ms ({100 * dt / total:4.1f} %)")
    rest = total - sum(acc.values())
    print(f"    {'the rest (masks, noise, PSF image, Python)':40s} {1e3 * rest / n:6.1f} ms ({100 * rest / total:4.1f} %)")


def metacal_kernel_split(objs, cfg, psf="dilated"):
    """Where a galaxy's metacal time goes, in compiled loops or not: one pass of the plain fits, then one of the
    metacal measurements, every call of the compiled loops and of scipy's FFTs clocked (no profiler) by stage: the
    plain fit; metacal's images, noshear fit, four sheared replays and the rest of ``measure_metacal``. Prints per
    stage the milliseconds a galaxy in the compiled loops, the FFTs and the rest (Python and numpy), and the ratio to
    the plain fit that metacal would have without the rest of its own stages (the images and the replays; the
    noshear fit is a fit as the plain one is): how much of metacal's cost over one fit is the interpreter's and the
    arrays' overhead rather than arithmetic."""
    from scipy import fft as sfft

    from shearfit.calib import kspace, metacal
    from shearfit.engine import likelihood, model, moffat, priors, profiles, sampling
    from shearfit.engine import measure as engine_measure

    mod = likelihood.KERNEL
    if mod is None:
        print("\n  metacal split: the numpy loops run (no compiled module); nothing to time")
        return
    proxy = _TimedKernel(mod)
    holders = [m for m in (likelihood, sampling, model, moffat, priors, profiles, engine_measure, kspace)
               if getattr(m, "KERNEL", None) is mod]
    fft_names = [n for n in ("fft", "ifft", "rfft", "irfft", "rfft2", "irfft2") if hasattr(sfft, n)]
    saved_fft = {n: getattr(sfft, n) for n in fft_names}
    fft_seconds, totals = {}, {}

    def clocked_fft(fn):
        def run(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                key = proxy.stage[0]
                fft_seconds[key] = fft_seconds.get(key, 0.0) + time.perf_counter() - t0
        return run

    # (a stage inside metacal only: a replay's own fallback fit is the replays', the plain fit's stages the plain's)
    real = (engine_measure._measure, engine_measure._replay_all, metacal.metacal_observations,
            metacal.measure_metacal, shearfit.measure_object)
    engine_measure._measure = _staged(proxy, totals, "noshear fit", real[0], within="metacal")
    engine_measure._replay_all = _staged(proxy, totals, "replays", real[1], within="metacal")
    metacal.metacal_observations = _staged(proxy, totals, "images", real[2], within="metacal")
    measure_mc, measure_plain = _staged(proxy, totals, "metacal", real[3]), _staged(proxy, totals, "plain", real[4])
    for m in holders:
        m.KERNEL = proxy
    for n in fft_names:
        setattr(sfft, n, clocked_fft(saved_fft[n]))
    rng = np.random.default_rng(3)
    try:
        for o, t in objs:
            measure_plain(o, mag=t["mag"], config=cfg)
            measure_mc(o, t["mag"], cfg, rng=rng, psf=psf)
    finally:
        engine_measure._measure, engine_measure._replay_all, metacal.metacal_observations = real[:3]
        for m in holders:
            m.KERNEL = mod
        for n in fft_names:
            setattr(sfft, n, saved_fft[n])
    n = len(objs)
    inner = ("images", "noshear fit", "replays")
    rows = {"plain": totals.get("plain", 0.0)}
    rows.update((k, totals.get(k, 0.0)) for k in inner)
    rows["metacal, the rest"] = totals.get("metacal", 0.0) - sum(rows[k] for k in inner)
    keys = {"metacal, the rest": "metacal"}
    print(f"\n  metacal's time by stage, every compiled loop and scipy FFT clocked ({n} galaxies, one pass each way; "
          f"ms per galaxy):")
    print(f"    {'stage':20s} {'total':>7s} {'compiled':>9s} {'FFTs':>6s} {'the rest':>9s}")
    rest = {}
    for name, tot in rows.items():
        key = keys.get(name, name)
        # (each call is counted in the innermost stage under way: the umbrella's own calls only under metacal)
        k_s, f_s = proxy.by_stage.get(key, 0.0), fft_seconds.get(key, 0.0)
        rest[name] = tot - k_s - f_s
        print(f"    {name:20s} {1e3 * tot / n:7.2f} {1e3 * k_s / n:9.2f} {1e3 * f_s / n:6.2f} {1e3 * rest[name] / n:9.2f}")
    tm, tp = totals.get("metacal", 0.0), rows["plain"]
    own = rest["images"] + rest["replays"]
    print(f"    metacal {tm / tp:.2f} x the plain fit on this pass; without the rest (Python and numpy) of its images and "
          f"replays ({1e3 * own / n:.2f} ms a galaxy) {(tm - own) / tp:.2f} x")


#: the settings that trade exactness for speed, at their exact values
EXACT = {"mode_bins_per_octave": 0, "mode_polar_angles": 0, "n_flux": 11, "fold_chi2_tolerance": 0.0,
         "pair_chi2_tolerance": 0.0, "e_grid_prepass": 0.0, "tail_skip": 0.0, "size_reuse_distance": 0.0}

#: the noise-aware mode cut off: every Fourier mode the PSF passes (psf_mode_tolerance) enters the likelihood.
#: The cut drops data, the modes whose models' own power is weakest; what those modes' noise did to e goes
#: with them, so its effect is a scatter of e (it grows about as the square root of the tolerance), reported apart
MODE_CUT = {"mode_chi2_tolerance": 0.0}


class _TimedKernel:
    """The compiled module with a clock around each call of its functions (their seconds summed by name, and by
    the fit's stage under way, ``stage[0]``)."""

    def __init__(self, mod):
        self._mod = mod
        self.seconds = {}
        self.by_stage = {}
        self.stage = [None]

    def __getattr__(self, name):
        fn = getattr(self._mod, name)
        if not callable(fn):
            return fn
        seconds, by_stage, stage = self.seconds, self.by_stage, self.stage

        def call(*a):
            t0 = time.perf_counter()
            try:
                return fn(*a)
            finally:
                dt = time.perf_counter() - t0
                seconds[name] = seconds.get(name, 0.0) + dt
                by_stage[stage[0]] = by_stage.get(stage[0], 0.0) + dt
        return call


def _staged(proxy, seconds, name, fn, within=None):
    """``fn`` clocked as the stage ``name`` of ``proxy`` (its seconds into ``seconds[name]``, the compiled loops' within
    it into ``proxy.by_stage[name]``); with ``within``, only while that stage is under way (elsewhere ``fn`` runs
    unclocked, its time its caller's stage's)."""
    def run(*a, **k):
        outer = proxy.stage[0]
        if within is not None and outer != within:
            return fn(*a, **k)
        proxy.stage[0] = name
        t0 = time.perf_counter()
        try:
            return fn(*a, **k)
        finally:
            seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - t0
            proxy.stage[0] = outer
    return run


#: the stages of one fit (shearfit.engine.measure._measure's calls, in its order), timed by --kernel-times
FIT_STAGES = ("prepare_exposures", "join_exposures", "coarse_peak", "find_position", "shift_joint", "_size_range",
              "_size_likelihood", "adaptive_samples", "_result")


def _timed_stages(proxy, seconds):
    """Replace the fit's stages in shearfit.engine.measure by clocked ones (their seconds into ``seconds``; the
    compiled loops' seconds within each go to ``proxy.by_stage`` under its name); returns the originals."""
    from shearfit.engine import measure

    originals = {name: getattr(measure, name) for name in FIT_STAGES}
    for name, fn in originals.items():
        setattr(measure, name, _staged(proxy, seconds, name, fn))
    return originals


def kernel_times_report(objs, cfg):
    """One pass over ``objs`` with every call of the compiled loops timed (a clock around each call, no
    profiler): milliseconds per galaxy in each, and what is left, Python and numpy."""
    from shearfit.engine import likelihood, model, moffat, sampling

    modules = (likelihood, sampling, model, moffat)
    mod = likelihood.KERNEL
    if mod is None:
        print("\n  --kernel-times: the numpy loops run (no compiled module); nothing to time")
        return
    from shearfit.engine import measure

    proxy = _TimedKernel(mod)
    for m in modules:
        m.KERNEL = proxy
    stage_seconds = {}
    originals = _timed_stages(proxy, stage_seconds)
    try:
        dt, _ = timed(objs, cfg)
    finally:
        for m in modules:
            m.KERNEL = mod
        for name, fn in originals.items():
            setattr(measure, name, fn)
    n = len(objs)
    total = sum(proxy.seconds.values())
    print(f"\n  the compiled loops, one pass of {n} galaxies timed call by call (ms per galaxy; {1e3 * dt / n:.1f} in "
          "all):")
    for name, sec in sorted(proxy.seconds.items(), key=lambda kv: -kv[1]):
        if 1e3 * sec / n >= 0.005:
            print(f"    {name:24s} {1e3 * sec / n:7.3f}  {100 * sec / dt:5.1f} %")
    print(f"    {'all compiled loops':24s} {1e3 * total / n:7.3f}  {100 * total / dt:5.1f} %")
    print(f"    {'the rest (Python, numpy)':24s} {1e3 * (dt - total) / n:7.3f}  {100 * (dt - total) / dt:5.1f} %")
    print("\n  the same pass by stage of the fit (ms per galaxy: the stage, its compiled loops, the rest; the rest's "
          "share of the whole):")
    for name in sorted(stage_seconds, key=lambda k: -stage_seconds[k]):
        sec, comp = stage_seconds[name], proxy.by_stage.get(name, 0.0)
        print(f"    {name:24s} {1e3 * sec / n:7.3f} {1e3 * comp / n:7.3f} {1e3 * (sec - comp) / n:7.3f}  "
              f"{100 * (sec - comp) / dt:5.1f} %")
    outside = dt - sum(stage_seconds.values())
    print(f"    {'outside the stages':24s} {1e3 * outside / n:7.3f} {1e3 * proxy.by_stage.get(None, 0.0) / n:7.3f}")


def census_report(objs, cfg):
    """Where a fit's ellipticity samples lie: per galaxy, by the lattice cell each stands for (its step; 0: a sample
    that stands for none, such as a coarse point inside a finer region) and by its posterior against the maximum:
    above the posterior cut (the estimator's samples), within ``e_grid_prepass_margin`` below it, or beyond."""
    cut = float(np.log(cfg.posterior_cut))
    margin = float(cfg.e_grid_prepass_margin)
    rows = {}
    n = 0
    for o, t in objs:
        r = shearfit.measure_object(o, mag=t["mag"], config=cfg, return_samples=True)
        s = getattr(r, "samples", None)
        if s is None or len(s) == 0:
            continue
        n += 1
        lp = np.asarray(s["logpost"], float)
        lp = lp - np.max(lp[np.isfinite(lp)])
        step = np.rint(np.sqrt(np.asarray(s["area"], float)) / cfg.e_grid_min).astype(int)
        for k in np.unique(step):
            m = step == k
            c = rows.setdefault(int(k), np.zeros(3))
            c += [np.sum(lp[m] > cut), np.sum((lp[m] <= cut) & (lp[m] > cut - margin)), np.sum(~(lp[m] > cut - margin))]
    if not n:
        return
    print(f"\n  ellipticity samples per galaxy ({n} galaxies), by the cell each stands for and by its posterior "
          f"against the maximum (cut: {cut:.2f} nats; margin below it: {margin:g}):")
    print(f"    {'cell (lattice steps of ' + format(cfg.e_grid_min, 'g') + ')':28s} {'above cut':>10s} "
          f"{'within margin':>14s} {'beyond':>8s}")
    tot = np.zeros(3)
    for k in sorted(rows, reverse=True):
        c = rows[k] / n
        tot += c
        label = f"{k} ({k * cfg.e_grid_min:g})" if k else "0 (stands for no cell)"
        print(f"    {label:28s} {c[0]:10.1f} {c[1]:14.1f} {c[2]:8.1f}")
    print(f"    {'all':28s} {tot[0]:10.1f} {tot[1]:14.1f} {tot[2]:8.1f}")


def check_report(objs, cfg, res, seed, each=False):
    """The speed settings against the exact ones (EXACT), on the timed galaxies and on faint ones:
    how far the estimates move, in e and in units of their own error. ``each``: also every setting of EXACT
    alone at its exact value, the others as they are, so that each approximation's own effect shows. Then the
    mode cut's own effect (MODE_CUT, the other settings as they are)."""
    from dataclasses import replace

    faint = ring_set(len(objs), (0.0, 0.0), np.random.default_rng(seed + 1000), n_rotations=1, n_exposures=7,
                     snr_range=(7, 15), mag_range=(23.0, 24.7), stamp_size=48)
    sets = (("timed set, SNR 10-60", objs, res),
            ("faint set, SNR 7-15", faint, [shearfit.measure_object(o, mag=t["mag"], config=cfg) for o, t in faint]))
    cases = [EXACT] + ([{k: v} for k, v in EXACT.items()] if each else []) + [MODE_CUT]
    for case in cases:
        what = ("the mode cut (it drops data: the modes where the models' own power is weakest): these settings against"
                if case is MODE_CUT else "check: these settings against")
        print(f"\n{what} {', '.join(f'{k}={v}' for k, v in case.items())}")
        exact = replace(cfg, **case)
        for label, ob, fast in sets:
            ref = [shearfit.measure_object(o, mag=t["mag"], config=exact) for o, t in ob]
            ok = [(a, b) for a, b in zip(ref, fast) if a.fitclass == 0 and b.fitclass == 0]
            de = np.array([[a.e1 - b.e1, a.e2 - b.e2] for a, b in ok])
            err = np.sqrt([a.e_var for a, _ in ok])
            rel = np.abs(de).max(axis=1) / err
            dw = np.array([abs(a.weight - b.weight) / a.weight for a, b in ok if a.weight > 0])
            same = sum(a.fitclass == b.fitclass for a, b in zip(ref, fast))
            move = np.abs(de).max(axis=1)
            order = np.argsort(move)[::-1]
            worst = ok[order[0]][0]
            print(f"  {label}: {len(ok)} galaxies; max |de| {np.max(np.abs(de)):.1e} (rms "
                  f"{np.sqrt(np.mean(de ** 2)):.1e}), at most {np.max(rel):.1e} of the error on e (rms "
                  f"{np.sqrt(np.mean((de / err[:, None]) ** 2)):.1e}); weights within {np.max(dw):.1e}; fitclass the "
                  f"same for {same} of {len(ref)}; the largest move at measured SNR {worst.snr:.1f}, e ("
                  f"{worst.e1:+.2f}, {worst.e2:+.2f}), {rel[order[0]]:.1e} of its error; the next "
                  f"{move[order[1]] if move.size > 1 else np.nan:.1e}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n-galaxies", type=int, default=40)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--passes", type=int, default=5,
                    help="timed passes over the galaxies (after an untimed one): the median is reported, with the "
                         "slowest and fastest, since a shared machine's speed drifts by 10-20 %% from pass to pass")
    ap.add_argument("--scaling", action="store_true", help="also time 1-14 exposures and 32-64 pixel stamps")
    ap.add_argument("--moffat-per-exposure", action="store_true",
                    help="fit the above-Nyquist Moffat (App. A) once per exposure, as shearfit measure does per "
                         "CCD, instead of once per object and exposure")
    ap.add_argument("--one-jacobian", action="store_true",
                    help="every exposure with the same Jacobian, so that their Fourier modes coincide and merge "
                         "(exactly); the default gives each exposure's pixel grid its own rotation, and "
                         "--jacobian-jitter its distortion, so that none merge, as on a real camera")
    ap.add_argument("--jacobian-jitter", type=float, default=0.01, metavar="RMS",
                    help="multiply each exposure's Jacobian by 1 + A, A of normal deviates of this rms (a camera's "
                         "distortion; default 0.01)")
    ap.add_argument("--same-galaxies", action="store_true",
                    help="time every pass on the same galaxies (by default each pass measures new ones)")
    ap.add_argument("--workers", type=int, default=0, metavar="N",
                    help="also time N worker processes (shearfit.measure_objects) against one")
    ap.add_argument("--no-hsm", action="store_true", help="do not time GalSim's HSM on the same stamps")
    ap.add_argument("--kernel-times", action="store_true",
                    help="one more pass with a clock around every call of the compiled loops: the time in each, and "
                         "the rest (Python and numpy), without a profiler's overhead; and the same by stage of the fit "
                         "(the exposures' preparation, their join, the peak searches, the sampling, ...); with "
                         "--metacal, metacal's stages (images, noshear fit, replays) split the same way")
    ap.add_argument("--isa-ab", metavar="LEVEL", default=None,
                    help="also time the loops in use against another level (avx512, avx2, baseline), galaxy by "
                         "galaxy in this process")
    ap.add_argument("--moffat-ab", action="store_true",
                    help="also time the App. A Moffat fits and tables made by the compiled kernel against the numpy "
                         "lines, galaxy by galaxy in this process")
    ap.add_argument("--setting-ab", action="append", default=[], metavar="KEY=VALUE",
                    help="also time the settings in use against the same with KEY=VALUE (repeatable: all together), "
                         "galaxy by galaxy in this process")
    ap.add_argument("--constant-psf", action="store_true",
                    help="one PSF image for every exposure of every galaxy (as the GREAT challenges' constant-PSF "
                         "branches): the App. A Moffat is fitted once and remembered")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="engine setting")
    ap.add_argument("--metacal", action="store_true",
                    help="also time the metacal measurement (five versions per object) against the plain one")
    ap.add_argument("--metacal-psf", choices=["dilated", "round"], default="dilated",
                    help="with --metacal: the versions' new PSF (shearfit.calib.metacal.metacal_observations' psf)")
    ap.add_argument("--metacal-own-position", action="store_true",
                    help="with --metacal: the sheared versions find their own position instead of replaying the "
                         "noshear fit's (measure_metacal's own_position=True)")
    ap.add_argument("--metacal-own-samples", action="store_true",
                    help="with --metacal: the sheared versions run the adaptive ellipticity grid on their own "
                         "likelihoods (measure_metacal's own_samples=True)")
    ap.add_argument("--census", action="store_true",
                    help="also count where each galaxy's ellipticity samples lie: by the lattice cell each stands for "
                         "and by its posterior against the cut (what the adaptive grid spends its fits on)")
    ap.add_argument("--check-each", action="store_true",
                    help="with --check, also each speed setting alone at its exact value (its own effect)")
    ap.add_argument("--check", action="store_true",
                    help="also measure the galaxies (and as many faint ones) with the exact settings and report "
                         "how far the speed settings (mode binning, flux nodes, ...) move the estimates; then the "
                         "mode cut's own effect (mode_chi2_tolerance: 0, every mode the PSF passes)")
    args = ap.parse_args(argv)
    from shearfit.config import settings_from_items

    cfg = shearfit.fit_config_from_mapping(settings_from_items(args.set))
    from shearfit.engine.kernel import kernel_info

    info = kernel_info()
    rotate = not args.one_jacobian
    jitter = 0.0 if args.one_jacobian else args.jacobian_jitter
    print(f"shearfit {shearfit.__version__}; CPU: {cpu_name()}; inner loops: {info['path']} "
          f"({info['isa']}; the CPU runs {', '.join(info['cpu_levels']) or '-'}"
          f"{'; SHEARFIT_ISA=' + info['requested'] if info['requested'] else ''}); "
          f"sampling={cfg.sampling}, alias_correction={cfg.alias_correction}")
    n_sets = 1 if args.same_galaxies else max(args.passes, 1) + 1
    sets = [simulate(args.n_galaxies, 7, 48, args.seed + 1000 * k, rotate, jitter, args.constant_psf)
            for k in range(n_sets)]
    if args.moffat_per_exposure:
        sets = [one_moffat_per_exposure(s) for s in sets]
    objs = sets[0]
    timed(objs[:2], cfg)   # build the profile tables once, outside the timing
    prof = cProfile.Profile()
    prof.enable()
    dt, res = timed(objs, cfg)
    prof.disable()
    n_models = np.mean([getattr(r, "n_models", np.nan) for r in res])
    n_samp = np.mean([r.n_samples for r in res])
    # the profiler slows Python-level code; time again without it, pass after pass (new galaxies each time)
    times, peer = [], []
    for k in range(max(args.passes, 1)):
        s = sets[(k + 1) % len(sets)]
        if args.no_hsm:
            dt, _ = timed(s, cfg)
        else:   # HSM on each galaxy right after shearfit (timed_with_peer)
            dt, dh, fails = timed_with_peer(s, cfg)
            peer.append((dh / len(s), fails, dt / dh))
        times.append(dt / len(s))
    per = float(np.median(times))
    jacobians = ("one Jacobian" if args.one_jacobian else
                 f"each its own rotation and {jitter:g} rms distortion")
    psfs = ("one constant PSF" if args.constant_psf else "each its own elliptical Moffat PSF") + (
        ", App. A Moffat fitted once per exposure" if args.moffat_per_exposure else
        ", App. A Moffat fitted to every PSF")
    print(f"\n7 exposures ({jacobians}; {psfs}), 48-pixel stamps, {len(objs)} galaxies per pass "
          f"({'the same' if args.same_galaxies else 'new'} galaxies every pass; SNR {SNR_RANGE[0]}-{SNR_RANGE[1]}, "
          f"mag 21-24.7):")
    print(f"  {1 / per:.2f} galaxies / s / core   ({1e3 * per:.1f} ms per galaxy; "
          f"{n_samp:.0f} ellipticity samples and {n_models:.0f} (e, r) models per galaxy on average)")
    print(f"  median of {len(times)} timed passes; slowest {1 / max(times):.2f}, fastest "
          f"{1 / min(times):.2f} galaxies / s")
    if peer:
        hsm = float(np.median([p[0] for p in peer]))
        ratio = [p[2] for p in peer]
        print(f"  peer: GalSim HSM REGAUSS on the same 7 stamps per galaxy, same process, galaxy by galaxy after "
              f"shearfit: {1e3 * hsm:.1f} ms per galaxy ({1 / hsm:.1f} galaxies / s; {sum(p[1] for p in peer)} failed "
              f"stamps); shearfit / HSM time: {float(np.median(ratio)):.2f} (median of the passes' ratios; "
              f"{min(ratio):.2f}-{max(ratio):.2f})")
    stage_report(pstats.Stats(prof))
    if args.kernel_times:   # galaxies of their own (the PSFs' App. A Moffats are remembered by image)
        extra = simulate(args.n_galaxies, 7, 48, args.seed + 1000 * n_sets, rotate, jitter, args.constant_psf)
        kernel_times_report(one_moffat_per_exposure(extra) if args.moffat_per_exposure else extra, cfg)
    print("\n  top functions by internal time:")
    pstats.Stats(prof).sort_stats("tottime").print_stats(8)
    if args.metacal:
        metacal_report(objs, cfg, args.passes, args.metacal_psf, args.metacal_own_position,
                       args.metacal_own_samples)
        metacal_image_profile(objs)
        if args.kernel_times:
            metacal_kernel_split(objs, cfg, args.metacal_psf)
    if args.census:
        census_report(objs, cfg)
    if args.check:
        check_report(objs, cfg, res, args.seed, each=args.check_each)
    if args.isa_ab:
        isa_ab_report(sets, cfg, args.isa_ab)
    if args.moffat_ab:
        moffat_ab_report(sets, cfg)
    if args.setting_ab:
        setting_ab_report(sets, cfg, settings_from_items(args.setting_ab))
    if args.workers > 1:
        workers_report([g for s in sets[:2] for g in s], cfg, args.workers)
    if args.scaling:
        print("growth with the number of exposures (48-pixel stamps):")
        base = None
        for n_exp in (1, 2, 4, 7, 14):
            o = simulate(max(args.n_galaxies // 2, 6), n_exp, 48, args.seed + n_exp, rotate, jitter)
            if args.moffat_per_exposure:
                o = one_moffat_per_exposure(o)
            d, _ = timed(o, cfg)
            per = d / len(o)
            base = base or per
            print(f"  {n_exp:3d} exposures: {1 / per:7.2f} galaxies/s/core  ({1e3 * per:7.1f} ms, x{per / base:.2f})")
        print("growth with the stamp size (7 exposures):")
        for stamp in (32, 48, 64):
            o = simulate(max(args.n_galaxies // 2, 6), 7, stamp, args.seed + stamp, rotate, jitter)
            if args.moffat_per_exposure:
                o = one_moffat_per_exposure(o)
            d, _ = timed(o, cfg)
            print(f"  {stamp:3d} pixels: {len(o) / d:7.2f} galaxies/s/core ({1e3 * d / len(o):7.1f} ms)")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"\npeak memory (max RSS of this process): {peak:.0f} MB")


if __name__ == "__main__":
    main()

#!/usr/bin/env python
"""Memory per object fit: the peak for stamps of 48-128 pixels and for the largest galaxies, against the estimate.

For each case, galaxies are simulated with GalSim as ``benchmarks/speed.py`` does (7 exposures, each with
its own rotation of the pixel grid, 1 % rms distortion and elliptical Moffat PSF image, the App. A Moffat
fitted to every PSF) and fitted by ``shearfit.measure_object`` in a fresh worker process (``spawn``), once
without and once with ``tracemalloc``, so that each case's numbers are its own:

* tracemalloc: the largest Python-level peak (numpy's arrays included) of one object's fit, the caches of
  its stamp size cold (the worker's first fit of that size builds its alias tables); each worker first fits
  one 32-pixel galaxy, which builds what every worker builds once whatever the size (profile tables, lazy
  imports);
* RSS: the worker's high-water mark over the case's fits (VmHWM, reset after that first fit; ``ru_maxrss``
  where it cannot be reset) and its growth over the worker's RSS before them;
* the estimate of :func:`shearfit.pipeline.memory.fit_memory_bytes` (what ``max_object_memory_mb`` is
  compared with; the largest over the case's galaxies), each exposure's PSF FWHM from its adaptive moments;
* the median wall time of one fit (the pass without tracemalloc).

Then, unless ``--no-field``, a small simulated field through ``measure_field`` with 2 worker processes
(``executor="processes"``, chunks of 8 objects): the peak RSS of a worker (the largest of the 2) and of
the parent. Prints the CPU.

    python benchmarks/memory.py                  # 2 galaxies per case, the field
    python benchmarks/memory.py --n-galaxies 4 --no-field
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import multiprocessing as mp  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from speed import cpu_name  # noqa: E402  (benchmarks/speed.py, beside this script)

MIB = 2.0 ** 20
PIX = 0.187
#: the largest galaxies: a disk of half-light radius 3 arcsec (scalelength 3 / 1.678)
LARGE_HLR = 3.0


def _large_population(mags, rng, cfg):
    """The largest galaxies: pure disks of half-light radius LARGE_HLR, random ellipticity up to 0.5."""
    e = 0.5 * np.sqrt(rng.uniform())
    phi = rng.uniform(0.0, np.pi)
    return {"scalelength": LARGE_HLR / 1.678, "bulge_fraction": 0.0, "is_bulge": False,
            "e1": e * np.cos(2 * phi), "e2": e * np.sin(2 * phi)}


#: name: (stamp side, ring_set keywords)
CASES = {
    "48 px": (48, {}),
    "64 px": (64, {}),
    "96 px": (96, {}),
    "128 px": (128, {}),
    "128 px, hlr 3\"": (128, dict(population=_large_population, mag_range=(18.5, 20.0), snr_range=(100, 300))),
    "128 px, PSF 0.45\"": (128, dict(psf_fwhm_range=(0.45, 0.5), psf_beta_range=(2.5, 2.5), snr_range=(200, 400),
                                     mag_range=(21.0, 22.0))),
}


def simulate(side, n, seed, extra):
    from shearfit.simulate.stamps import ring_set

    kw = dict(snr_range=(10, 40), mag_range=(21.0, 24.7))
    kw.update(extra)
    return ring_set(n, (0.0, 0.0), np.random.default_rng(seed), n_rotations=1, n_exposures=7, stamp_size=side,
                    rotate_exposures=True, jacobian_jitter=0.01, **kw)


def _status(key):
    """VmRSS or VmHWM of this process, bytes (Linux /proc); ru_maxrss where there is none."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return float(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0


def _reset_high_water():
    """Reset this process's RSS high-water mark (Linux: 5 to /proc/self/clear_refs); False where it cannot."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _worker(objs, warm, traced, queue):
    """One case in a fresh process: after one fit of a 32-pixel galaxy (the profile tables, lazy imports and
    the compiled loops of any worker, not of the case), fit every object; tracemalloc peaks or RSS, times."""
    import tracemalloc

    import shearfit

    cfg = shearfit.FitConfig()
    shearfit.measure_object(warm[0], warm[1]["mag"], cfg)
    reset = _reset_high_water()
    rss0 = _status("VmRSS")
    peaks, times, classes = [], [], []
    for obs, truth in objs:
        if traced:
            tracemalloc.start()
        t0 = time.perf_counter()
        res = shearfit.measure_object(obs, truth["mag"], cfg)
        times.append(time.perf_counter() - t0)
        if traced:
            peaks.append(tracemalloc.get_traced_memory()[1])
            tracemalloc.stop()
        classes.append(int(res.fitclass))
    hwm = _status("VmHWM") if reset else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0
    queue.put(dict(peaks=peaks, times=times, rss0=rss0, hwm=hwm, classes=classes))


def in_fresh_process(target, *args):
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=target, args=(*args, q))
    p.start()
    out = q.get()
    p.join()
    return out


def estimate(objs, side):
    """The largest estimate over the case's galaxies (each exposure's FWHM from its PSF's adaptive moments)."""
    import shearfit
    from shearfit.pipeline.driver import psf_moments
    from shearfit.pipeline.memory import fit_memory_bytes

    cfg = shearfit.FitConfig()
    out, every = [], []
    for obs, _ in objs:
        fwhm = []
        for o in obs:
            m = psf_moments(o.psf)
            fwhm.append(np.nan if m is None else 2.3548 * m[0] / o.psf_oversampling)
        out.append(fit_memory_bytes(side, len(obs), cfg, psf_fwhm=fwhm,
                                    psf_oversampling=[o.psf_oversampling for o in obs]))
        every += fwhm
    return max(out), float(np.nanmean(every))


def object_table(n, seed):
    print("Peak memory of one object's fit, 7 exposures, each case in a fresh worker process (MiB; time per fit):\n")
    print("| case | PSF FWHM (px) | tracemalloc peak | worker RSS high-water | RSS growth | estimate | "
          "estimate / max(peak, growth) | s per fit |")
    print("|---|---|---|---|---|---|---|---|")
    warm = simulate(32, 1, seed + 99, {})[0]
    for k, (name, (side, extra)) in enumerate(CASES.items()):
        objs = simulate(side, n, seed + 100 + k, extra)
        est, fwhm = estimate(objs, side)
        plain = in_fresh_process(_worker, objs, warm, False)
        traced = in_fresh_process(_worker, objs, warm, True)
        peak = max(traced["peaks"])
        growth = plain["hwm"] - plain["rss0"]
        print(f"| {name} | {fwhm:.1f} | {peak / MIB:.1f} | {plain['hwm'] / MIB:.0f} | {growth / MIB:.1f} | "
              f"{est / MIB:.1f} | {est / max(peak, growth):.2f} | {np.median(plain['times']):.2f} |", flush=True)


def _field_worker(directory, queue):
    import logging

    from shearfit.io.fieldconfig import load_field_config
    from shearfit.pipeline.driver import measure_field
    from shearfit.simulate.field import simulate_field, simulation_config

    logging.disable(logging.WARNING)
    sc = simulation_config({"preset": "tiny", "n_exposures": 7, "seed": 3, "ccd_nx": 540, "ccd_ny": 540,
                            "grid_spacing": 90.0, "mag_range": [17.5, 22.0], "max_scalelength": 2.5})
    info = simulate_field(sc, directory)
    cfg = load_field_config(info["config"], ["chunk_size=8"])
    rss0 = _status("VmRSS")
    t0 = time.perf_counter()
    tab = measure_field(cfg, os.path.join(directory, "shear.fits"), processes=2, executor="processes")
    dt = time.perf_counter() - t0
    sizes = {int(s): int(c) for s, c in zip(*np.unique(np.asarray(tab["stamp_size"]), return_counts=True))}
    queue.put(dict(n=len(tab), dt=dt, rss0=rss0, sizes=sizes,
                   workers=resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024.0,
                   parent=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0,
                   measured=int(np.sum(np.asarray(tab["fitclass"]) >= 0))))


def field_report():
    with tempfile.TemporaryDirectory() as d:
        r = in_fresh_process(_field_worker, d)
    sizes = ", ".join(f"{c} on {s} px" for s, c in sorted(r["sizes"].items()))
    print(f"\nmeasure_field, 2 worker processes (executor 'processes', fork), a simulated field of 7 exposures "
          f"(one 540 x 540 CCD each, given PSFs; galaxies of mag 17.5-22, 90 pixels apart), {r['n']} objects "
          f"({r['measured']} measured; stamps: {sizes}) in {r['dt']:.1f} s:")
    print(f"  peak RSS per worker (the larger of the 2): {r['workers'] / MIB:.0f} MiB; the parent: "
          f"{r['parent'] / MIB:.0f} MiB (before measure_field, with the field simulated: {r['rss0'] / MIB:.0f} "
          f"MiB; the workers fork from it, sharing its pages copy-on-write)")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-galaxies", type=int, default=2, help="galaxies fitted per case")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-field", action="store_true", help="skip the measure_field run with 2 workers")
    args = ap.parse_args(argv)
    import shearfit
    from shearfit.engine.kernel import kernel_info

    info = kernel_info()
    print(f"shearfit {shearfit.__version__}; CPU: {cpu_name()}; inner loops: {info['path']} ({info['isa']}); "
          f"Python {sys.version.split()[0]}\n")
    object_table(args.n_galaxies, args.seed)
    if not args.no_field:
        field_report()


if __name__ == "__main__":
    main()

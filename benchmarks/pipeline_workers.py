#!/usr/bin/env python
"""``shearfit measure`` with worker processes: one process against ``-j N`` on Dask and on a process pool.

Simulates a field (preset ``small`` with ``n_ccd: 6`` and ``exposure_rotation: 1``: 7 exposures, each turned by
its own angle, about 1600 objects), then runs the pipeline with the PSF images given, alternately on one process,
on a local Dask cluster of N workers and on a process pool of N, ``--rounds`` times, and prints each run's wall
time and CPU time (this process and its workers), and per chunk of objects, as the workers measured it: its CPU
time, its compute thread's own CPU time, its minor page faults and GalSim HSM calls. The catalogues of the runs
are compared column by column.

    python benchmarks/pipeline_workers.py                    # 2 workers, 2 rounds
    python benchmarks/pipeline_workers.py --before           # Dask's own worker settings, PSFs pickled as they come
    python benchmarks/pipeline_workers.py --keep DIR         # keep (or reuse) the simulated field

``--before`` puts back what session 86 changed, in this process and in the workers: Dask's
``MALLOC_TRIM_THRESHOLD_`` and sampling profiler (``local_cluster_config`` returns nothing) and the PSF images as
unpickling leaves them (no ``_ExposurePSF.__setstate__``).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

import shearfit.pipeline.driver as drv  # noqa: E402

#: where each worker appends a line per chunk (inherited by the workers, whose start re-runs this module's top level:
#: Dask's and spawn's workers import it as ``__mp_main__``, fork's inherit it)
LOG_ENV = "SHEARFIT_WORKERS_LOG"
BEFORE_ENV = "SHEARFIT_WORKERS_BEFORE"

if os.environ.get(BEFORE_ENV):
    drv.local_cluster_config = lambda: {}
    if "__setstate__" in vars(drv._ExposurePSF):
        del drv._ExposurePSF.__setstate__

_HSM_CALLS = [0]


def _count_hsm():
    import galsim.hsm

    orig = galsim.hsm.FindAdaptiveMom
    if getattr(orig, "_counted", False):
        return

    def counted(*a, **k):
        _HSM_CALLS[0] += 1
        return orig(*a, **k)

    counted._counted = True
    galsim.hsm.FindAdaptiveMom = counted


def _clocked(orig):
    def run(*a, **k):
        _count_hsm()
        r0 = resource.getrusage(resource.RUSAGE_SELF)
        c0, th0, h0 = time.process_time(), time.thread_time(), _HSM_CALLS[0]
        rows = orig(*a, **k)
        r1 = resource.getrusage(resource.RUSAGE_SELF)
        path = os.environ.get(LOG_ENV)
        if path:
            with open(path, "a") as fh:
                fh.write(json.dumps(dict(pid=os.getpid(), n=len(a[1]), cpu=time.process_time() - c0,
                                         thread=time.thread_time() - th0, minflt=r1.ru_minflt - r0.ru_minflt,
                                         hsm=_HSM_CALLS[0] - h0, main=threading.current_thread() is
                                         threading.main_thread())) + "\n")
        return rows
    return run


drv._measure_objects = _clocked(drv._measure_objects)


def _cpu_all():
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def _run(cfg, out, processes, executor, log):
    """One run in a child process (so that its workers' CPU is counted as its children's): (wall, CPU, chunks)."""
    import multiprocessing

    if os.path.exists(log):
        os.remove(log)
    ctx = multiprocessing.get_context("fork")
    q = ctx.Queue()

    def child():
        os.environ[LOG_ENV] = log
        c0, t0 = _cpu_all(), time.perf_counter()
        drv.measure_field(cfg, out_path=out, processes=processes, restart=True, executor=executor)
        # a pool's or cluster's workers have ended: their CPU is in RUSAGE_CHILDREN
        q.put((time.perf_counter() - t0, _cpu_all() - c0))

    p = ctx.Process(target=child)
    p.start()
    wall, cpu = q.get()
    p.join()
    with open(log) as fh:
        chunks = [json.loads(line) for line in fh]
    return wall, cpu, chunks


def _same(a, b):
    from astropy.table import Table

    ta, tb = Table.read(a), Table.read(b)
    if len(ta) != len(tb):
        return [f"rows {len(ta)} != {len(tb)}"]
    bad = []
    for c in ta.colnames:
        x, y = np.asarray(ta[c]), np.asarray(tb[c])
        if not (np.array_equal(x, y, equal_nan=True) if x.dtype.kind in "fc" else np.array_equal(x, y)):
            bad.append(c)
    return bad


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--keep", default=None, help="keep the field in this directory (reused if it holds one)")
    ap.add_argument("--before", action="store_true",
                    help="Dask's own worker settings and the PSF images as unpickling leaves them (see the doc)")
    args = ap.parse_args(argv)
    if args.before:
        # set before any worker starts; this module's top level reads it again in each worker
        os.environ[BEFORE_ENV] = "1"
        drv.local_cluster_config = lambda: {}
        if "__setstate__" in vars(drv._ExposurePSF):
            del drv._ExposurePSF.__setstate__
    from shearfit.engine.kernel import kernel_info
    from shearfit.io.fieldconfig import load_field_config
    from shearfit.simulate.field import simulate_field, simulation_config

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from speed import cpu_name

    info = kernel_info()
    print(f"CPU: {cpu_name()}; inner loops: {info['path']} ({info['isa']}); {os.cpu_count()} CPUs"
          f"{'; --before: Dask worker defaults, PSF images as unpickled' if args.before else ''}")
    with tempfile.TemporaryDirectory() as tmp:
        d = args.keep or tmp
        if not os.path.exists(os.path.join(d, "field_truepsf.yaml")):
            t0 = time.perf_counter()
            simulate_field(simulation_config(dict(preset="small", n_ccd=6, exposure_rotation=1, seed=args.seed)), d)
            print(f"simulated in {time.perf_counter() - t0:.0f} s")
        cfg = load_field_config(os.path.join(d, "field_truepsf.yaml"))
        modes = [("one process", 1, "processes"), (f"Dask, {args.workers} workers", args.workers, "dask"),
                 (f"process pool, {args.workers} workers", args.workers, "processes")]
        walls = {m[0]: [] for m in modes}
        for r in range(max(args.rounds, 1)):
            for label, n, ex in modes:
                out = os.path.join(d, f"shear_{n}_{ex}.fits")
                wall, cpu, chunks = _run(cfg, out, n, ex, os.path.join(d, "chunks.jsonl"))
                walls[label].append(wall)
                k = len(chunks)
                per = lambda f: np.median([c[f] for c in chunks if c["n"] == max(x["n"] for x in chunks)])  # noqa: E731
                print(f"round {r + 1}, {label}: wall {wall:.2f} s, CPU {cpu:.1f} s (this process and its workers); "
                      f"{k} chunks, per full chunk (median): CPU {per('cpu'):.2f} s, its thread {per('thread'):.2f} s, "
                      f"{per('minflt'):.0f} page faults, {per('hsm'):.0f} HSM calls", flush=True)
        one = np.array(walls[modes[0][0]])
        for label, _, _ in modes[1:]:
            x = one / np.array(walls[label])
            print(f"{label}: x{', x'.join(f'{v:.2f}' for v in x)} the single process's speed (round by round)")
        ref = os.path.join(d, "shear_1_processes.fits")
        for _, n, ex in modes[1:]:
            bad = _same(ref, os.path.join(d, f"shear_{n}_{ex}.fits"))
            print(f"catalogue of -j {n} --executor {ex} against -j 1: "
                  f"{'identical in every column' if not bad else 'DIFFERS in ' + ', '.join(bad)}")


if __name__ == "__main__":
    main()

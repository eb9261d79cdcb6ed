#!/usr/bin/env python
"""Survey-scale behaviour of ``shearfit measure`` (issue 7): workers, scheduler, kills, memory.

On one simulated field (``shearfit simulate``, preset ``small`` by default,
true PSF given so that every run does the same work):

1. throughput with 1 process, with a local Dask cluster of 2 workers
   (``-j 2``, each under ``--memory-limit``), and on an explicitly started
   LocalCluster through ``--scheduler ADDRESS``; scaling efficiency =
   rate(2) / (2 rate(1)); the peak resident memory of the main process and
   of the largest worker (sampled every 0.2 s);
2. the run killed (SIGKILL) at three moments (after 1, 3 and 6 finished
   chunks), rerun to completion: the final catalogue against the
   uninterrupted one, and the work lost (objects measured twice);
3. peak memory (max RSS of the measuring process tree) for catalogues of
   10^3, 10^4 and 10^5 objects: the field's objects plus objects outside
   every exposure (they cost a catalogue row each), so the fitting work is
   the same and only the catalogue grows.

    python benchmarks/cluster_run.py
    python benchmarks/cluster_run.py --field /tmp/psxi/field --chunk-size 256 --parts throughput,scheduler

(the second on a CFHTLenS-sized field made by ``benchmarks/shear_field_xi.py`` or ``shearfit simulate``
with ``preset: cfhtlens``).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np
from astropy.table import Table, vstack

from shearfit.simulate.field import simulate_field, simulation_config


# ``shearfit measure ARGS`` in a fresh interpreter
MEASURE = [sys.executable, "-c", "import sys; from shearfit.app.cli import main; sys.exit(main(sys.argv[1:]))",
           "measure"]


def run(args, env=None):
    """``shearfit measure ...`` in a fresh process: (wall seconds, peak RSS MB of the main process, peak RSS MB
    of the largest of its child processes (the Dask workers), or 0 without any), sampled every 0.2 s."""
    import psutil

    t0 = time.perf_counter()
    proc = subprocess.Popen(MEASURE + args, env=env)
    main_peak, child_peak = 0, 0
    ps = psutil.Process(proc.pid)
    while proc.poll() is None:
        try:
            main_peak = max(main_peak, ps.memory_info().rss)
            for c in ps.children(recursive=True):
                try:
                    child_peak = max(child_peak, c.memory_info().rss)
                except psutil.Error:
                    pass
        except psutil.Error:
            pass
        time.sleep(0.2)
    if proc.returncode != 0:
        raise SystemExit(f"shearfit measure {' '.join(args)} failed ({proc.returncode})")
    return time.perf_counter() - t0, main_peak / 1e6, child_peak / 1e6


def same(a, b):
    for c in a.colnames:
        x, y = np.asarray(a[c]), np.asarray(b[c])
        if not np.array_equal(x, y, equal_nan=x.dtype.kind == "f"):
            return False
    return a.colnames == b.colnames


def kill_after(cfg, out, n_chunks, chunk_size):
    """Start the run, SIGKILL it once ``n_chunks`` chunks are on disk; the chunks done and seconds run."""
    parts = out + ".parts"
    proc = subprocess.Popen(MEASURE + [cfg, f"chunk_size={chunk_size}", "--out", out, "--quiet"])
    t0 = time.perf_counter()
    while proc.poll() is None:
        done = [f for f in os.listdir(parts) if f.startswith("chunk_")] if os.path.isdir(parts) else []
        if len(done) >= n_chunks:
            proc.send_signal(signal.SIGKILL)
            break
        time.sleep(0.02)
    proc.wait()
    done = [f for f in os.listdir(parts) if f.startswith("chunk_")] if os.path.isdir(parts) else []
    return len(done), time.perf_counter() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="small")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--field", default=None, help="an already simulated field directory (then no simulation)")
    ap.add_argument("--chunk-size", type=int, default=32)
    ap.add_argument("--memory-limit", default="1GB", help="per worker of the -j 2 and --scheduler runs")
    ap.add_argument("--parts", default="throughput,scheduler,kill,memory",
                    help="comma-separated: throughput (1 process and -j 2), scheduler, kill, memory")
    ap.add_argument("--keep", default=None)
    ap.add_argument("--reuse-ref", action="store_true",
                    help="take the 1-process reference (catalogue, time, memory) from an earlier run kept in --keep")
    args = ap.parse_args(argv)
    parts = set(args.parts.split(","))
    from dask.distributed import LocalCluster

    with tempfile.TemporaryDirectory() as tmp:
        d = args.field or args.keep or tmp
        os.makedirs(d, exist_ok=True)
        if args.field is None:
            simulate_field(simulation_config({"preset": args.preset, "seed": args.seed}), d)
        out_dir = args.keep or tmp
        cfg = os.path.join(d, "field_truepsf.yaml")
        cs = f"chunk_size={args.chunk_size}"
        n = len(Table.read(os.path.join(d, "objects.fits")))
        print(f"field: {d if args.field else 'preset ' + args.preset}, {n} objects, chunks of {args.chunk_size}")

        ref = os.path.join(out_dir, "ref.fits")
        ref_json = os.path.join(out_dir, "ref.json")
        t1 = None
        if args.reuse_ref and os.path.exists(ref) and os.path.exists(ref_json):
            with open(ref_json) as f:
                saved = json.load(f)
            t1, mem1 = saved["seconds"], saved["rss_mb"]
            print(f"(the 1-process reference catalogue and its time from an earlier run: {ref})")
        elif parts & {"throughput", "kill"}:
            t1, mem1, _ = run([cfg, cs, "--out", ref, "--quiet"])
            with open(ref_json, "w") as f:
                json.dump({"seconds": t1, "rss_mb": mem1}, f)
        reft = Table.read(ref) if t1 is not None else None
        if "throughput" in parts:
            t2, mem2, wmem2 = run([cfg, cs, "--out", os.path.join(out_dir, "j2.fits"), "--quiet", "-j", "2",
                                   "--memory-limit", args.memory_limit])
            print("\n1. throughput (objects per second, the whole command), peak RSS:")
            print(f"   1 process:                 {n / t1:6.2f}  ({t1:.0f} s); {mem1:.0f} MB")
            print(f"   -j 2 (local Dask cluster): {n / t2:6.2f}  ({t2:.0f} s); scaling efficiency "
                  f"{t1 / (2 * t2):.2f}; catalogue identical: {same(Table.read(os.path.join(out_dir, 'j2.fits')), reft)}"
                  f"; main process {mem2:.0f} MB, largest worker {wmem2:.0f} MB (limit {args.memory_limit})")
        if "scheduler" in parts:
            with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                              memory_limit=args.memory_limit) as cl:
                t3, mem3, _ = run([cfg, cs, "--out", os.path.join(out_dir, "sched.fits"), "--quiet", "--scheduler",
                                   cl.scheduler_address])
            same3 = same(Table.read(os.path.join(out_dir, "sched.fits")), reft) if reft is not None else "(no reference)"
            print(f"   --scheduler {cl.scheduler_address} (LocalCluster, 2 workers started beforehand): "
                  f"{n / t3:6.2f}  ({t3:.0f} s); catalogue identical: {same3}; client process {mem3:.0f} MB")

        if "kill" in parts:
            print("\n2. killed with SIGKILL, then rerun:")
            for k in (1, 3, 6):
                out = os.path.join(out_dir, f"killed{k}.fits")
                done, t_kill = kill_after(cfg, out, k, args.chunk_size)
                t_rest, _, _ = run([cfg, cs, "--out", out, "--quiet"])
                ok = same(Table.read(out), reft)
                lost = t_kill + t_rest - t1
                print(f"   killed after {done} chunk(s) ({t_kill:.0f} s), resumed in {t_rest:.0f} s: identical {ok}; "
                      f"time lost {lost:+.0f} s (a chunk takes about {t1 * args.chunk_size / n:.0f} s)")

        if "memory" in parts:
            print("\n3. peak memory (max RSS of the measuring process) against catalogue size, same fitting work:")
            cat = Table.read(os.path.join(d, "objects.fits"))
            rng = np.random.default_rng(0)
            for total in (1000, 10000, 100000):
                extra = max(total - len(cat), 0)
                far = Table({"id": np.arange(extra) + 10 ** 7, "ra": rng.uniform(100, 110, extra),
                             "dec": rng.uniform(30, 40, extra), "mag": np.full(extra, 23.0)})
                big = vstack([cat[["id", "ra", "dec", "mag"]], far])
                cpath = os.path.join(out_dir, f"objects_{total}.fits")
                big.write(cpath, overwrite=True)
                out = os.path.join(out_dir, f"mem_{total}.fits")
                wall, mem = run_isolated([cfg, f"catalog={cpath}", "--out", out, "--quiet"])
                print(f"   {len(big):7d} objects: {mem:6.0f} MB peak, {wall:.0f} s")


def run_isolated(args):
    """Like ``run`` but the RSS measured under /usr/bin/time-like isolation: a fresh grandchild per run."""
    code = ("import json, resource, subprocess, sys, time; t0 = time.perf_counter(); "
            "subprocess.run(json.loads(sys.argv[1]) + sys.argv[2:], check=True); "
            "print(time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
    out = subprocess.run([sys.executable, "-c", code, json.dumps(MEASURE)] + args, check=True,
                         capture_output=True, text=True).stdout
    wall, rss = out.split()[-2:]
    return float(wall), float(rss) / 1024.0


if __name__ == "__main__":
    main()

#!/usr/bin/env python
"""Survey-scale behaviour of ``shearfit measure`` (issue 7): workers, scheduler, kills, memory.

On one simulated field (``shearfit simulate``, preset ``small`` by default,
true PSF given so that every run does the same work):

1. throughput with 1 process, with a local Dask cluster of 2 workers
   (``-j 2``), and on an explicitly started LocalCluster through
   ``--scheduler ADDRESS``; scaling efficiency = rate(2) / (2 rate(1));
2. the run killed (SIGKILL) at three moments (after 1, 3 and 6 finished
   chunks), rerun to completion: the final catalogue against the
   uninterrupted one, and the work lost (objects measured twice);
3. peak memory (max RSS of the measuring process tree) for catalogues of
   10^3, 10^4 and 10^5 objects: the field's objects plus objects outside
   every exposure (they cost a catalogue row each), so the fitting work is
   the same and only the catalogue grows.

    python benchmarks/cluster_run.py
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np
from astropy.table import Table, vstack

from shearfit.simulate.field import simulate_field, simulation_config


# ``shearfit measure ARGS`` in a fresh interpreter
MEASURE = [sys.executable, "-c", "import sys; from shearfit.cli import main; sys.exit(main(sys.argv[1:]))",
           "measure"]


def run(args, env=None):
    """``shearfit measure ...`` in a fresh process: (wall seconds, max RSS MB of its process tree)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t0 = time.perf_counter()
    subprocess.run(MEASURE + args, check=True, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return wall, max(after, before) / 1024.0


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
    ap.add_argument("--chunk-size", type=int, default=32)
    ap.add_argument("--keep", default=None)
    args = ap.parse_args(argv)
    from dask.distributed import LocalCluster

    with tempfile.TemporaryDirectory() as tmp:
        d = args.keep or tmp
        os.makedirs(d, exist_ok=True)
        simulate_field(simulation_config({"preset": args.preset, "seed": args.seed}), d)
        cfg = os.path.join(d, "field_truepsf.yaml")
        cs = f"chunk_size={args.chunk_size}"
        n = len(Table.read(os.path.join(d, "objects.fits")))
        print(f"field: preset {args.preset}, {n} objects, chunks of {args.chunk_size}")

        ref = os.path.join(d, "ref.fits")
        t1, mem1 = run([cfg, cs, "--out", ref, "--quiet"])
        t2, _ = run([cfg, cs, "--out", os.path.join(d, "j2.fits"), "--quiet", "-j", "2"])
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cl:
            t3, _ = run([cfg, cs, "--out", os.path.join(d, "sched.fits"), "--quiet", "--scheduler",
                         cl.scheduler_address])
        reft = Table.read(ref)
        print("\n1. throughput (objects per second, the whole command):")
        print(f"   1 process:                           {n / t1:6.2f}  ({t1:.0f} s)")
        print(f"   -j 2 (local Dask cluster):            {n / t2:6.2f}  ({t2:.0f} s); scaling efficiency "
              f"{t1 / (2 * t2):.2f}; catalogue identical: {same(Table.read(os.path.join(d, 'j2.fits')), reft)}")
        print(f"   --scheduler {'(LocalCluster, 2 workers)':24s} {n / t3:6.2f}  ({t3:.0f} s); catalogue identical: "
              f"{same(Table.read(os.path.join(d, 'sched.fits')), reft)}")

        print("\n2. killed with SIGKILL, then rerun:")
        for k in (1, 3, 6):
            out = os.path.join(d, f"killed{k}.fits")
            done, t_kill = kill_after(cfg, out, k, args.chunk_size)
            t_rest, _ = run([cfg, cs, "--out", out, "--quiet"])
            ok = same(Table.read(out), reft)
            lost = t_kill + t_rest - t1
            print(f"   killed after {done} chunk(s) ({t_kill:.0f} s), resumed in {t_rest:.0f} s: identical {ok}; "
                  f"time lost {lost:+.0f} s (a chunk takes about {t1 * args.chunk_size / n:.0f} s)")

        print("\n3. peak memory (max RSS of the measuring process) against catalogue size, same fitting work:")
        cat = Table.read(os.path.join(d, "objects.fits"))
        rng = np.random.default_rng(0)
        for total in (1000, 10000, 100000):
            extra = max(total - len(cat), 0)
            far = Table({"id": np.arange(extra) + 10 ** 7, "ra": rng.uniform(100, 110, extra),
                         "dec": rng.uniform(30, 40, extra), "mag": np.full(extra, 23.0)})
            big = vstack([cat[["id", "ra", "dec", "mag"]], far])
            cpath = os.path.join(d, f"objects_{total}.fits")
            big.write(cpath, overwrite=True)
            out = os.path.join(d, f"mem_{total}.fits")
            wall, mem = run_isolated([cfg, f"catalog={cpath}", "--out", out, "--quiet"])
            print(f"   {len(big):7d} objects: {mem:6.0f} MB peak, {wall:.0f} s")
        print(f"   (the 1-process run of part 1: {mem1:.0f} MB)")


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

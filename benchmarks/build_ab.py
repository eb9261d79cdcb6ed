#!/usr/bin/env python
"""This checkout's engine against another build of shearfit, on the same galaxies.

A change to the engine is measured against the code before it, on a machine whose speed drifts by 10-30 %
from minute to minute: runs one after the other cannot tell a 10 % gain. This script installs nothing; give it
another build, installed apart, e.g.

    git worktree add /tmp/before <commit> && pip install --no-deps --target /tmp/before-pkg /tmp/before
    python benchmarks/build_ab.py --other /tmp/before-pkg

It simulates the realistic case of ``speed.py`` (7 exposures, each with its own Jacobian and elliptical Moffat
PSF, SNR 10-40) once and then

1. times ``measure_object`` on those galaxies in child processes, one of the other build and one of this
   checkout alternated ``--rounds`` times (galaxies per second per core, each round's ratio), and checks
   the estimates agree. Every round measures the same galaxies, each in a fresh process whose caches (the
   App. A Moffats, the alias tables) start empty, so no round finds the galaxies' work already done;
2. loads the other build's compiled module of the same instruction-set level into this process and times
   its ``make_bins`` against this one's on the bins of a few of the galaxies, interleaved (ns per mode and
   ellipticity), with the largest difference between their bins;
3. with ``--per-galaxy N``, times the two builds' compiled modules galaxy by galaxy in this process on N more
   galaxies, this checkout's Python around both (where only the compiled loops differ, the finer comparison).

With ``--paired N`` it does none of these but runs the two builds in two long-lived processes, each of N new
galaxies measured by one build and then the other (the order alternating), in CPU time: the comparison that a
machine's drift does not swamp, for changes to the Python as well as to the compiled loops.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import glob  # noqa: E402
import importlib.util  # noqa: E402
import pickle  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

import shearfit  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))

#: what each child process runs: the galaxies' fits, timed after two untimed ones
_CHILD = """
import pickle, sys, time
import numpy as np
import shearfit
objs = pickle.load(open(sys.argv[1], "rb"))
for o, t in objs[:2]:
    shearfit.measure_object(o, mag=t["mag"])
t0 = time.process_time()
res = [shearfit.measure_object(o, mag=t["mag"]) for o, t in objs[2:]]
dt = time.process_time() - t0
np.save(sys.argv[2], np.array([[r.e1, r.e2] for r in res], float))
print(len(res) / dt)
"""


#: a child of --paired: measures the galaxy whose index it reads on stdin and writes its CPU time and estimate
_PAIRED_CHILD = """
import pickle, sys, time
import shearfit
objs = pickle.load(open(sys.argv[1], "rb"))
for o, t in objs[:2]:
    shearfit.measure_object(o, mag=t["mag"])
print("ready", flush=True)
for line in sys.stdin:
    o, t = objs[int(line)]
    t0 = time.process_time()
    r = shearfit.measure_object(o, mag=t["mag"])
    print(repr(time.process_time() - t0), repr(r.e1), repr(r.e2), flush=True)
"""


def _env(other=None):
    env = dict(os.environ)
    if other:
        env["PYTHONPATH"] = other + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def paired_ab(pickled, n, other):
    """The two builds in two long-lived child processes, galaxy by galaxy: each galaxy (a new one each time) is
    measured by one build and then by the other, the order alternating, so both see the same moment of a machine
    whose speed drifts (CPU seconds, measured inside each child). Prints the ratio of their summed times, the
    median of the galaxies' ratios, the spread of the ratio over the halves and quarters of the galaxies, and
    the largest difference of the estimates."""
    procs = {name: subprocess.Popen([sys.executable, "-c", _PAIRED_CHILD, pickled], env=_env(o),
                                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                    cwd=tempfile.gettempdir())
             for name, o in (("other", other), ("this", None))}
    try:
        for p in procs.values():
            if p.stdout.readline().strip() != "ready":
                raise SystemExit("build_ab.py: error: a --paired child did not start")
        t = {"other": [], "this": []}
        de = 0.0
        for i in range(2, n):
            order = ("other", "this") if i % 2 else ("this", "other")
            got = {}
            for name in order:
                procs[name].stdin.write(f"{i}\n")
                procs[name].stdin.flush()
                got[name] = [float(v) for v in procs[name].stdout.readline().split()]
                t[name].append(got[name][0])
            d = np.abs(np.subtract(got["other"][1:], got["this"][1:]))
            if np.all(np.isfinite(d)):
                de = max(de, float(d.max()))
    finally:
        for p in procs.values():
            p.stdin.close()
            p.wait()
    a, b = np.array(t["other"]), np.array(t["this"])
    parts = [f"x{a[k].sum() / b[k].sum():.3f}" for m in (2, 4) for k in np.array_split(np.arange(a.size), m)]
    print(f"\n{a.size} galaxies, each measured by both builds in turn (two long-lived processes, the order "
          f"alternating; CPU time): other {1e3 * a.mean():.2f}, this {1e3 * b.mean():.2f} ms per galaxy, "
          f"x{a.sum() / b.sum():.3f} (the galaxies' median ratio x{np.median(a / b):.3f}; halves and quarters "
          f"{', '.join(parts)}); estimates differ by at most {de:.1e}")


def _child(pickled, out, other=None):
    got = subprocess.run([sys.executable, "-c", _CHILD, pickled, out], env=_env(other), capture_output=True, text=True,
                         check=True, cwd=tempfile.gettempdir())
    return float(got.stdout.strip().splitlines()[-1])


def _other_kernel(other):
    """The other build's compiled module of the level this process uses."""
    from shearfit.engine.likelihood import KERNEL

    name = KERNEL.__name__.rsplit(".", 1)[-1]
    found = glob.glob(os.path.join(other, "shearfit", "engine", f"{name}.*.so")) + \
        glob.glob(os.path.join(other, "shearfit", "engine", f"{name}.*.pyd"))
    if not found:
        raise SystemExit(f"build_ab.py: error: no {name} module under {other}/shearfit/engine")
    spec = importlib.util.spec_from_file_location(name, found[0])
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return KERNEL, mod


def kernel_ab(objs, other, rounds):
    from shearfit.engine import likelihood, sampling

    mine, theirs = _other_kernel(other)
    calls = []
    orig = sampling.mode_bins

    def capture(jm, e1, e2, bpo, **kw):
        calls.append((jm, np.array(e1, float), np.array(e2, float), int(bpo)))
        return orig(jm, e1, e2, bpo, **kw)

    sampling.mode_bins = capture
    try:
        for o, t in objs:
            shearfit.measure_object(o, mag=t["mag"])
    finally:
        sampling.mode_bins = orig
    args = []
    for jm, e1, e2, bpo in calls:
        shape = np.ascontiguousarray(np.stack(likelihood.shape_matrix(e1, e2), axis=1))
        b3, c8 = likelihood._packed_bins(jm)[:2]
        args.append((shape, b3, c8, bpo))
    n_mode_e = sum(a[0].shape[0] * a[1].shape[0] for a in args)
    worst, same_range = 0.0, True
    for a in args:
        lo1, off1, col1, _ = theirs.make_bins(*a)
        lo2, off2, col2, _ = mine.make_bins(*a)
        if lo1 != lo2 or off1 != off2:
            same_range = False
            continue
        c1, c2 = np.frombuffer(col1), np.frombuffer(col2)
        worst = max(worst, float(np.max(np.abs(c1 - c2)) / max(np.max(np.abs(c1)), 1e-300)))
    tot = {"other": 0.0, "this": 0.0}
    for _ in range(rounds):
        for name, mod in (("other", theirs), ("this", mine)):
            t0 = time.perf_counter()
            for a in args:
                mod.make_bins(*a)
            tot[name] += time.perf_counter() - t0
    print(f"\nmake_bins ({mine.__name__.rsplit('.', 1)[-1]}), the two builds interleaved in this process, {rounds} "
          f"rounds over the bins of {len(objs)} galaxies ({len(args)} calls): other "
          f"{1e9 * tot['other'] / rounds / n_mode_e:.2f}, this {1e9 * tot['this'] / rounds / n_mode_e:.2f} ns per "
          f"mode and ellipticity; bins differ by at most {worst:.1e} of the largest"
          f"{'' if same_range else ' (some ellipticities with other bin ranges, left out)'}")


class _Adapted:
    """Another build's compiled module, called with this checkout's arguments: the arguments a later build added
    at the end of a call (before its output buffer) are left out for a build that does not take them
    (binned_sums' pair_tol: such a build keeps every pair term, as pair_chi2_tolerance: 0 does)."""

    def __init__(self, mod):
        self._mod = mod

    def __getattr__(self, name):
        return getattr(self._mod, name)

    def binned_sums(self, *args):
        try:
            return self._mod.binned_sums(*args)
        except TypeError:
            return self._mod.binned_sums(*args[:-2], args[-1])


def per_galaxy_ab(objs, other):
    """This checkout's compiled loops against the other build's (the same level), galaxy by galaxy in this
    process with this checkout's Python around both (speed.py's ``alternate``: the order alternating, the App. A
    Moffat caches emptied before each fit), in CPU time: both see the same machine within a tenth of a second."""
    from speed import alternate, use_kernel

    mine, theirs = _other_kernel(other)
    theirs = _Adapted(theirs)

    def build(mod):
        def setup():
            use_kernel(mod)
            return None   # measure_object's default settings
        return setup

    try:
        t, de, n = alternate(objs, {"this": build(mine), "other": build(theirs)}, clock=time.process_time)
    finally:
        use_kernel(mine)
    print(f"\nthe compiled loops of the two builds, galaxy by galaxy in this process ({n} galaxies, this checkout's "
          f"Python): other {1e3 * t['other'] / n:.2f}, this {1e3 * t['this'] / n:.2f} CPU-ms per galaxy, "
          f"x{t['other'] / t['this']:.3f}; estimates differ by at most {de:.1e}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--other", required=True, help="directory holding the other build's shearfit package")
    ap.add_argument("--n-galaxies", type=int, default=60)
    ap.add_argument("--rounds", type=int, default=4, help="alternations of the two builds")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--paired", type=int, default=0, metavar="N",
                    help="instead of the rounds of child processes, N new galaxies each measured by both builds in "
                         "turn in two long-lived processes (the finer comparison where the machine's speed drifts)")
    ap.add_argument("--per-galaxy", type=int, default=0, metavar="N",
                    help="also time the two builds' compiled loops galaxy by galaxy in this process on N more "
                         "galaxies (this checkout's Python around both; finer than the child processes where only "
                         "the compiled loops differ)")
    args = ap.parse_args(argv)
    if not os.path.isdir(os.path.join(args.other, "shearfit")):
        raise SystemExit(f"build_ab.py: error: no shearfit package in {args.other}")
    sys.path.insert(0, HERE)
    from speed import cpu_name, simulate

    from shearfit.engine.kernel import kernel_info

    info = kernel_info()
    print(f"CPU: {cpu_name()}; inner loops: {info['path']} ({info['isa']}); other build: {args.other}")
    if args.paired:
        objs = simulate(args.paired + 2, 7, 48, args.seed, rotate=True, jitter=0.01)
        with tempfile.TemporaryDirectory() as tmp:
            pickled = os.path.join(tmp, "galaxies.pkl")
            with open(pickled, "wb") as f:
                pickle.dump(objs, f)
            paired_ab(pickled, len(objs), args.other)
        return
    objs = simulate(args.n_galaxies, 7, 48, args.seed, rotate=True, jitter=0.01)
    with tempfile.TemporaryDirectory() as tmp:
        pickled = os.path.join(tmp, "galaxies.pkl")
        with open(pickled, "wb") as f:
            pickle.dump(objs, f)
        print(f"{len(objs) - 2} galaxies of the realistic case (speed.py's), timed in child processes alternated:")
        ratios = []
        for k in range(args.rounds):
            a = _child(pickled, os.path.join(tmp, "other.npy"), args.other)
            b = _child(pickled, os.path.join(tmp, "this.npy"))
            ratios.append(b / a)
            print(f"  round {k + 1}: other {a:.2f}, this {b:.2f} galaxies / s / core (x{b / a:.2f})", flush=True)
        de = np.abs(np.load(os.path.join(tmp, "other.npy")) - np.load(os.path.join(tmp, "this.npy")))
        de = de[np.all(np.isfinite(de), axis=1)]
        print(f"  median x{np.median(ratios):.2f}; estimates differ by at most {de.max() if de.size else np.nan:.1e} "
              f"in e ({de.shape[0]} galaxies measured by both)")
    kernel_ab(objs[:12], args.other, args.rounds)
    if args.per_galaxy:
        per_galaxy_ab(simulate(args.per_galaxy, 7, 48, args.seed + 1, rotate=True, jitter=0.01), args.other)


if __name__ == "__main__":
    main()

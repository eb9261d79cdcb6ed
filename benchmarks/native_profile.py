#!/usr/bin/env python
"""Where the engine's time goes, sampled: the compiled loops against the Python and numpy around them, by stage.

``speed.py --kernel-times`` times each compiled call through a Python wrapper and takes the rest for Python; the
wrappers' own cost lands in the rest, and the rest's share by stage is then not where the Python is (session 83:
the sampler's chunks, credited 0.66 ms a galaxy of Python, held 0.1-0.3 ms; its store and refinement about
1.5 ms, not 0.87). This script samples instead. It simulates ``speed.py``'s realistic case (7 exposures, each
with its own Jacobian and elliptical Moffat PSF, SNR 10-40), measures the galaxies once untimed, then runs
``--passes`` passes over them in a child process under py-spy (``py-spy record --native``: Python and C frames
together; py-spy is not a dependency of shearfit, ``pip install py-spy``) and prints, as shares of the samples
taken inside ``measure_object``:

- the compiled loops (any frame of ``shearfit.engine._kernels*``) against the rest (Python, numpy, scipy, libm
  called from Python), by stage of the fit (the function ``_measure`` called);
- the rest by the innermost line of shearfit it was spent under (``--lines`` of them).

The first build of the profiles' tables (``fast_pair``) is left out. Shares carry the sampling error of their
counts (about sqrt(n) / N).

    python benchmarks/native_profile.py                       # 80 galaxies, 6 passes
    SHEARFIT_ISA=avx2 python benchmarks/native_profile.py --lines 40
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import collections  # noqa: E402
import pickle  # noqa: E402
import re  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402

_CHILD = """
import pickle, sys
import shearfit
objs = pickle.load(open(sys.argv[1], "rb"))
cfg = shearfit.FitConfig()
for o, t in objs:
    shearfit.measure_object(o, mag=t["mag"], config=cfg)
for _ in range(int(sys.argv[2])):
    for o, t in objs:
        shearfit.measure_object(o, mag=t["mag"], config=cfg)
"""

_PY_FRAME = re.compile(r"\((.*\.py):(\d+)\)")


def aggregate(raw_lines, n_lines=25):
    """(total samples, compiled share, {stage: (rest, compiled)}, [(line, rest share)]) of py-spy's raw output."""
    total = 0
    rest = collections.Counter()
    kern = collections.Counter()
    by_line = collections.Counter()
    for line in raw_lines:
        line = line.strip()
        if not line:
            continue
        stack, n = line.rsplit(" ", 1)
        n = int(n)
        frames = stack.split(";")
        if not any(f.startswith("measure_object ") for f in frames) or any(f.startswith("fast_pair ") for f in frames):
            continue
        total += n
        py = [i for i, f in enumerate(frames) if _PY_FRAME.search(f)]
        native = frames[py[-1] + 1:] if py else frames
        ours = [re.sub(r" \(.*/", " (", frames[i]) for i in py if "shearfit" in frames[i]]
        names = [f.split(" (")[0] for f in ours]
        stage = "(outside _measure)"
        if "_measure" in names:
            i = names.index("_measure")
            stage = names[i + 1] if i + 1 < len(names) else "_measure"
        if any("_kernels" in f for f in native):
            kern[stage] += n
        else:
            rest[stage] += n
            if ours:
                by_line[ours[-1]] += n
    stages = {s: (rest[s], kern[s]) for s in set(rest) | set(kern)}
    return total, sum(kern.values()), stages, by_line.most_common(n_lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n-galaxies", type=int, default=80)
    ap.add_argument("--passes", type=int, default=6)
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--rate", type=int, default=500, help="py-spy's samples per second")
    ap.add_argument("--lines", type=int, default=25, help="lines of shearfit listed by their share of the rest")
    args = ap.parse_args(argv)
    spy = shutil.which("py-spy")
    if spy is None:
        sys.exit("native_profile.py: py-spy is not installed (pip install py-spy)")
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import speed

    objs = speed.simulate(args.n_galaxies, 7, 48, args.seed, rotate=True, jitter=0.01)
    print(f"CPU: {speed.cpu_name()}; SHEARFIT_ISA={os.environ.get('SHEARFIT_ISA', '(native)')}")
    with tempfile.TemporaryDirectory() as tmp:
        gal, child, raw = (os.path.join(tmp, n) for n in ("galaxies.pkl", "child.py", "raw.txt"))
        with open(gal, "wb") as f:
            pickle.dump(objs, f)
        with open(child, "w") as f:
            f.write(_CHILD)
        subprocess.run([spy, "record", "-r", str(args.rate), "-f", "raw", "-o", raw, "--native", "--",
                        sys.executable, child, gal, str(args.passes)], check=True, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL)
        with open(raw) as f:
            total, compiled, stages, lines = aggregate(f, args.lines)
    if total == 0:
        sys.exit("native_profile.py: py-spy took no sample inside measure_object")
    print(f"{args.n_galaxies} galaxies x {args.passes} passes (after an untimed one); {total} samples inside "
          f"measure_object: compiled loops {compiled / total:.1%}, the rest {1 - compiled / total:.1%}")
    print("by stage of the fit (share of all samples): the rest, the compiled loops")
    for s, (r, k) in sorted(stages.items(), key=lambda x: -x[1][0]):
        if r + k >= 0.002 * total:
            print(f"  {s:34s} {r / total:6.1%} {k / total:6.1%}")
    print("the rest by the innermost line of shearfit it was spent under:")
    for name, n in lines:
        print(f"  {name:72s} {n / total:6.2%}")


if __name__ == "__main__":
    main()

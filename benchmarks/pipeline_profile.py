#!/usr/bin/env python
"""Throughput of ``shearfit measure`` against the engine's, and where the difference goes (issue 3, item 5).

Simulates a field with ``shearfit.simulate`` (preset ``small`` by default:
7 exposures of 2 CCDs, stars, bad columns and cosmic rays), runs the field
pipeline on one process under the profiler, and prints objects per second
for the whole command and for ``measure_object`` alone, then the time of
each pipeline stage. With ``--psf fitted`` the PSF models are fitted from the
stars first (their time is a stage too).

    python benchmarks/pipeline_profile.py                   # true PSF given
    python benchmarks/pipeline_profile.py --psf fitted      # PSF fitted from the field's stars
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import cProfile  # noqa: E402
import pstats  # noqa: E402
import resource  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from shearfit.io.fieldconfig import load_field_config  # noqa: E402
from shearfit.pipeline.driver import measure_field  # noqa: E402
from shearfit.simulate.field import simulate_field, simulation_config  # noqa: E402

# (label, file suffix, function): cumulative time of each
STAGES = [
    ("read exposures and weights (FITS)", "field/io.py", "read_exposure"),
    ("read the catalogue", "field/io.py", "read_catalog"),
    ("fit PSF models from stars", "field/pipeline.py", "fit_exposure_psf"),
    ("locate objects on CCDs (WCS)", "field/stamps.py", "locate_all"),
    ("cut stamps", "field/stamps.py", "cut_stamp"),
    ("local WCS Jacobians", "field/wcs.py", "local_jacobian"),
    ("PSF at the object", "field/pipeline.py", "at"),
    ("PSF adaptive moments (FWHM, psf_e)", "field/pipeline.py", "psf_moments"),
    ("above-Nyquist Moffat per CCD", "field/pipeline.py", "moffat"),
    ("isophotes, neighbours, blends (sec. 3.6)", "field/pipeline.py", "_isophote_analysis"),
    ("the engine: measure_object", "shearfit/measure.py", "measure_object"),
    ("write the catalogue", "field/io.py", "write_catalog_atomic"),
]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="small")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--psf", choices=["true", "fitted"], default="true")
    ap.add_argument("--keep", default=None, help="keep the field in this directory")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        d = args.keep or tmp
        sc = simulation_config({"preset": args.preset, "seed": args.seed})
        t0 = time.perf_counter()
        info = simulate_field(sc, d)
        print(f"simulated preset {args.preset} in {time.perf_counter() - t0:.0f} s")
        cfg = load_field_config(os.path.join(d, "field_truepsf.yaml" if args.psf == "true" else "field.yaml"))
        prof = cProfile.Profile()
        t0 = time.perf_counter()
        prof.enable()
        table = measure_field(cfg, out_path=os.path.join(d, "shear.fits"), processes=1)
        prof.disable()
        wall = time.perf_counter() - t0
    del info
    st = pstats.Stats(prof).stats
    total = sum(v[2] for v in st.values())

    def cum(fname, func):
        return sum(v[3] for k, v in st.items() if k[0].endswith(fname) and k[2] == func)

    n = len(table)
    fc = np.asarray(table["fitclass"])
    engine = cum("shearfit/measure.py", "measure_object")
    print(f"\n{n} objects ({int((fc == 0).sum())} galaxies, {int((fc == 1).sum())} stars, {int((fc < 0).sum())} "
          f"flagged or unmeasured), {len(cfg.exposures)} exposures, PSF {args.psf}, one process:")
    print(f"  whole command: {n / wall:.2f} objects/s/core ({wall:.1f} s wall, profiled)")
    print(f"  engine alone:  {n / engine:.2f} objects/s/core over the same objects "
          f"(measure_object: {engine:.1f} s, {100 * engine / total:.0f} % of the profiled time)")
    print(f"\n  where the time goes (cumulative, % of {total:.1f} s profiled):")
    for label, fname, func in STAGES:
        t = cum(fname, func)
        if t > 0:
            print(f"    {label:44s} {t:7.2f} s  {100 * t / total:5.1f} %")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"\npeak memory (max RSS of this process): {peak:.0f} MB")


if __name__ == "__main__":
    main()

#!/usr/bin/env python
"""Throughput of ``shearfit measure`` against the engine's, and where the difference goes.

Simulates a field with ``shearfit.simulate`` (preset ``small`` by default:
7 dithered exposures of 2 CCDs, each with its own PSF, stars, bad columns and
cosmic rays), runs the field pipeline on one process (``-j 1``), once with
the true PSF images given and once with PSF models fitted from the stars, and
prints objects per CPU-second of each, the Fourier modes the engine sums per
fit (and how many are linked into fold groups), the share of the PSF stage,
and the peak memory; then, under the profiler, the time of each pipeline stage and of
``measure_object`` alone.

    python benchmarks/pipeline_profile.py                   # given and fitted PSFs, then the profile
    python benchmarks/pipeline_profile.py --psf fitted      # only PSF models fitted from the stars
    python benchmarks/pipeline_profile.py --keep A          # at one commit, then at another:
    python benchmarks/pipeline_profile.py --compare-with A  # how far the catalogues moved
    python benchmarks/pipeline_profile.py --no-profile --psf true --stage-clock   # the pipeline's stages, timed directly
    python benchmarks/pipeline_profile.py --no-profile --psf true --pairs 1 --metacal 3   # metacal's cost per object
                                                          # (whole runs alternated, then each object both ways in turn)
    python benchmarks/pipeline_profile.py --no-profile --psf true --pairs 1 --metacal 3 --metacal-psf fitted   # with the
                                                          # PSF models fitted from the stars (each object its own)
    python benchmarks/pipeline_profile.py --no-profile --psf true --pairs 1 --isophotes   # sec. 3.6, compiled vs numpy
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import cProfile  # noqa: E402
import pstats  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import yaml  # noqa: E402

from shearfit.io.fieldconfig import load_field_config  # noqa: E402
from shearfit.pipeline.driver import measure_field  # noqa: E402
from shearfit.simulate.field import simulate_field, simulation_config  # noqa: E402

# (label, file suffix, function): cumulative time of each
STAGES = [
    ("read exposures and weights (FITS)", "io/fits.py", "read_exposure"),
    ("read the catalogue", "io/fits.py", "read_catalog"),
    ("fit PSF models from stars", "pipeline/driver.py", "fit_exposure_psf"),
    ("locate objects on CCDs (WCS)", "io/stamps.py", "locate_all"),
    ("cut stamps", "io/stamps.py", "cut_stamp"),
    ("local WCS Jacobians", "io/wcs.py", "local_jacobian"),
    ("PSF at the object", "pipeline/driver.py", "at"),
    ("PSF adaptive moments (FWHM, psf_e)", "pipeline/driver.py", "moments_at"),
    ("PSF moments from the per-CCD grid", "pipeline/driver.py", "moments_many"),
    ("above-Nyquist Moffat per CCD", "pipeline/driver.py", "moffat"),
    ("isophotes, neighbours, blends (sec. 3.6)", "pipeline/driver.py", "_isophote_analysis"),
    ("the engine: measure_object", "engine/measure.py", "measure_object"),
    ("write the catalogue", "io/fits.py", "write_catalog_atomic"),
]


class _ModeCounter:
    """Per fit, the Fourier modes the engine sums, those of them in fold groups (aliases of one sampled mode,
    App. A) and the groups' cross terms, counted where the engine packs them for binning; and the modes by
    their wavenumber in radians per pixel (|K| times the pixel scale), where fitted PSF models keep more of them
    than true PSF images do."""

    K_EDGES = (0.0, 2.0, 2.5, 3.0, 3.5, np.inf)

    def __enter__(self):
        import shearfit.engine.likelihood as lik

        self.lik, self.orig, self.rows, self.bands = lik, lik._packed_bins, [], []

        def counted(jm):
            fresh = getattr(jm, "_bins32", None) is None
            out = self.orig(jm)
            if fresh:
                self.rows.append((out[0].shape[0], jm.multi.size, out[3].size))
                self.bands.append(np.histogram(np.hypot(jm.kx, jm.ky) * jm.pixel_scale, self.K_EDGES)[0])
            return out

        lik._packed_bins = counted
        return self

    def __exit__(self, *exc):
        self.lik._packed_bins = self.orig

    def summary(self):
        if not self.rows:
            return "no fits"
        med = np.median(np.array(self.rows), axis=0)
        mean = np.mean(np.array(self.bands), axis=0)
        edges = self.K_EDGES
        bands = ", ".join(f"{lo:g}-{hi:g}: {m:.0f}" if np.isfinite(hi) else f">= {lo:g}: {m:.0f}"
                          for lo, hi, m in zip(edges[:-1], edges[1:], mean))
        return (f"Fourier modes per fit, median {med[0]:.0f}, of which {med[1]:.0f} in fold groups with {med[2]:.0f} "
                f"cross terms ({len(self.rows)} fits); mean per fit by wavenumber (radians per pixel) {bands}")


class _CpuClock:
    """CPU seconds spent inside some functions during an unprofiled run (nested calls among them counted once),
    without the profiler's cost per Python call, which inflates the pipeline's many small calls more than the
    engine's compiled loops. ``targets()`` names them as (owner, attribute name) pairs, patched while the clock
    runs."""

    def targets(self):
        raise NotImplementedError

    def __enter__(self):
        self.cpu, self.depth, self.saved = 0.0, 0, []

        def timed(orig):
            def call(*a, **k):
                if self.depth:
                    return orig(*a, **k)
                self.depth += 1
                c0 = time.process_time()
                try:
                    return orig(*a, **k)
                finally:
                    self.cpu += time.process_time() - c0
                    self.depth -= 1
            return call

        for owner, name in self.targets():
            orig = getattr(owner, name)
            self.saved.append((owner, name, orig))
            setattr(owner, name, timed(orig))
        return self

    def __exit__(self, *exc):
        for owner, name, orig in reversed(self.saved):
            setattr(owner, name, orig)


class _EngineClock(_CpuClock):
    """The engine (``measure_object``, as the pipeline's driver calls it): the pipeline's own share of a run."""

    def targets(self):
        import shearfit.pipeline.driver as drv

        return [(drv, "measure_object")]


class _PsfClock(_CpuClock):
    """The PSF itself, timed directly: reading given PSF files, selecting stars and fitting the models
    (``fit_exposure_psf``), the model's image, registration shift and above-Nyquist Moffat at each object
    (``_ExposurePSF`` and ``_chunk_geometry``'s batches), and the PSF's adaptive moments for each object's PSF
    columns. What a model that varies across the field makes the engine do per object (its own modes and alias
    tables, counted in the engine's time) is not in it: that is the difference between the fitted and the given
    runs' engine time."""

    def targets(self):
        import shearfit.pipeline.driver as drv

        return [(drv, "_load_psf"), (drv, "fit_exposure_psf"), (drv, "psf_moments"),
                (drv._ExposurePSF, "at"), (drv._ExposurePSF, "fitted_at_many"), (drv._ExposurePSF, "moffat"),
                (drv._ExposurePSF, "shift"), (drv._ExposurePSF, "model_uv"), (drv._ExposurePSF, "sigma_guess"),
                (drv._ExposurePSF, "moments_at"), (drv._ExposurePSF, "moments_many")]


#: the pipeline's own stages timed directly by ``--stage-clock`` (label, attribute of shearfit.pipeline.driver or of
#: its _ExposurePSF, name): each call's CPU time, the calls it makes included, as a share of the engine's time
CLOCKED_STAGES = [
    ("isophotes, neighbours, blends (sec. 3.6)", "driver", "_isophote_analysis"),
    ("cut stamps (memory-mapped pages)", "driver", "cut_stamp"),
    ("read exposures and weights (FITS, WCS)", "driver", "_read_exposures"),
    ("memory maps and WCS per chunk", "driver", "_attached"),
    ("chunk geometry (Jacobians, PSF per CCD)", "driver", "_chunk_geometry"),
    ("Observations (checks, read-only copies)", "driver", "Observation"),
    ("object memory estimate", "driver", "object_memory_bytes"),
    ("PSF moments at the object", "_ExposurePSF", "moments_at"),
    ("PSF ellipticity at the object", "driver", "psf_ellipticity"),
    ("catalogue neighbours (k-d trees)", "driver", "catalogue_neighbours"),
    ("checkpoint (each chunk written)", "driver", "_store_chunk"),
    ("write the catalogue", "driver", "write_catalog_atomic"),
]


class _AttrClock(_CpuClock):
    """One attribute's calls (``owner.name``), timed."""

    def __init__(self, owner, name):
        self.owner, self.name = owner, name

    def targets(self):
        return [(self.owner, self.name)]


def _stage_clock_run(cfg, out_path):
    """One run of ``measure_field`` with the engine and each of CLOCKED_STAGES timed around its calls (CPU time,
    no profiler): (total CPU, engine CPU, [(label, CPU), ...])."""
    import shearfit.pipeline.driver as drv

    clocks = [(label, _AttrClock(drv if where == "driver" else getattr(drv, where), name))
              for label, where, name in CLOCKED_STAGES]
    _forget_psfs()
    c0 = _cpu_seconds()
    with contextlib.ExitStack() as stack:
        engine = stack.enter_context(_EngineClock())
        for _, clock in clocks:
            stack.enter_context(clock)
        measure_field(cfg, out_path=out_path, processes=1)
    return _cpu_seconds() - c0, engine.cpu, [(label, clock.cpu) for label, clock in clocks]


def _metacal_pairs(d, settings, n_pairs, psf="true"):
    """``calibration: metacal`` against the plain run, on the given PSF images (``psf`` 'true') or the PSF models
    fitted from the stars ('fitted': each object its own PSF image at the stamp's pixels), ``n_pairs`` times
    alternated in this warm process (its imports and one-off tables excluded, which a whole command's CPU time
    would share between the two and so understate the ratio): CPU seconds of ``measure_field`` each, per object,
    and their ratio."""
    from dataclasses import replace

    cfg = _with_settings(load_field_config(os.path.join(d, "field_truepsf.yaml" if psf == "true" else "field.yaml")),
                         settings)
    what = "PSF images given" if psf == "true" else "PSF models fitted from the stars"
    print(f"\ncalibration: metacal against the plain run ({what}), {n_pairs} pairs alternated, CPU of "
          "measure_field in this process:")
    ratios, by_class = [], {}
    for k in range(max(n_pairs, 1)):
        cpu, rows = {}, {}
        for mode in ("plain", "metacal"):
            run = cfg if mode == "plain" else replace(cfg, calibration="metacal")
            _forget_psfs()
            c0 = _cpu_seconds()
            with _object_clock() as rows[mode]:
                table = measure_field(run, out_path=os.path.join(d, f"shear_{mode}_pair.fits"), processes=1)
            cpu[mode] = _cpu_seconds() - c0
        ratios.append(cpu["metacal"] / cpu["plain"])
        print(f"  pair {k + 1}: plain {1e3 * cpu['plain'] / len(table):.1f} ms, metacal "
              f"{1e3 * cpu['metacal'] / len(table):.1f} ms an object ({len(table)} objects): **x{ratios[-1]:.2f}**")
        # per class of the plain run's fit (the objects measured in the same order both times)
        cls = np.array([c for c, _ in rows["plain"]])
        tp, tm = np.array([t for _, t in rows["plain"]]), np.array([t for _, t in rows["metacal"]])
        for name, sel in (("galaxies", cls == 0), ("stars", cls == 1),
                          ("flagged (blended, off-centre, too large, ...)", cls < 0)):
            if sel.any() and tm.size == tp.size:
                by_class.setdefault(name, []).append((int(sel.sum()), tp[sel].mean(), tm[sel].mean()))
    print(f"  median x{float(np.median(ratios)):.2f} ({', '.join(f'{r:.2f}' for r in ratios)})")
    print("  per object of the plain run's class (each object's own measurement, timed around it):")
    for name, got in by_class.items():
        r = [m / p for _, p, m in got]
        print(f"    {name} ({got[0][0]}): plain {1e3 * np.median([p for _, p, _ in got]):.1f} ms, metacal "
              f"{1e3 * np.median([m for _, _, m in got]):.1f} ms: median x{float(np.median(r)):.2f} "
              f"({', '.join(f'{x:.2f}' for x in r)})")
    _metacal_interleaved(cfg, n_pairs, os.path.join(d, "shear_metacal_pair.fits"))


#: the plain fit's SNR bins of :func:`_metacal_interleaved`'s galaxies
_SNR_BINS = ((0.0, 10.0), (10.0, 15.0), (15.0, 20.0), (20.0, 30.0), (30.0, np.inf))


def _metacal_interleaved(cfg, n_runs, metacal_path):
    """Metacal's cost per object with the plain and the metacal measurement of each object made one after the
    other (their order alternating from object to object), so that the machine's drift over a run, which moves
    whole runs by 10-30 %, meets both alike: ``n_runs`` runs of ``calibration: metacal`` whose driver measures
    every object both ways (``_measure_one`` wrapped) and writes the metacal rows. Prints, per class of the
    plain fit and over all objects, the ratio of the summed CPU times (metacal's cost per object over the plain
    one's) with its bootstrap error over the objects, and checks that the catalogue is the metacal run's; and the
    galaxies' ratio in bins of the plain fit's SNR (why it falls with SNR: ``benchmarks/README.md``, session 96)."""
    from dataclasses import replace

    from astropy.table import Table

    run = replace(cfg, calibration="metacal")
    print(f"\ncalibration: metacal against the plain run, each object measured both ways in turn (order alternating), "
          f"{n_runs} runs; CPU seconds of the driver's measurement of each object (stamps, PSF at the object, fits):")
    per_class = {}
    rng = np.random.default_rng(0)
    for k in range(max(n_runs, 1)):
        _forget_psfs()
        out = metacal_path.replace(".fits", "_interleaved.fits")
        with _interleaved_clock(cfg) as rows:
            table = measure_field(run, out_path=out, processes=1)
        same = _same_table(Table.read(metacal_path), Table.read(out)) if os.path.exists(metacal_path) else None
        cls, tp, tm, snr = (np.array(col) for col in zip(*rows)) if rows else (np.zeros(0),) * 4
        gal = cls == 0
        parts = []
        bins = [("all objects", np.ones(cls.size, bool)), ("galaxies", gal), ("stars", cls == 1), ("flagged", cls < 0)]
        bins += [(f"galaxies of SNR {lo:g}-{hi:g}" if hi < np.inf else f"galaxies of SNR {lo:g}+",
                  gal & (snr >= lo) & (snr < hi)) for lo, hi in _SNR_BINS]
        for name, sel in bins:
            if not sel.any():
                continue
            p, m = tp[sel], tm[sel]
            boot = [m[i].sum() / p[i].sum() for i in rng.integers(0, p.size, (400, p.size))]
            ratio = m.sum() / p.sum()
            per_class.setdefault(name, []).append(ratio)
            parts.append(f"{name} ({int(sel.sum())}): plain {1e3 * p.mean():.1f} ms, metacal {1e3 * m.mean():.1f} ms, "
                         f"**x{ratio:.2f}** +- {np.std(boot):.2f}")
        check = "" if same is None else ", the catalogue " + ("identical to" if same else "DIFFERS from") + " the metacal run"
        print(f"  run {k + 1} ({len(table)} rows{check}):")
        for line in parts:
            print(f"    {line}")
    print("  median over runs: " + "; ".join(f"{name} x{float(np.median(r)):.2f}" for name, r in per_class.items()))


def _same_table(a, b):
    """Whether two catalogues hold the same columns with the same values (NaN equal to NaN)."""
    if a.colnames != b.colnames or len(a) != len(b):
        return False
    for c in a.colnames:
        x, y = np.asarray(a[c]), np.asarray(b[c])
        if x.dtype.kind == "f":
            if not np.array_equal(x, y, equal_nan=True):
                return False
        elif not np.array_equal(x, y):
            return False
    return True


@contextlib.contextmanager
def _interleaved_clock(cfg):
    """[(plain fitclass, plain CPU s, metacal CPU s, plain SNR)] of each object the driver measures while in the
    block: its ``_measure_one`` wrapped to measure the object with ``cfg`` (the plain run) and as the run asks
    (metacal), in turn, the first of the two alternating from object to object; the run's own row is returned."""
    import shearfit.pipeline.driver as drv

    rows, real = [], drv._measure_one

    def both(hits, exposures, mag, run_cfg, *args, **kwargs):
        got, cpu = {}, {}
        order = ((cfg, "plain"), (run_cfg, "metacal"))
        for c, mode in (order if len(rows) % 2 == 0 else order[::-1]):
            t0 = time.process_time()
            got[mode] = real(hits, exposures, mag, c, *args, **kwargs)
            cpu[mode] = time.process_time() - t0
        rows.append((int(got["plain"].get("fitclass", -99)), cpu["plain"], cpu["metacal"],
                     float(got["plain"].get("snr", np.nan))))
        return got["metacal"]

    drv._measure_one = both
    try:
        yield rows
    finally:
        drv._measure_one = real


@contextlib.contextmanager
def _object_clock():
    """[(fitclass, CPU seconds)] of each object the driver measures while in the block (its ``_measure_one``
    wrapped)."""
    import shearfit.pipeline.driver as drv

    rows, real = [], drv._measure_one

    def timed(*args, **kwargs):
        t0 = time.process_time()
        row = real(*args, **kwargs)
        rows.append((int(row.get("fitclass", -99)), time.process_time() - t0))
        return row

    drv._measure_one = timed
    try:
        yield rows
    finally:
        drv._measure_one = real


def _isophote_loop(d, settings, n_objects=200, loops=5):
    """The isophote analysis (sec. 3.6, ``driver._isophote_analysis``) of the first ``n_objects`` objects of a run
    with the PSF images given, their inputs captured as the pipeline made them, then timed in a loop: with the
    compiled loops and with their numpy and scipy lines (``USE_KERNEL`` off in ``pipeline.blends`` and the
    driver's maps), CPU time per object (the least of ``loops`` passes, the machine's drift aside), and whether
    every flag, kept exposure and weight is the same both ways."""
    import shearfit.pipeline.blends as blends
    import shearfit.pipeline.driver as drv

    cfg = _with_settings(load_field_config(os.path.join(d, "field_truepsf.yaml")), settings)
    captured = []
    orig = drv._isophote_analysis

    def capture(cuts, pc, near=()):
        if len(captured) < n_objects:
            # (a shallow copy: the stamps are read-only and the analysis puts new weights in the dicts it is given)
            captured.append(([dict(c) for c in cuts], pc, near))
        return orig(cuts, pc, near)

    drv._isophote_analysis = capture
    try:
        _forget_psfs()
        measure_field(cfg, out_path=os.path.join(d, "shear_isophotes.fits"), processes=1)
    finally:
        drv._isophote_analysis = orig

    def one_pass():
        out = []
        for cuts, pc, near in captured:
            cc = [dict(c) for c in cuts]
            out.append((orig(cc, pc, near), [(c.get("keep"), c["weight"]) for c in cc]))
        return out

    def timed():
        one_pass()
        best = np.inf
        for _ in range(max(loops, 1)):
            c0 = _cpu_seconds()
            one_pass()
            best = min(best, _cpu_seconds() - c0)
        return best / max(len(captured), 1), one_pass()

    compiled, got = timed()
    saved = blends.USE_KERNEL, drv.USE_KERNEL
    blends.USE_KERNEL = drv.USE_KERNEL = False
    try:
        reference, ref = timed()
    finally:
        blends.USE_KERNEL, drv.USE_KERNEL = saved
    same = all(a[0] == b[0] and all(ka == kb and np.array_equal(wa, wb) for (ka, wa), (kb, wb) in zip(a[1], b[1]))
               for a, b in zip(got, ref))
    print(f"\nisophote analysis (sec. 3.6) of {len(captured)} objects as the pipeline cut them, CPU per object, least "
          f"of {loops} loops: compiled {1e3 * compiled:.3f} ms, numpy and scipy lines {1e3 * reference:.3f} ms "
          f"(x{reference / compiled:.2f}); flags, kept exposures and weights "
          f"{'identical' if same else 'DIFFERENT'}")


def _with_settings(cfg, items):
    """The field config with KEY=VALUE settings of the engine (cfg.fit) or the pipeline (cfg.pipeline)."""
    from dataclasses import replace

    from shearfit.config import settings_from_items

    for key, value in settings_from_items(items).items():
        if hasattr(cfg.fit, key):
            cfg = replace(cfg, fit=replace(cfg.fit, **{key: value}))
        elif hasattr(cfg.pipeline, key):
            cfg = replace(cfg, pipeline=replace(cfg.pipeline, **{key: value}))
        else:
            raise SystemExit(f"pipeline_profile.py: error: no setting {key!r}")
    return cfg


def _forget_psfs():
    """Empty what the pipeline and the engine remember by PSF image or Moffat (each image's adaptive moments,
    fine modes and Moffat, each Moffat's alias tables), so that every run pays for its PSFs as a fresh
    ``shearfit measure`` process does, instead of reusing the first run's: the same field's PSF images are
    the same arrays' contents run after run (and a later run's new arrays of the same contents would find the
    first run's entries only by comparing contents, at every object)."""
    import shearfit.engine.model as model
    import shearfit.pipeline.driver as drv

    drv._PSF_MOMENTS.clear()
    model._FINE_PSF.clear()
    model._OWN_MOFFAT.clear()
    model._moffat_aliases.cache_clear()
    mc = sys.modules.get("shearfit.calib.metacal")
    if mc is not None:   # metacal's dilated PSFs and PSF tables (held by the PSF images' contents)
        mc._DILATED.clear()
        mc._PSF_TABLES.clear()


def _cpu_seconds():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _runs(d, settings, modes, tag, queue):
    """A child process's runs of the PSF modes in ``modes``, one after the other: (tag, mode, CPU seconds,
    objects) of each into ``queue``."""
    for mode in modes:
        cfg = _with_settings(load_field_config(os.path.join(d, "field_truepsf.yaml" if mode == "true"
                                                            else "field.yaml")), settings)
        _forget_psfs()
        c0 = _cpu_seconds()
        table = measure_field(cfg, out_path=os.path.join(d, f"shear_{mode}_{tag}.fits"), processes=1)
        queue.put((tag, mode, _cpu_seconds() - c0, len(table)))


def _simultaneous_pairs(d, settings, n_pairs):
    """Two processes side by side (forked from this warm process), one core each, n_pairs times: one runs the
    given-PSF field then the fitted-PSF one, the other the reverse, so that each mode meets the same load from
    the rest of the machine and from the other process (on a machine whose two cores share one physical
    core, a process alone runs faster than two side by side: the order is swapped so that neither mode has
    the machine to itself more than the other)."""
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    shares, rates = [], {"true": [], "fitted": []}
    print(f"\n{n_pairs} pairs of processes side by side (given then fitted, and fitted then given):")
    for k in range(n_pairs):
        queue = ctx.Queue()
        procs = [ctx.Process(target=_runs, args=(d, settings, order, tag, queue))
                 for tag, order in (("a", ("true", "fitted")), ("b", ("fitted", "true")))]
        for p in procs:
            p.start()
        got = [queue.get() for _ in range(4)]
        for p in procs:
            p.join()
        n = got[0][3]
        cpu = {m: sum(c for _, mm, c, _ in got if mm == m) for m in ("true", "fitted")}
        rates["true"].append(2 * n / cpu["true"])
        rates["fitted"].append(2 * n / cpu["fitted"])
        shares.append(100 * (cpu["fitted"] - cpu["true"]) / cpu["fitted"])
        print(f"  pair {k + 1}: given {rates['true'][-1]:.2f}, fitted {rates['fitted'][-1]:.2f} objects per "
              f"CPU-second (two runs each, side by side); PSF stage {shares[-1]:.0f} % of the fitted runs", flush=True)
    print(f"  median: given {np.median(rates['true']):.2f}, fitted {np.median(rates['fitted']):.2f} objects per "
          f"CPU-second; **PSF stage {np.median(shares):.0f} %** of the fitted runs (pairs "
          f"{', '.join(f'{x:.0f}' for x in shares)} %)")
    if len(shares) > 1:
        # the pairs scatter by several per cent with the machine's load: their mean and its standard error
        # say how far the PSF stage is known
        print(f"  mean over the pairs: PSF stage {np.mean(shares):.1f} +- "
              f"{np.std(shares, ddof=1) / np.sqrt(len(shares)):.1f} % of the fitted runs")


def _warm_up():
    """Fit one small simulated galaxy and take one PSF's adaptive moments: the tables and imports any run needs."""
    import shearfit
    from shearfit.pipeline.driver import psf_moments
    from shearfit.simulate import ring_set

    objs = ring_set(1, (0.0, 0.0), np.random.default_rng(0), n_rotations=1, n_exposures=2, snr_range=(20, 30),
                    mag_range=(22.0, 23.0), stamp_size=32)
    obs, truth = objs[0]
    shearfit.measure_object(obs, mag=truth["mag"])
    psf_moments(np.array(obs[0].psf, float))


def _compare_catalogues(before, after, mode):
    """How far the ellipticities and weights of catalogue ``after`` moved from ``before`` (the same objects)."""
    from astropy.table import Table

    label = "given" if mode == "true" else "fitted"
    if not os.path.exists(before):
        print(f"\nPSF {label}: no {before} to compare with")
        return
    a, b = Table.read(before), Table.read(after)
    if len(a) != len(b) or not np.array_equal(np.asarray(a["id"]), np.asarray(b["id"])):
        print(f"\nPSF {label}: {before} holds other objects; not compared")
        return
    de = np.hypot(np.asarray(a["e1"], float) - np.asarray(b["e1"], float),
                  np.asarray(a["e2"], float) - np.asarray(b["e2"], float))
    both = np.isfinite(de)
    de = de[both]
    dw = np.abs(np.asarray(a["weight"], float) - np.asarray(b["weight"], float))[both]
    err = np.sqrt(np.asarray(a["e_var"], float))[both]
    rel = de[err > 0] / err[err > 0]
    flips = int(np.sum(np.asarray(a["fitclass"]) != np.asarray(b["fitclass"])))
    print(f"\nPSF {label}, against {before}: {de.size} objects measured in both; |delta e| at most "
          f"{de.max() if de.size else 0:.2e} (at most {rel.max() if rel.size else 0:.1e} of the error on e); "
          f"more than 1e-7, 1e-5, 1e-4: {int(np.sum(de > 1e-7))}, {int(np.sum(de > 1e-5))}, {int(np.sum(de > 1e-4))}; "
          f"weight at most {dw.max() if dw.size else 0:.2e} apart; fitclass changed for {flips}")
    # the PSF's adaptive moments at the objects (psf_e1, psf_e2, psf_fwhm), e.g. against a psf_moment_grid=0 run
    dp = [np.abs(np.asarray(a[c], float) - np.asarray(b[c], float)) for c in ("psf_e1", "psf_e2")]
    dp.append(np.abs(np.asarray(b["psf_fwhm"], float) / np.asarray(a["psf_fwhm"], float) - 1))
    if all(np.any(np.isfinite(x)) for x in dp):
        print(f"PSF {label}: at the objects, psf_e1 and psf_e2 at most {np.nanmax(dp[0]):.1e} and {np.nanmax(dp[1]):.1e} "
              f"apart, psf_fwhm at most {np.nanmax(dp[2]):.1e} of itself")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="small")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--psf", choices=["true", "fitted", "both"], default="both")
    ap.add_argument("--no-profile", action="store_true", help="skip the profiled run (stages)")
    ap.add_argument("--stage-clock", action="store_true",
                    help="one more run of the last PSF mode with the pipeline's own stages timed directly around "
                         "their calls (CPU time, no profiler, whose cost per Python call inflates the pipeline's "
                         "small calls), each as a share of the engine's time")
    ap.add_argument("--simultaneous", type=int, default=0, metavar="N",
                    help="also run N pairs with the given-PSF and the fitted-PSF run at the same time, one per core "
                         "(two processes): both meet the same load from the rest of the machine, so the PSF stage is "
                         "measured pair by pair without the drift between runs one after the other")
    ap.add_argument("--pairs", type=int, default=3,
                    help="runs of each PSF mode, given and fitted alternately (a shared machine's speed drifts by "
                         "10-30 %% from minute to minute: the PSF stage is taken from each pair and from the medians)")
    ap.add_argument("--metacal", type=int, default=0, metavar="N",
                    help="also run N pairs of the plain run and calibration: metacal (PSF images given), alternated, "
                         "and print metacal's CPU time per object as a multiple of the plain run's; then N runs that "
                         "measure each object both ways in turn (the machine's drift met by both alike), the ratio "
                         "per class of the plain fit with its bootstrap error")
    ap.add_argument("--metacal-psf", choices=("true", "fitted"), default="true",
                    help="the PSFs of --metacal's runs: the given images (default) or the models fitted from the stars")
    ap.add_argument("--isophotes", action="store_true",
                    help="also time the isophote analysis (sec. 3.6) of 200 objects as the pipeline cut them, in a "
                         "loop, compiled against its numpy and scipy lines, and check that both decide the same")
    ap.add_argument("--keep", default=None, help="keep the field in this directory")
    ap.add_argument("--sim", action="append", default=[], metavar="KEY=VALUE",
                    help="a simulation key of the field (e.g. exposure_rotation=0.5: every exposure its own "
                         "rotation, so that no two share a Jacobian, as on a camera)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a setting of the engine or the pipeline for every run (e.g. psf_native_width=0)")
    ap.add_argument("--compare-with", default=None, metavar="DIR",
                    help="the --keep directory of an earlier run (another commit, the same preset and seed): how far "
                         "this run's catalogues moved from its shear_true.fits and shear_fitted.fits")
    args = ap.parse_args(argv)
    from shearfit.engine.kernel import kernel_info

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from speed import cpu_name

    info = kernel_info()
    print(f"CPU: {cpu_name()}; inner loops: {info['path']} ({info['isa']})")
    modes = ["true", "fitted"] if args.psf == "both" else [args.psf]
    with tempfile.TemporaryDirectory() as tmp:
        d = args.keep or tmp
        sim = {"preset": args.preset, "seed": args.seed}
        for kv in args.sim:
            k, v = kv.split("=", 1)
            sim[k.strip()] = yaml.safe_load(v)
        sc = simulation_config(sim)
        t0 = time.perf_counter()
        simulate_field(sc, d)
        print(f"simulated preset {args.preset} in {time.perf_counter() - t0:.0f} s")
        # what every process builds once (profile tables, lazy imports), timed apart from the runs so that the
        # first run does not carry it and the PSF stage (fitted minus given) is not understated by it
        c0 = _cpu_seconds()
        _warm_up()
        print(f"one-off per process (profile tables, imports): {_cpu_seconds() - c0:.1f} CPU-s, not counted below")
        rates = {m: [] for m in modes}
        engine_cpu = {m: [] for m in modes}
        psf_cpu = {m: [] for m in modes}
        for rep in range(max(args.pairs, 1)):
            for mode in modes:
                cfg = _with_settings(load_field_config(os.path.join(d, "field_truepsf.yaml" if mode == "true"
                                                                    else "field.yaml")), args.set)
                _forget_psfs()
                c0, t0 = _cpu_seconds(), time.perf_counter()
                with _ModeCounter() as counter, _EngineClock() as clock, _PsfClock() as psf_clock:
                    table = measure_field(cfg, out_path=os.path.join(d, f"shear_{mode}.fits"), processes=1)
                cpu, wall = _cpu_seconds() - c0, time.perf_counter() - t0
                rates[mode].append(cpu)
                engine_cpu[mode].append(clock.cpu)
                psf_cpu[mode].append(psf_clock.cpu)
                fc = np.asarray(table["fitclass"])
                if rep == 0:
                    print(f"\nPSF {'given (true images)' if mode == 'true' else 'fitted from the stars'}: {len(table)} "
                          f"objects ({int((fc == 0).sum())} galaxies, {int((fc == 1).sum())} stars, "
                          f"{int((fc < 0).sum())} flagged or unmeasured), {len(cfg.exposures)} exposures, one process; "
                          f"{counter.summary()}")
                print(f"  run {rep + 1}, PSF {'given' if mode == 'true' else 'fitted'}: {len(table) / cpu:.2f} objects "
                      f"per CPU-second ({cpu:.1f} CPU-s, {wall:.1f} s wall); the engine {clock.cpu:.1f} CPU-s of it, "
                      f"the rest of the pipeline adds {100 * (cpu - clock.cpu) / clock.cpu:.0f} % to the engine's cost; "
                      f"the PSF itself (timed directly) {psf_clock.cpu:.2f} CPU-s, {100 * psf_clock.cpu / cpu:.1f} %",
                      flush=True)
        n_obj = len(table)
        for mode in modes:
            med = float(np.median(rates[mode]))
            print(f"\nPSF {'given' if mode == 'true' else 'fitted'}, median of {len(rates[mode])} runs: "
                  f"**{n_obj / med:.2f} objects per CPU-second** ({med:.1f} CPU-s; runs "
                  f"{', '.join(f'{n_obj / c:.1f}' for c in rates[mode])}); the pipeline adds "
                  f"{', '.join(f'{100 * (c - e) / e:.0f}' for c, e in zip(rates[mode], engine_cpu[mode]))} % to the "
                  f"engine's CPU time (run by run, timed around measure_object without the profiler)")
        if len(modes) == 2:
            pair = [100 * (f - t) / f for t, f in zip(rates["true"], rates["fitted"])]
            mt, mf = float(np.median(rates["true"])), float(np.median(rates["fitted"]))
            print(f"PSF stage (fitted minus given): {mf - mt:.1f} CPU-s, {100 * (mf - mt) / mf:.0f} % of the run with "
                  f"fitted PSFs (medians); pair by pair {', '.join(f'{p:.0f}' for p in pair)} %")
            share = [100 * p / c for p, c in zip(psf_cpu["fitted"], rates["fitted"])]
            de = [f - t for t, f in zip(engine_cpu["true"], engine_cpu["fitted"])]
            print(f"PSF stage of the fitted runs, timed directly (star selection and fits, the model at each object, "
                  f"its moments): {', '.join(f'{x:.1f}' for x in share)} % (median {np.median(share):.1f} %); the "
                  f"engine's own time with the fitted models minus with the given images: "
                  f"{', '.join(f'{x:+.2f}' for x in de)} CPU-s "
                  f"({', '.join(f'{100 * x / c:+.1f}' for x, c in zip(de, rates['fitted']))} % of the fitted runs)")
        if args.simultaneous > 0 and len(modes) == 2:
            _simultaneous_pairs(d, args.set, args.simultaneous)
        if args.metacal > 0:
            _metacal_pairs(d, args.set, args.metacal, args.metacal_psf)
        if args.isophotes:
            _isophote_loop(d, args.set)
        if args.compare_with:
            for mode in modes:
                _compare_catalogues(os.path.join(args.compare_with, f"shear_{mode}.fits"),
                                    os.path.join(d, f"shear_{mode}.fits"), mode)
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        print(f"peak memory (max RSS of this process): {peak:.0f} MB")
        if args.stage_clock:
            mode = modes[-1]
            cfg = _with_settings(load_field_config(os.path.join(d, "field_truepsf.yaml" if mode == "true"
                                                                else "field.yaml")), args.set)
            total, eng, parts = _stage_clock_run(cfg, os.path.join(d, "shear_clocked.fits"))
            print(f"\nthe pipeline's stages timed directly (PSF {mode}; {total:.2f} CPU-s, the engine {eng:.2f}, the "
                  f"rest adding {100 * (total - eng) / eng:.1f} % to it; each stage's calls included, % of the engine):")
            for label, cpu in sorted(parts, key=lambda p: -p[1]):
                print(f"    {label:44s} {cpu:6.3f} s  {100 * cpu / eng:5.1f} %")
        if args.no_profile:
            return
        mode = modes[-1]
        cfg = _with_settings(load_field_config(os.path.join(d, "field_truepsf.yaml" if mode == "true" else "field.yaml")),
                             args.set)
        _forget_psfs()
        prof = cProfile.Profile()
        prof.enable()
        table = measure_field(cfg, out_path=os.path.join(d, "shear_profiled.fits"), processes=1)
        prof.disable()
    st = pstats.Stats(prof).stats
    total = sum(v[2] for v in st.values())

    def cum(fname, func):
        return sum(v[3] for k, v in st.items() if k[0].endswith(fname) and k[2] == func)

    n = len(table)
    engine = cum("engine/measure.py", "measure_object")
    print(f"\nprofiled run (PSF {mode}): the engine alone {n / engine:.2f} objects/s/core over the same objects "
          f"(measure_object: {engine:.1f} s, {100 * engine / total:.0f} % of the profiled time)")
    print(f"  where the time goes (cumulative, % of {total:.1f} s profiled):")
    for label, fname, func in STAGES:
        t = cum(fname, func)
        if t > 0:
            print(f"    {label:44s} {t:7.2f} s  {100 * t / total:5.1f} %")


if __name__ == "__main__":
    main()

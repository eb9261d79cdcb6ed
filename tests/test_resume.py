"""shearfit measure keeps finished chunks: a killed run resumes to the same catalogue, bit for bit."""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from astropy.table import Table

pytest.importorskip("galsim")

from shearfit.app.cli import main  # noqa: E402
from shearfit.pipeline import driver as pipeline  # noqa: E402
from shearfit.simulate.field import simulate_field, simulation_config  # noqa: E402


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    d = tmp_path_factory.mktemp("resume")
    sc = simulation_config({"preset": "tiny", "seed": 11})
    simulate_field(sc, d)
    cfg = d / "field_truepsf.yaml"
    ref = d / "ref.fits"
    assert main(["measure", str(cfg), "chunk_size=6", "--out", str(ref), "--quiet"]) == 0
    return d, cfg, Table.read(ref)


def _same(a, b):
    assert a.colnames == b.colnames
    for c in a.colnames:
        x, y = np.asarray(a[c]), np.asarray(b[c])
        if x.dtype.kind == "f":
            differ = np.flatnonzero(~((x == y) | (np.isnan(x) & np.isnan(y))))
            # which rows and by how much: a last-bit difference and a real one read differently
            assert differ.size == 0, (c, differ.tolist(), np.abs(x[differ] - y[differ]).tolist())
        else:
            assert np.array_equal(x, y), c


def test_chunks_are_deterministic_and_cover_the_catalogue(field):
    _, _, ref = field
    a = pipeline.sky_chunks(ref, 6)
    b = pipeline.sky_chunks(ref, 6)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert np.array_equal(np.sort(np.concatenate(a)), np.arange(len(ref)))
    assert max(len(c) for c in a) == 6


def test_same_catalogue_for_any_chunking_and_workers(field, tmp_path):
    d, cfg, ref = field
    out = tmp_path / "other.fits"
    assert main(["measure", str(cfg), "chunk_size=17", "--out", str(out), "--quiet", "-j", "2"]) == 0
    _same(Table.read(out), ref)
    assert not os.path.exists(str(out) + ".parts")


def test_killed_run_resumes_to_the_same_catalogue(field, tmp_path, monkeypatch):
    d, cfg, ref = field
    out = tmp_path / "shear.fits"
    parts = str(out) + ".parts"
    code = ("import sys; from shearfit.app.cli import main; "
            f"sys.exit(main(['measure', {str(cfg)!r}, 'chunk_size=6', '--out', {str(out)!r}, '--quiet']))")
    proc = subprocess.Popen([sys.executable, "-c", code])
    t0 = time.time()
    try:
        while time.time() - t0 < 300:
            done = [f for f in os.listdir(parts) if f.startswith("chunk_")] if os.path.isdir(parts) else []
            if len(done) >= 2 or proc.poll() is not None:
                break
            time.sleep(0.05)
        assert proc.poll() is None, "the run finished before it could be killed"
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not out.exists()
    n_done = len([f for f in os.listdir(parts) if f.startswith("chunk_") and f.endswith(".fits")])
    n_chunks = len(pipeline.sky_chunks(ref, 6))
    assert 2 <= n_done < n_chunks
    calls = []
    real = pipeline._measure_chunk
    monkeypatch.setattr(pipeline, "_measure_chunk", lambda k: (calls.append(k), real(k))[1])
    assert main(["measure", str(cfg), "chunk_size=6", "--out", str(out), "--quiet"]) == 0
    assert len(calls) == n_chunks - n_done          # finished chunks were not measured again
    _same(Table.read(out), ref)
    assert not os.path.exists(parts)


def test_checkpoint_of_another_run_is_refused(field, tmp_path, capsys):
    d, cfg, ref = field
    out = tmp_path / "shear.fits"
    parts = tmp_path / "shear.fits.parts"
    parts.mkdir()
    (parts / "manifest.yaml").write_text("run: something else\n")
    assert main(["measure", str(cfg), "chunk_size=6", "--out", str(out), "--quiet"]) != 0
    err = capsys.readouterr().err
    assert "different run" in err and "--restart" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
    assert main(["measure", str(cfg), "chunk_size=6", "--out", str(out), "--quiet", "--restart"]) == 0
    _same(Table.read(out), ref)


def test_explicit_scheduler_and_fork_pool_give_the_same_catalogue(field, tmp_path):
    from dask.distributed import LocalCluster

    d, cfg, ref = field
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        out = tmp_path / "sched.fits"
        assert main(["measure", str(cfg), "chunk_size=9", "--out", str(out), "--quiet",
                     "--scheduler", cluster.scheduler_address]) == 0
    _same(Table.read(out), ref)
    out2 = tmp_path / "fork.fits"
    assert main(["measure", str(cfg), "chunk_size=9", "--out", str(out2), "--quiet", "-j", "2",
                 "--executor", "fork"]) == 0
    _same(Table.read(out2), ref)


def test_unreachable_scheduler_is_one_line(field, tmp_path, capsys):
    d, cfg, _ = field
    out = tmp_path / "x.fits"
    assert main(["measure", str(cfg), "--out", str(out), "--quiet", "--scheduler", "tcp://127.0.0.1:9"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "scheduler" in err[0]
    assert not out.exists() and not os.path.exists(str(out) + ".parts")


@pytest.mark.parametrize("text,message", [("alpha: [1, 2\n", "invalid YAML"),
                                          ("beta: -0.3\n", "calibration has no key 'alpha'")])
def test_bad_calibration_file_fails_before_measuring(field, tmp_path, capsys, text, message):
    d, cfg, _ = field
    cal = tmp_path / "cal.yaml"
    cal.write_text(text)
    out = tmp_path / "x.fits"
    assert main(["measure", str(cfg), f"calibration={cal}", "--out", str(out), "--quiet"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(cal) in err[0] and message in err[0]
    assert not out.exists() and not os.path.exists(str(out) + ".parts")


def test_truncated_exposure_is_one_line_naming_file_and_hdu(field, tmp_path, capsys):
    import shutil

    d, cfg, _ = field
    work = tmp_path / "f"
    shutil.copytree(d, work, ignore=shutil.ignore_patterns("*.parts", "ref.fits"))
    img = work / "exp1.fits"
    size = img.stat().st_size
    with open(img, "r+b") as f:
        f.truncate(size // 2)
    out = tmp_path / "x.fits"
    assert main(["measure", str(work / "field_truepsf.yaml"), "--out", str(out), "--quiet"]) != 0
    err = [line for line in capsys.readouterr().err.strip().splitlines() if line.startswith("shearfit:")]
    assert len(err) == 1 and "exp1.fits" in err[0] and "HDU" in err[0]
    assert not out.exists() and not os.path.exists(str(out) + ".parts")


def _disk_full(only_file_objects):
    import errno

    from astropy.io import fits

    real = fits.HDUList.writeto

    def writeto(self, fileobj, *a, **k):
        if not only_file_objects or not isinstance(fileobj, (str, os.PathLike)):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, fileobj, *a, **k)
    return writeto


def test_disk_full_at_the_final_write_keeps_the_checkpoint(field, tmp_path, capsys, monkeypatch):
    """ENOSPC while writing the catalogue: one line, no catalogue and no temporary file, the finished
    chunks kept; the same command afterwards resumes to the reference catalogue."""
    from astropy.io import fits

    d, cfg, ref = field
    out = tmp_path / "shear.fits"
    monkeypatch.setattr(fits.HDUList, "writeto", _disk_full(only_file_objects=True))
    assert main(["measure", str(cfg), "chunk_size=6", "--out", str(out), "--quiet"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "shear.fits" in err[0] and "No space left" in err[0]
    assert not out.exists() and not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]
    assert len(os.listdir(str(out) + ".parts")) > 1
    monkeypatch.undo()
    assert main(["measure", str(cfg), "chunk_size=6", "--out", str(out), "--quiet"]) == 0
    _same(Table.read(out), ref)


def test_disk_full_at_a_checkpoint_is_one_line(field, tmp_path, capsys, monkeypatch):
    from astropy.io import fits

    d, cfg, _ = field
    out = tmp_path / "shear.fits"
    monkeypatch.setattr(fits.HDUList, "writeto", _disk_full(only_file_objects=False))
    assert main(["measure", str(cfg), "chunk_size=6", "--out", str(out), "--quiet"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "checkpoint" in err[0] and "No space left" in err[0]
    assert not out.exists()


def test_memory_limit_per_worker(field, tmp_path, capsys):
    d, cfg, ref = field
    out = tmp_path / "m.fits"
    assert main(["measure", str(cfg), "chunk_size=6", "--out", str(out), "--quiet", "-j", "2",
                 "--memory-limit", "1GB"]) == 0
    _same(Table.read(out), ref)
    capsys.readouterr()   # the first run's output: on a loaded machine Dask's nanny may warn as it stops workers
    bad = tmp_path / "b.fits"
    assert main(["measure", str(cfg), "--out", str(bad), "--quiet", "-j", "2", "--memory-limit", "lots"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--memory-limit" in err[0]
    assert not bad.exists()


def test_process_pool_under_spawn_gives_the_same_catalogue(field, tmp_path, monkeypatch):
    """The one worker policy (shearfit.workers) is spawn-safe: the plain process pool started by spawn (as on
    macOS and Windows), whose workers get the field's state through the pool's initializer instead of
    inheriting it, writes the same catalogue as one process."""
    import multiprocessing

    from shearfit import workers

    monkeypatch.setattr(workers, "mp_context", lambda: multiprocessing.get_context("spawn"))
    d, cfg, ref = field
    out = tmp_path / "spawn.fits"
    assert main(["measure", str(cfg), "chunk_size=6", "--out", str(out), "--quiet", "-j", "2",
                 "--executor", "processes"]) == 0
    _same(Table.read(out), ref)

"""Worker processes: one policy for every pool of shearfit (the demos, ``measure_objects``, the field pipeline).

- Start method: ``fork`` on Linux (no re-import of the caller's ``__main__``,
  workers start at once and inherit what the parent has opened), the
  platform's safe ``spawn`` elsewhere (macOS, Windows). Work handed to a pool
  therefore goes through ``initargs`` and task arguments, never through
  module globals set in the parent, so that both start methods see it.
- One BLAS / OpenMP thread per worker: the pool gives the parallelism, and
  several threads per process make the engine's small matrix products slower,
  not faster (the throughput is quoted per process). Runs in the caller's
  process (``shearfit measure -j 1``, ``measure_objects(processes=1)``) hold
  its BLAS to one thread for their duration too (:func:`single_threaded`).
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import sys
import warnings

__all__ = ["SINGLE_THREAD_ENV", "mp_context", "process_pool", "single_threaded", "limit_threads", "thread_controls",
           "environment"]

#: Environment of the worker processes: one BLAS / OpenMP thread each.
SINGLE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                     "VECLIB_MAXIMUM_THREADS": "1", "NUMEXPR_NUM_THREADS": "1"}


def mp_context():
    """``fork`` on Linux, else the platform's safe default (``spawn``)."""
    if sys.platform.startswith("linux") and "fork" in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("fork")
    return multiprocessing.get_context("spawn")


@contextlib.contextmanager
def process_pool(processes: int, initializer=None, initargs=()):
    """A ``multiprocessing`` pool of ``processes`` single-threaded workers (see the module doc).

    ``initializer(*initargs)`` runs in each worker after its threads are
    limited; with ``fork`` the arguments are inherited, not pickled.
    """
    with environment(SINGLE_THREAD_ENV), warnings.catch_warnings():
        # OpenBLAS's idle thread pool makes Python >= 3.12 warn about forking a multi-threaded process;
        # OpenBLAS re-initialises itself in the child, and no Python thread of ours runs yet.
        warnings.filterwarnings("ignore", message=r".*multi-threaded.*fork", category=DeprecationWarning)
        pool = mp_context().Pool(processes, initializer=_init_worker, initargs=(initializer, tuple(initargs)))
    with pool:
        yield pool


def _init_worker(initializer, initargs):
    os.environ.update(SINGLE_THREAD_ENV)
    limit_threads()
    if initializer is not None:
        initializer(*initargs)


@contextlib.contextmanager
def single_threaded():
    """One BLAS / OpenMP thread in this process for the duration of the block (work run in-process)."""
    restore = limit_threads()
    try:
        yield
    finally:
        restore()


def thread_controls():
    """(getter, setter) of the thread count of every BLAS (OpenBLAS) and OpenMP library this process has loaded,
    found in ``/proc/self/maps`` and called through ctypes; empty where there is no such file (not Linux)."""
    try:
        import ctypes

        with open("/proc/self/maps", encoding="utf-8", errors="replace") as fh:
            paths = {line.split()[-1] for line in fh if line.rstrip().endswith((".so", ".dylib")) or ".so." in line}
    except (OSError, ImportError):
        return []
    found = []
    for path in sorted(paths):
        name = os.path.basename(path).lower()
        if "openblas" in name:
            pairs = [(f"{pre}openblas_set_num_threads{suf}", f"{pre}openblas_get_num_threads{suf}")
                     for pre in ("", "scipy_") for suf in ("", "64_")]
        elif "gomp" in name or "libomp" in name or "libiomp" in name:
            pairs = [("omp_set_num_threads", "omp_get_max_threads")]
        else:
            continue
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for set_name, get_name in pairs:
            setter, getter = getattr(lib, set_name, None), getattr(lib, get_name, None)
            if setter is None or getter is None:
                continue
            setter.argtypes, getter.restype = [ctypes.c_int], ctypes.c_int
            found.append((getter, setter))
            break
    return found


def limit_threads():
    """Limit already-loaded BLAS and OpenMP libraries to one thread; return a function that restores them.

    Environment variables act only on libraries loaded later, and a forked
    worker inherits the parent's loaded OpenBLAS with its thread count (several
    threads per process make the engine's small matrix products slower, not
    faster). Uses threadpoolctl when it is installed, else calls the
    libraries' own setters (:func:`thread_controls`, Linux); elsewhere it
    does nothing.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        pass
    else:
        limits = threadpool_limits(1)
        return limits.restore_original_limits
    restore = []
    for getter, setter in thread_controls():
        old = int(getter())
        setter(1)
        restore.append((setter, old))

    def _restore():
        for setter, old in restore:
            setter(old)

    return _restore


@contextlib.contextmanager
def environment(values):
    """Set environment variables for the duration of the block, then restore them."""
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v

"""Test helper: the thread counts of the OpenBLAS libraries this process has loaded."""

import contextlib


def openblas_thread_counts():
    """The thread count of every OpenBLAS this process has loaded (numpy's and scipy's), as (getter, setter)
    pairs read through ctypes; empty where none is found (not Linux, another BLAS)."""
    import ctypes
    import os

    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as fh:
            paths = sorted({line.split()[-1] for line in fh if "openblas" in os.path.basename(line.split()[-1]).lower()})
    except OSError:
        return []
    found = []
    for path in paths:
        lib = ctypes.CDLL(path)
        for pre in ("", "scipy_"):
            for suf in ("", "64_"):
                get = getattr(lib, f"{pre}openblas_get_num_threads{suf}", None)
                put = getattr(lib, f"{pre}openblas_set_num_threads{suf}", None)
                if get is not None and put is not None:
                    get.restype, put.argtypes = ctypes.c_int, [ctypes.c_int]
                    found.append((get, put))
    return found


@contextlib.contextmanager
def threads_set_to(libs, n):
    """Every library of ``libs`` (:func:`openblas_thread_counts`) at ``n`` threads for the block, then back."""
    before = [get() for get, _ in libs]
    try:
        for _, put in libs:
            put(n)
        yield
    finally:
        for (_, put), k in zip(libs, before):
            put(k)

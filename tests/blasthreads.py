"""Test helper: set the loaded BLAS and OpenMP libraries' thread counts for a block."""

import contextlib


@contextlib.contextmanager
def threads_set_to(libs, n):
    """Every library of ``libs`` (:func:`shearfit.workers.thread_controls`' (getter, setter) pairs) at ``n``
    threads for the block, then back."""
    before = [get() for get, _ in libs]
    try:
        for _, put in libs:
            put(n)
        yield
    finally:
        for (_, put), k in zip(libs, before):
            put(k)

"""Write a file under a temporary name and rename it into place, so no half-written output is left behind."""

from __future__ import annotations

import os
from contextlib import contextmanager

__all__ = ["atomic_path"]


@contextmanager
def atomic_path(path):
    """Yield a temporary name beside ``path``; on success rename it to ``path``, on failure remove it."""
    d, base = os.path.split(os.fspath(path))
    tmp = os.path.join(d, f".{base}.tmp{os.getpid()}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)

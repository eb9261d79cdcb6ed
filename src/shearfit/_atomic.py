"""File helpers: atomic writes (a temporary name, then a rename: no half-written output) and YAML mappings."""

from __future__ import annotations

import os
from contextlib import contextmanager

__all__ = ["atomic_path", "read_yaml_mapping"]


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


def read_yaml_mapping(path, what):
    """A YAML file's top-level mapping, read with the field config's strict loader (duplicate keys refused,
    ``1e-6`` a float); one-line errors naming the file."""
    from .errors import ShearfitIOError
    from .field.fieldconfig import _yaml_load

    try:
        with open(path) as f:
            text = f.read()
    except OSError as exc:
        raise ShearfitIOError(f"{path}: cannot read the {what}: {exc.strerror}") from None
    d = _yaml_load(text, str(path))
    if d is None:
        d = {}
    if not isinstance(d, dict):
        raise ShearfitIOError(f"{path}: the {what} must be a mapping of keys")
    return d

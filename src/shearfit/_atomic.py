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
    """A YAML file's top-level mapping; one-line ShearfitIOError naming the file otherwise."""
    import yaml

    from .errors import ShearfitIOError

    try:
        with open(path) as f:
            d = yaml.safe_load(f)
    except OSError as exc:
        raise ShearfitIOError(f"{path}: cannot read the {what}: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise ShearfitIOError(f"{path}: not valid YAML: {str(exc).splitlines()[0]}") from None
    if d is None:
        d = {}
    if not isinstance(d, dict):
        raise ShearfitIOError(f"{path}: the {what} must be a mapping of keys")
    return d

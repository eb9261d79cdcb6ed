"""File helpers: atomic writes (a temporary name, then a rename: no half-written output) and strict YAML."""

from __future__ import annotations

import os
import re
from contextlib import contextmanager

import yaml

from .errors import ShearfitIOError, ShearfitValueError

__all__ = ["atomic_path", "load_yaml", "read_yaml_mapping"]


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
    try:
        with open(path) as f:
            text = f.read()
    except OSError as exc:
        raise ShearfitIOError(f"{path}: cannot read the {what}: {exc.strerror}") from None
    d = load_yaml(text, str(path))
    if d is None:
        d = {}
    if not isinstance(d, dict):
        raise ShearfitIOError(f"{path}: the {what} must be a mapping of keys")
    return d


class _StrictLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
    """SafeLoader that rejects duplicate keys and reads ``1e-6`` as a float.

    PyYAML follows YAML 1.1, where a float needs a dot, so ``1e-6`` would be a
    string and then a confusing type error; YAML 1.2 (and every user) reads it
    as a number. A duplicate key silently keeps the last value in PyYAML,
    which hides typos in long configs. Where PyYAML has libyaml, its C parser
    reads the text (in the pure-Python parser the packaged calibration tables
    were a run's largest fixed cost); the constructors are the same.
    """


_StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                    |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                    |[-+]?\.(?:inf|Inf|INF)
                    |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."),
)


def _construct_mapping(loader, node, deep=False):
    loader.flatten_mapping(node)
    seen = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r}", key_node.start_mark)
        seen[key] = True
    return yaml.SafeLoader.construct_mapping(loader, node, deep=deep)


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def load_yaml(text: str, source: str):
    """Parse YAML text strictly (duplicate keys refused, ``1e-6`` a float); one-line errors naming ``source``."""
    try:
        return yaml.load(text, Loader=_StrictLoader)
    except yaml.YAMLError as exc:
        # PyYAML's messages span several lines; keep the error to one.
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ShearfitValueError(f"{source}: invalid YAML{where}: {problem}") from None

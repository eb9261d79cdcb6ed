"""Loading the repository's scripts (benchmarks/, tools/) as modules in the tests (not a test module)."""

import importlib.util
import pathlib

#: the repository's root
ROOT = pathlib.Path(__file__).resolve().parents[1]


def load_script(relpath, name=None):
    """The script at ``relpath`` (from the repository's root) as a module of its own, run once on import."""
    path = ROOT / relpath
    spec = importlib.util.spec_from_file_location(name or path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod

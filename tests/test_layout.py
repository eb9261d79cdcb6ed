"""The package's architecture (tools/import_graph.py): layers import downwards, no cycles, no private names
imported across modules; and the checker itself catches each kind of violation."""

import pytest

from scripts import load_script


def _checker():
    return load_script("tools/import_graph.py", "import_graph")


def test_package_layers_cycles_and_private_names():
    graph, problems = _checker().check()
    assert "shearfit.engine.measure" in graph and len(graph) > 30
    assert problems == []


@pytest.mark.parametrize("files, expected", [
    ({"engine/a.py": "from ..pipeline import b\n", "pipeline/b.py": ""}, "upwards"),
    ({"engine/a.py": "from . import b\n", "engine/b.py": "def f():\n    from . import a\n"}, "import cycle"),
    ({"engine/a.py": "from .b import _hidden\n", "engine/b.py": "_hidden = 1\n"}, "private name _hidden"),
    ({"newmodule.py": "from . import errors\n", "errors.py": ""}, "has no layer"),
])
def test_checker_finds_each_violation(tmp_path, files, expected):
    for name, text in {"__init__.py": "", "engine/__init__.py": "", "pipeline/__init__.py": "", **files}.items():
        p = tmp_path / "shearfit" / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    _, problems = _checker().check(tmp_path)
    assert any(expected in p for p in problems), problems

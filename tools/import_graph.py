"""Print shearfit's import graph and check its architecture: layers point downwards, no cycles, no private
names imported across modules.

Usage: ``python tools/import_graph.py [--modules]`` from the repository root (or any directory). Every
``import`` statement of ``src/shearfit`` counts, those inside functions too. Exit status 1 and one line per
violation when a check fails; ``tests/test_layout.py`` runs the same checks.

The layers, bottom to top (a module may import its own layer and the layers below it):

====  ==========================================================  ==============================
rank  modules                                                     role
====  ==========================================================  ==============================
0     errors, version, workers                                    no shearfit imports
1     config, observation, files                                  settings, records, file helpers
2     engine/                                                     per-object fits; no files
3     shearfit (the package's ``__init__``: the public API)       measure_object, Observation...
4     io/                                                         FITS, WCS, stamps, PSF inputs
5     psf/                                                        PSF models from stars
6     calib/                                                      bias, calibration, metacal
7     stats/, simulate/                                           statistics, GalSim simulations
8     pipeline/                                                   the field pipeline
9     app/                                                        the command line and the demos
====  ==========================================================  ==============================
"""

from __future__ import annotations

import ast
import pathlib
import sys

PACKAGE = "shearfit"
SRC = pathlib.Path(__file__).resolve().parents[1] / "src"

RANKS = {
    "shearfit.errors": 0, "shearfit.version": 0, "shearfit.workers": 0,
    "shearfit.config": 1, "shearfit.observation": 1, "shearfit.files": 1,
    "shearfit.engine": 2, "shearfit": 3, "shearfit.io": 4, "shearfit.psf": 5, "shearfit.calib": 6,
    "shearfit.stats": 7, "shearfit.simulate": 7, "shearfit.pipeline": 8, "shearfit.app": 9,
}
#: (importer, private module) pairs allowed: the one loader of the compiled extension
PRIVATE_MODULES_ALLOWED = {("shearfit.engine.kernel", "shearfit.engine._kernels")}


def modules(src=SRC) -> dict:
    """{module name: (path, is_package)} of every module of the package (the compiled one included)."""
    out = {}
    for f in sorted((src / PACKAGE).rglob("*")):
        if f.suffix not in (".py", ".c") or "__pycache__" in f.parts:
            continue
        parts = f.relative_to(src).with_suffix("").parts
        is_pkg = f.name == "__init__.py"
        out[".".join(parts[:-1] if is_pkg else parts)] = (f, is_pkg)
    return out


def layer(mod: str):
    """The unit a module belongs to (its folder, or itself at the top) and its rank."""
    best = max((k for k in RANKS if mod == k or mod.startswith(k + ".")), key=len, default=None)
    if best == PACKAGE and mod != PACKAGE:          # a top-level module missing from RANKS
        return mod, None
    return best, RANKS.get(best)


def edges(mods: dict) -> list:
    """(importer, imported module, imported name or None, line) for every intra-package import."""
    out = []
    for mod, (path, is_pkg) in mods.items():
        if path.suffix != ".py":
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name == PACKAGE or a.name.startswith(PACKAGE + "."):
                        out.append((mod, a.name, None, node.lineno))
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                    base = base[:len(base) - (node.level - 1)]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                if not (target == PACKAGE or target.startswith(PACKAGE + ".")):
                    continue
                for a in node.names:
                    sub = f"{target}.{a.name}"
                    if sub in mods:
                        out.append((mod, sub, None, node.lineno))
                    else:
                        out.append((mod, target, a.name, node.lineno))
    return out


def cycles(graph: dict) -> list:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1 or v in graph.get(v, ()):
                out.append(sorted(comp))

    sys.setrecursionlimit(10000)
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def check(src=SRC) -> tuple[dict, list]:
    """The module graph {module: set of imported modules} and the list of violations (strings)."""
    mods = modules(src)
    graph = {m: set() for m in mods}
    problems = []
    for a, b, name, line in edges(mods):
        where = f"{mods[a][0].relative_to(src)}:{line}"
        if b != a:
            graph[a].add(b)
        la, ra = layer(a)
        lb, rb = layer(b)
        if ra is None:
            problems.append(f"{where}: module {a} has no layer (add it to RANKS in tools/import_graph.py)")
        elif rb is not None and rb > ra:
            problems.append(f"{where}: {a} (layer {la}, rank {ra}) imports {b} (layer {lb}, rank {rb}): upwards")
        if name is not None and name.startswith("_") and not name.startswith("__"):
            problems.append(f"{where}: {a} imports the private name {name} of {b}")
        leaf = b.rsplit(".", 1)[-1]
        if name is None and leaf.startswith("_") and not leaf.startswith("__") and (a, b) not in PRIVATE_MODULES_ALLOWED:
            problems.append(f"{where}: {a} imports the private module {b}")
    for comp in cycles(graph):
        problems.append("import cycle: " + " <-> ".join(comp))
    return graph, problems


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    graph, problems = check()
    units = {}
    for a, bs in graph.items():
        la = layer(a)[0]
        for b in bs:
            lb = layer(b)[0]
            if lb != la:
                units.setdefault(la, set()).add(lb)
    print("layers (rank: unit -> the units it imports)")
    for unit, rank in sorted(RANKS.items(), key=lambda kv: (kv[1], kv[0])):
        print(f"  {rank}: {unit:20s} -> {', '.join(sorted(units.get(unit, ()))) or '-'}")
    if "--modules" in argv:
        print("modules")
        for a in sorted(graph):
            print(f"  {a} -> {', '.join(sorted(graph[a])) or '-'}")
    if problems:
        print(f"{len(problems)} problem(s):")
        for p in problems:
            print("  " + p)
        return 1
    print(f"{len(graph)} modules: no import cycle, every import points downwards, no private name crosses a module")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The house (issue 19): errplan's import graph has no circle and every import points down the layers
of the data flow (scenario -> kinematics/anatomy -> metrics -> fields -> planning/gains -> simulation ->
recording; measured data -> calibration; only the API and the CLI import everything), and each heavy
third-party library lives behind one module.

The graph is read from the source with ``ast`` (every ``import`` statement, at module level or inside a
function: a lazy import is still an arrow of the drawing), not by importing anything.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "errplan"

# Lower number = lower layer. A module may import only modules of its own component or of a lower layer.
LAYERS = {
    "errors": 0, "inputs": 0, "report": 0, "cluster": 0, "jit": 0, "packages": 0,
    "scenario": 1,
    "linalg": 2,
    "kinematics": 3, "anatomy": 3,
    "metrics": 4, "effects": 4, "errorset": 4,  # errorset: the bounded error sets (plain data over the kinematics)
    "models": 5,  # each arm built once (kinematics, error set, truth, anatomy)
    "fields": 6,  # takes the arm's model (its evaluators are built from it)
    "planning": 7, "gains": 7, "tolerance": 7,
    "simulation": 8,
    "recording": 9, "experiment": 9,
    "pipeline": 10, "calibration": 10,
    "api": 11,
    "cli": 12, "__main__": 12, "": 12,  # "": the package's own __init__ (its API names load lazily)
}
# third-party libraries that must each be imported by one module only (the brief's "behind one module")
BEHIND_ONE = ("rerun", "ompl", "casadi", "dask", "distributed", "trimesh", "fcl", "coal", "sklearn")


def _modules() -> dict[str, Path]:
    mods = {}
    for p in PKG.rglob("*.py"):
        parts = list(p.relative_to(PKG.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mods[".".join(parts)] = p
    return mods


def _imports(mod: str, path: Path, mods: dict[str, Path]) -> tuple[set[str], set[str]]:
    """(errplan modules, third-party top-level names) that ``mod`` imports."""
    internal, external = set(), set()
    is_pkg = path.name == "__init__.py"
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                base = base[:len(base) - (node.level - 1)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            names = [f"{name}.{a.name}" if f"{name}.{a.name}" in mods else name for a in node.names]
        for n in names:
            if n == "errplan" or n.startswith("errplan."):
                while n not in mods and "." in n:
                    n = n.rsplit(".", 1)[0]
                if n != mod:
                    internal.add(n)
            else:
                external.add(n.split(".")[0])
    return internal, external


@pytest.fixture(scope="module")
def graph():
    mods = _modules()
    assert len(mods) > 50, f"only {len(mods)} modules found under {PKG}"  # never a vacuous drawing
    return mods, {m: _imports(m, p, mods) for m, p in mods.items()}


def _component(mod: str) -> str:
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else ""


def test_every_module_has_a_layer(graph):
    mods, _ = graph
    missing = sorted({_component(m) for m in mods} - set(LAYERS))
    assert not missing, f"modules with no layer in tests/test_layers.py: {missing}"


def test_no_import_points_up(graph):
    _, edges = graph
    up = [f"{a} -> {b}" for a, (ins, _) in edges.items() for b in ins
          if _component(a) != _component(b) and LAYERS[_component(b)] > LAYERS[_component(a)]]
    assert not up, "imports pointing up:\n" + "\n".join(sorted(up))


def test_no_import_circle(graph):
    _, edges = graph
    index, low, stack, on, circles = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges[v][0]:
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
            if len(comp) > 1:
                circles.append(sorted(comp))

    for v in edges:
        if v not in index:
            visit(v)
    assert not circles, f"import circles: {circles}"


def _mutual_pairs(edges) -> list[tuple[str, str]]:
    """The pairs of components of which each imports the other (some module of one imports some module of
    the other, both ways)."""
    pairs = {(_component(a), _component(b)) for a, (ins, _) in edges.items() for b in ins
             if _component(a) != _component(b)}
    return sorted({tuple(sorted(p)) for p in pairs if (p[1], p[0]) in pairs})


def test_no_two_components_import_each_other(graph):
    """A pair of components that import each other is a circle of the drawing even when no module imports
    itself back and the two share a layer (a lazy import inside a function counts)."""
    _, edges = graph
    both = _mutual_pairs(edges)
    assert not both, f"components importing each other: {both}"


def test_the_pair_test_catches_a_pair():
    """The check above on the drawing as it was: the fields built an arm's model inside a function while the
    models imported the fields' error set (no module circle, both on one layer)."""
    edges = {"errplan.fields.compute": ({"errplan.models"}, set()),
             "errplan.models": ({"errplan.fields.errorset"}, set()),
             "errplan.fields.errorset": (set(), set())}
    assert _mutual_pairs(edges) == [("fields", "models")]


@pytest.mark.parametrize("lib", BEHIND_ONE)
def test_each_heavy_library_lives_behind_one_module(graph, lib):
    _, edges = graph
    users = sorted(m for m, (_, ext) in edges.items() if lib in ext)
    assert len(users) <= 1, f"{lib} is imported by {users}"

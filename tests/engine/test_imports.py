"""The package's import structure: layers import downwards only.

Walks the AST of every module of ``isac_twin`` (``engine/``; imports at the top and
inside functions alike) and checks the layer order of :data:`LAYERS`, that there is
no import cycle, no private (``_name``) name imported from another module, no module
loaded by file path, and that every subpackage states its public API.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import isac_twin

ROOT = Path(isac_twin.__file__).parent
PKG = "isac_twin"

#: Subpackages from the bottom up. A module may import its own subpackage, the
#: stdlib-only contract and any subpackage of a lower layer: never one beside it
#: or above it. Nothing below ``twin`` knows the twin exists.
LAYERS: list[tuple[str, ...]] = [
    ("utils", "errors"),
    ("bus",),
    ("robots", "phy"),
    ("scene",),
    ("raytrace",),
    ("sensing", "localization", "radiomap", "scaleout"),
    ("transport",),
    ("twin", "calibration"),
    ("live", "devices"),
    ("experiments",),
    ("cli",),
]
#: Importable from every layer (stdlib only, outside ``engine/``).
ANYWHERE = {"contract"}


def _modules() -> dict[str, Path]:
    mods = {}
    for f in ROOT.rglob("*.py"):
        rel = f.relative_to(ROOT).with_suffix("")
        parts = (PKG,) + (rel.parts[:-1] if rel.name == "__init__" else rel.parts)
        mods[".".join(parts)] = f
    return mods


def _resolve(name: str, node: ast.ImportFrom, is_pkg: bool) -> str | None:
    """Absolute module of a ``from ... import`` (relative imports resolved)."""
    if node.level == 0:
        return node.module
    base = name.split(".")
    base = base if is_pkg else base[:-1]
    base = base[:len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def import_graph() -> tuple[dict[str, set[str]], list[str]]:
    """``module -> modules of isac_twin it imports`` and the private imports found.

    A target outside ``engine/`` (``isac_twin.contract...``) appears as itself."""
    mods = _modules()
    edges: dict[str, set[str]] = {}
    private: list[str] = []
    for name, f in mods.items():
        out: set[str] = set()
        for node in ast.walk(ast.parse(f.read_text(), str(f))):
            if isinstance(node, ast.ImportFrom):
                tgt = _resolve(name, node, f.name == "__init__.py")
                if not tgt or tgt.split(".")[0] != PKG:
                    continue
                for a in node.names:
                    sub = f"{tgt}.{a.name}"
                    out.add(sub if sub in mods else tgt)
                    if a.name.startswith("_") and not a.name.startswith("__") and tgt != name:
                        private.append(f"{name} imports {tgt}.{a.name}")
            elif isinstance(node, ast.Import):
                out.update(a.name for a in node.names if a.name.split(".")[0] == PKG)
        # a module's own parent packages are always imported first: not an edge
        edges[name] = {t for t in out if t != name and not name.startswith(t + ".")
                       and t != PKG}
    return edges, private


def layer_of(module: str) -> tuple[int, str] | None:
    """``(layer index, subpackage)`` of an ``isac_twin`` module; ``None`` for the
    package itself and for what may be imported from anywhere."""
    parts = module.split(".")
    if len(parts) < 2 or parts[1] in ANYWHERE:
        return None
    for i, names in enumerate(LAYERS):
        if parts[1] in names:
            return i, parts[1]
    raise AssertionError(f"{module}: its subpackage {parts[1]!r} is in no layer of LAYERS")


def layer_violations(edges: dict[str, set[str]]) -> list[str]:
    """Every import that goes sideways or up the layer order."""
    bad = []
    for src, targets in sorted(edges.items()):
        a = layer_of(src)
        if a is None:
            continue
        for tgt in sorted(targets):
            b = layer_of(tgt)
            if b is None or b[1] == a[1] or b[0] < a[0]:
                continue
            where = "beside it" if b[0] == a[0] else "above it"
            bad.append(f"{src} (layer {a[0]}, {a[1]}) imports {tgt} ({b[1]}, {where})")
    return bad


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    for root in edges:
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(edges.get(w, ())))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def test_the_checker_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_layer_checker_finds_sideways_and_upward_imports():
    edges = {"isac_twin.phy.channel": {"isac_twin.raytrace.base", "isac_twin.utils.geometry",
                                       "isac_twin.phy.arrays", "isac_twin.contract.schema"},
             "isac_twin.robots.agent": {"isac_twin.phy.units"}}
    assert layer_violations(edges) == [
        "isac_twin.phy.channel (layer 2, phy) imports isac_twin.raytrace.base (raytrace, above it)",
        "isac_twin.robots.agent (layer 2, robots) imports isac_twin.phy.units (phy, beside it)"]
    with pytest.raises(AssertionError, match="in no layer"):
        layer_of("isac_twin.newthing.mod")


def test_every_subpackage_has_a_layer():
    subs = {p.name for p in ROOT.iterdir() if (p / "__init__.py").is_file()}
    subs |= {p.stem for p in ROOT.glob("*.py") if p.stem != "__init__"}
    layered = {n for names in LAYERS for n in names}
    assert subs == layered, f"not in LAYERS: {subs - layered}; gone: {layered - subs}"


def test_layers_import_downwards_only():
    edges, _ = import_graph()
    assert len(edges) > 50  # it really walked the package
    bad = layer_violations(edges)
    assert not bad, "imports against the layer order:\n" + "\n".join(bad)


def test_no_import_cycle_in_the_package():
    edges, _ = import_graph()
    found = {" <-> ".join(c) for c in cycles(edges)}
    assert found == set(), "import cycles:\n" + "\n".join(sorted(found))


def test_no_private_name_imported_across_modules():
    _, private = import_graph()
    assert set(private) == set(), \
        "private cross-module imports:\n" + "\n".join(private)


@pytest.mark.parametrize("folder", ["engine", "addon", "tests", "bench"])
def test_no_module_is_loaded_by_file_path(folder):
    top = ROOT.parents[0] / folder
    hits = [f"{f.relative_to(top.parent)}" for f in top.rglob("*.py")
            if "spec_from_file_location" in f.read_text() and f.name != "test_imports.py"]
    assert not hits, f"modules loaded by file path in: {hits}"


def test_every_package_states_its_public_api():
    import importlib
    missing = []
    for name, f in sorted(_modules().items()):
        if f.name != "__init__.py":
            continue
        mod = importlib.import_module(name)
        if not (mod.__doc__ or "").strip():
            missing.append(f"{name}: no docstring")
        names = getattr(mod, "__all__", None)
        if names is None:
            missing.append(f"{name}: no __all__")
            continue
        missing += [f"{name}.__all__ names {n!r}, which it lacks" for n in names
                    if not hasattr(mod, n)]
    assert not missing, "\n".join(missing)

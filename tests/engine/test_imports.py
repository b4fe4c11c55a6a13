"""engine/: layers import downwards only. Walks the AST of every module (imports at
the top and inside functions alike) and checks there is no import cycle and no
private (``_name``) name imported from another module."""

from __future__ import annotations

import ast
from pathlib import Path

import engine

ROOT = Path(engine.__file__).parent


def _modules() -> dict[str, Path]:
    mods = {}
    for f in ROOT.rglob("*.py"):
        rel = f.relative_to(ROOT.parent).with_suffix("")
        parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
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
    """``module -> modules it imports`` inside ``engine`` and the private imports found."""
    mods = _modules()
    edges: dict[str, set[str]] = {}
    private: list[str] = []
    for name, f in mods.items():
        out: set[str] = set()
        for node in ast.walk(ast.parse(f.read_text(), str(f))):
            if isinstance(node, ast.ImportFrom):
                tgt = _resolve(name, node, f.name == "__init__.py")
                if not tgt or tgt.split(".")[0] != "engine":
                    continue
                for a in node.names:
                    sub = f"{tgt}.{a.name}"
                    out.add(sub if sub in mods else tgt)
                    if a.name.startswith("_") and not a.name.startswith("__") and tgt != name:
                        private.append(f"{name} imports {tgt}.{a.name}")
            elif isinstance(node, ast.Import):
                out.update(a.name for a in node.names if a.name.split(".")[0] == "engine")
        # a module's own parent packages are always imported first: not an edge
        edges[name] = {t for t in out if t in mods and t != name
                       and not name.startswith(t + ".") and t != "engine"}
    return edges, private


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


def test_no_import_cycle_in_engine():
    edges, _ = import_graph()
    assert len(edges) > 50  # it really walked the package
    found = {" <-> ".join(c) for c in cycles(edges)}
    assert found == set(), "import cycles:\n" + "\n".join(sorted(found))


def test_no_private_name_imported_across_modules():
    _, private = import_graph()
    assert set(private) == set(), \
        "private cross-module imports:\n" + "\n".join(private)


#: packages another issue is rebuilding
_FACE_PENDING: set[str] = set()


def test_every_package_states_its_public_api():
    import importlib
    missing = []
    for name, f in sorted(_modules().items()):
        if f.name != "__init__.py" or name in _FACE_PENDING:
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

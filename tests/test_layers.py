"""The rooms of the package follow the data: no import circles, and no room imports a higher one.

The layer order (lowest first) is the one the README's layout section states. Imports inside
functions count (they are how the rooms talk); ``if TYPE_CHECKING:`` blocks do not.
"""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "lodbuilder"

#: rooms, lowest first; a module may import its own room and any lower one
LAYERS = [
    ["errors", "progress", "_validate", "_optional", "_resources", "_atomic", "_json", "py"],
    ["_kernels"],
    ["levels", "filters", "io", "datasets"],
    ["features", "sampling"],
    ["archive"],
    ["fill", "query", "quality", "export", "viewer"],
    ["build"],
    ["api", "collection"],
    ["cli"],
]
LEVEL = {room: i for i, rooms in enumerate(LAYERS) for room in rooms}


def _modules() -> dict[str, Path]:
    out = {}
    for p in PKG.rglob("*.py"):
        parts = list(p.relative_to(PKG.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _imports(mod: str, path: Path, mods: dict[str, Path]) -> set[str]:
    """The lodbuilder modules ``mod`` imports (a name imported from a package counts as its
    submodule when there is one, else as the package)."""
    tree = ast.parse(path.read_text())
    typing_only = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If)
                   and "TYPE_CHECKING" in ast.unparse(node.test) for n in ast.walk(node)}
    out = set()
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = mod.split(".") if path.name == "__init__.py" else mod.split(".")[:-1]
                base = base[: len(base) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            for alias in node.names:
                sub = f"{name}.{alias.name}"
                out.add(sub if sub in mods else name)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return {m for m in out if m in mods and m != mod}


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    return {m: _imports(m, p, mods) for m, p in mods.items()}


def _room(mod: str) -> str:
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else "py"


def test_every_room_has_a_layer():
    rooms = {_room(m) for m in _modules()}
    assert rooms - set(LEVEL) == set(), "add the new room to LAYERS and to the README's layout section"


def test_no_room_imports_a_higher_room():
    climbs = sorted(f"{m} -> {t}" for m, ts in _graph().items() for t in ts
                    if LEVEL[_room(t)] > LEVEL[_room(m)])
    assert climbs == []


def test_no_import_circles():
    graph = _graph()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    circles: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert circles == []


#: modules still over the limit, each with the work that splits it (the test fails when one of
#: them shrinks, so that the list is kept short)
OVER_LIMIT = {"lodbuilder/io/las.py"}  # reader checks, metadata, layout policy and writer: to split


def test_no_module_over_the_size_limit_outside_the_kernels():
    big = {str(p.relative_to(PKG.parent)) for p in PKG.rglob("*.py")
           if "_kernels" not in p.parts and len(p.read_text().splitlines()) > 600}
    assert big == OVER_LIMIT


def test_one_current_json_per_benchmark():
    # docs/bench keeps the current result of each tools/bench_*.py (history is in git)
    root = PKG.parent
    benches = {p.stem for p in (root / "tools").glob("bench_*.py")}
    stray = sorted(p.name for p in (root / "docs" / "bench").glob("*") if p.stem not in benches or p.suffix != ".json")
    assert stray == []

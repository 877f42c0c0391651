"""The layers of the architecture page (docs/explanation/architecture.md) hold: no module of ``src/relloc`` imports one of a higher layer.

Every ``import relloc.x`` and ``from relloc.x import ...`` counts, inside functions too (a lazy
import is still a dependency).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "relloc"

LAYERS: tuple[tuple[str, ...], ...] = (
    ("events", "config", "estimate", "odometry", "malloc"),
    ("geometry",),
    ("filter",),
    ("localizers", "stages", "ranging", "ros", "simulator", "faults", "sensors"),
    ("estimators",),
    ("sources",),
    ("engine", "methods"),
    ("sinks", "evaluation", "drafting"),
    ("live",),
    ("navigation",),
    ("runs",),
    ("cli",),
)
"""Bottom first, as on the architecture page: a module may import its own layer and those before it."""

LAYER_OF = {part: i for i, parts in enumerate(LAYERS) for part in parts}


def _part(module: str) -> str | None:
    """The top-level part of ``relloc.<part>...``, or ``None`` for another package."""
    names = module.split(".")
    return names[1] if names[0] == "relloc" and len(names) > 1 else None


def _imports(path: Path) -> set[str]:
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module == "relloc":
                out.update(f"relloc.{alias.name}" for alias in node.names)
            else:
                out.add(node.module)
    return out


MODULES = sorted(p for p in SRC.rglob("*.py") if p.parent != SRC or p.name != "__init__.py")


def test_every_part_of_the_package_has_a_layer() -> None:
    parts = {(p.relative_to(SRC).parts[0]).removesuffix(".py") for p in MODULES}
    assert parts == set(LAYER_OF)


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(SRC)))
def test_no_import_reaches_a_higher_layer(path: Path) -> None:
    own = LAYER_OF[path.relative_to(SRC).parts[0].removesuffix(".py")]
    higher = sorted(
        m
        for m in _imports(path)
        if (part := _part(m)) is not None and part in LAYER_OF and LAYER_OF[part] > own
    )
    assert not higher, f"{path.relative_to(SRC)} (layer {own + 1}) imports {higher}"


def _module(path: Path) -> str:
    parts = ("relloc", *path.relative_to(SRC).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


PACKAGE = {_module(p): p for p in SRC.rglob("*.py")}


def _edges(path: Path) -> set[str]:
    """The package's modules that ``path`` imports (``from relloc.a import b`` names module
    ``relloc.a.b`` where that is one, else ``relloc.a``), inside functions and
    ``TYPE_CHECKING`` blocks too."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.update(
                f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in PACKAGE else node.module
                for a in node.names
            )
    return out & PACKAGE.keys()


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (or a module importing
    itself), by Tarjan's algorithm: every import cycle lies within one."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1 or v in graph[v]:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_package_has_no_import_cycle() -> None:
    graph = {module: _edges(path) for module, path in PACKAGE.items()}
    assert _cycles(graph) == []


def test_the_cycle_check_finds_a_cycle() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": {"e"}}
    assert _cycles(graph) == [["a", "b", "c"], ["e"]]

"""The shape of the package: layers point one way, no import circle, a lazy front door.

The import graph is built from the source with :mod:`ast` (every ``import`` and ``from ...
import`` statement, at module level or inside functions, ``TYPE_CHECKING`` blocks included), so
a circle that only closes at run time is caught too.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "hallcal"

#: Layer of each top-level part of the package; a module may import only from its own layer or
#: lower ones (README, "Layout").
LAYERS: dict[str, int] = {
    "_version": 0,
    "errors": 0,
    "sensor": 1,
    "sim": 2,
    "identify": 3,
    "fit": 4,
    "io": 5,
    "pipeline": 6,
    "output": 7,
    "api": 8,
    "demo": 8,
    "fleet": 8,
    "cli": 9,
    "__init__": 10,
}


def _module_name(path: Path) -> str:
    rel = path.relative_to(SRC.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path) -> set[str]:
    """Every hallcal module that `path` imports (absolute or relative, anywhere in the file)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    me = _module_name(path)
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.split(".")[0] == "hallcal")
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.split(".")[0] != "hallcal":
                continue
            if mod != "hallcal":  # the root package is loaded before any of its modules
                found.add(mod)
            for a in node.names:  # "from hallcal.fit import sem" imports a module
                if (SRC.parent / (mod.replace(".", "/") + f"/{a.name}.py")).exists() or (
                    SRC.parent / (mod.replace(".", "/") + f"/{a.name}/__init__.py")
                ).exists():
                    found.add(f"{mod}.{a.name}")
    found.discard(me)
    return found


def _graph() -> dict[str, set[str]]:
    return {_module_name(p): _imports(p) for p in sorted(SRC.rglob("*.py"))}


def _part(module: str) -> str:
    parts = module.split(".")
    return "__init__" if len(parts) == 1 else parts[1]


def test_every_part_of_the_package_has_a_layer():
    parts = {_part(m) for m in _graph()}
    assert parts <= set(LAYERS), f"add {sorted(parts - set(LAYERS))} to LAYERS and the README"


def test_imports_point_down_the_layers():
    upward = [
        f"{m} (layer {LAYERS[_part(m)]}) imports {t} (layer {LAYERS[_part(t)]})"
        for m, targets in _graph().items()
        for t in targets
        if LAYERS[_part(t)] > LAYERS[_part(m)]
    ]
    assert upward == []


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Elementary circles found by depth-first search (one per back edge)."""
    found: list[list[str]] = []
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in graph:
                continue
            if state.get(nxt) == 1:
                found.append(stack[stack.index(nxt) :] + [nxt])
            elif nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node)
    return found


def test_no_import_circle_among_modules():
    graph = _graph()
    # a package's __init__ re-exporting its own modules is not a circle of the design
    graph = {
        m: {t for t in ts if not (graph.get(m) is not None and t.startswith(m + "."))}
        for m, ts in graph.items()
    }
    assert _cycles(graph) == []


def test_the_cycle_finder_finds_a_planted_circle():
    """The check can fail: a two-module circle and a three-module circle are reported."""
    assert _cycles({"a": {"b"}, "b": {"a"}}) == [["a", "b", "a"]]
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == [["a", "b", "c", "a"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


@pytest.mark.parametrize(
    "heavy", ["numba", "scipy", "matplotlib", "h5py", "pyarrow", "hallcal.fit", "hallcal.sim"]
)
def test_import_hallcal_loads_no_numeric_stack(heavy):
    """``import hallcal`` and ``hallcal --help`` cost only what they use (names load lazily)."""
    code = f"import sys, hallcal; print({heavy!r} in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_front_door_names_resolve():
    import hallcal

    for name in hallcal.__all__:
        assert getattr(hallcal, name) is not None, name
    with pytest.raises(AttributeError):
        hallcal.no_such_name  # noqa: B018


def test_the_parser_sees_module_level_and_function_level_imports():
    """The graph is not empty by accident: known edges of both kinds are found."""
    graph = _graph()
    assert "hallcal.fit.sem" in graph["hallcal.fit.order"]  # module level
    assert "hallcal.pipeline.open_loop" in graph["hallcal.pipeline"]  # inside a function
    assert "hallcal.pipeline" in graph["hallcal.cli"]  # "from hallcal import pipeline"

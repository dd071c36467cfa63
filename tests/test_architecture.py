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
    "_constants": 0,
    "_version": 0,
    "errors": 0,
    "formatting": 0,
    "limits": 0,
    "messages": 0,
    "settings": 0,
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


def test_module_names_are_unique():
    """One name, one module: a file name (other than ``__init__.py``) is used once in the
    package, so that "``cogging.py``" or a traceback's file name says which one (docs/design.md,
    "Names")."""
    seen: dict[str, list[str]] = {}
    for path in SRC.rglob("*.py"):
        if path.name != "__init__.py":
            seen.setdefault(path.name, []).append(str(path.relative_to(SRC)))
    assert {k: v for k, v in seen.items() if len(v) > 1} == {}


def _private_imports(path: Path) -> list[tuple[str, str]]:
    """(module, name) of every ``from hallcal.x import _name`` in ``path``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module and not node.level:
            if node.module.split(".")[0] == "hallcal":
                found += [(node.module, a.name) for a in node.names
                          if a.name.startswith("_") and not a.name.startswith("__")]  # fmt: skip
    return found


def _package(module: str) -> str:
    """The subpackage a module belongs to (``hallcal.fit.sem`` -> ``hallcal.fit``)."""
    return ".".join(module.split(".")[:2])


def test_underscore_names_stay_inside_their_package():
    """An underscore name is private to its package (``hallcal.fit``, ``hallcal.output``, ...):
    modules of the package share it, no other package imports it; what another package needs
    is public (docs/design.md, "Names")."""
    crossing = [
        f"{_module_name(p)} imports {name} from {module}"
        for p in SRC.rglob("*.py")
        for module, name in _private_imports(p)
        if _package(module) != _package(_module_name(p)) and name != "_version"
    ]
    assert crossing == []


def test_the_private_name_check_sees_a_planted_import(tmp_path):
    planted = tmp_path / "planted.py"
    planted.write_text("from hallcal.sim.loop import _secret, public\n", encoding="utf-8")
    assert _private_imports(planted) == [("hallcal.sim.loop", "_secret")]


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


#: Runs the command line in a fresh interpreter and writes the names in sys.modules to a file.
_RUN_AND_LIST_MODULES = """
import sys
from hallcal.cli import main
sys.argv = ["hallcal", *{args!r}]
try:
    main()
except SystemExit as exc:
    status = exc.code
else:
    status = 0
with open({listing!r}, "w") as f:
    f.write("\\n".join(sorted(sys.modules)))
sys.exit(status)
"""


def _modules_after(args: list[str], cwd: Path) -> set[str]:
    listing = cwd / "modules.txt"
    code = _RUN_AND_LIST_MODULES.format(args=args, listing=str(listing))
    res = subprocess.run(
        [sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=600
    )
    assert res.returncode == 0, res.stderr
    return set(listing.read_text().split())


def _loaded(modules: set[str], heavy: list[str]) -> list[str]:
    """The entries of `heavy` that are loaded (a package or any of its submodules)."""
    return [h for h in heavy if any(m == h or m.startswith(h + ".") for m in modules)]


NUMERIC_STACK = ["numpy", "scipy", "numba", "pyarrow", "matplotlib", "h5py", "rich"]
NUMERIC_STACK += ["hallcal.io", "hallcal.pipeline", "hallcal.sim", "hallcal.fit", "hallcal.api"]


@pytest.mark.parametrize(
    "args",
    [
        ["--help"],
        ["calibrate", "--help"],
        ["reconstruct", "--help"],
        ["simulate", "--help"],
        ["report", "--help"],
        ["export-c", "--help"],
        ["--version"],
    ],
)
def test_help_loads_no_numeric_stack(tmp_path, args):
    """``hallcal --help`` and ``hallcal <cmd> --help`` load click and hallcal's front only."""
    modules = _modules_after(args, tmp_path)
    assert "click" in modules  # the listing is real
    assert _loaded(modules, NUMERIC_STACK) == []


@pytest.fixture(scope="module")
def paper_like_run(tmp_path_factory):
    """A short closed-loop run (6 s, 1.1 revolutions of the paper's bench) as CSV, and its setup."""
    from hallcal.io import default_setup, write_dataset, write_setup
    from hallcal.pipeline import simulate

    d = tmp_path_factory.mktemp("modules")
    setup = default_setup()
    run = simulate(setup, ramp_end=7.0, duration=6.0)
    write_dataset(d / "cal.csv", run.columns())
    write_setup(d / "s.toml", setup)
    return d


def test_calibrate_loads_only_what_it_uses(paper_like_run):
    """A Fourier calibration from CSV: no plotting, HDF5, MAT, Parquet, kernel solver, bench."""
    modules = _modules_after(
        ["calibrate", "cal.csv", "--setup", "s.toml", "--out", "cal.json"], paper_like_run
    )
    assert _loaded(modules, ["numba", "hallcal.fit.sem", "pyarrow.csv"]) == [
        "numba",
        "hallcal.fit.sem",
        "pyarrow.csv",
    ]
    unused = ["matplotlib", "h5py", "scipy.io", "scipy.signal", "scipy.stats", "scipy.optimize"]
    unused += ["scipy.special"]
    unused += ["pyarrow.parquet", "hallcal.fit.kernel", "hallcal.sim.bench", "hallcal.output"]
    unused += ["rich"]
    assert _loaded(modules, unused) == []


def test_reconstruct_needs_neither_numba_nor_scipy(paper_like_run):
    """Applying a table is NumPy work: reading the artifact must not load the solver stack."""
    if not (paper_like_run / "cal.json").exists():
        _modules_after(
            ["calibrate", "cal.csv", "--setup", "s.toml", "--out", "cal.json"], paper_like_run
        )
    modules = _modules_after(
        ["reconstruct", "cal.json", "cal.csv", "--out", "angles.npz"], paper_like_run
    )
    assert _loaded(modules, ["numpy", "hallcal.sensor.lut"]) == ["numpy", "hallcal.sensor.lut"]
    unused = ["numba", "scipy", "matplotlib", "h5py", "pyarrow.parquet", "hallcal.fit"]
    unused += ["hallcal.sim.loop", "hallcal.output", "rich"]
    assert _loaded(modules, unused) == []


def test_the_module_listing_sees_a_planted_import(tmp_path):
    """The check can fail: a command that loads matplotlib is reported."""
    modules = _modules_after(["--help"], tmp_path)
    assert _loaded(modules | {"matplotlib.figure"}, ["matplotlib"]) == ["matplotlib"]
    assert _loaded(modules | {"matplotlibx"}, ["matplotlib"]) == []


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


# --------------------------------------------------------------------------------------------------
# No function in the numeric core that a reader cannot hold in mind

#: Packages of the numeric core (layers 1-4).
NUMERIC_CORE = ("sensor", "sim", "identify", "fit")

#: Longest function allowed there, in lines from ``def`` to its last line without the docstring
#: (documentation is never a reason to split): a longer one becomes a few named steps, each a
#: function whose name says the step of the method.
MAX_FUNCTION_LINES = 80

#: The numba kernels allowed to be longer: each is one per-sample loop over the closed loop and
#: its sensitivities, already built from named ``@njit`` steps; what remains is the loop's state
#: in a dozen scratch arrays, which a further split would pass through every call of the hot loop.
LONG_NUMBA_KERNELS = {
    "hallcal.fit.gauss_newton._sens_block",
}


def _functions(root: Path) -> dict[str, tuple[int, bool]]:
    """Every function and method in the numeric core under ``root`` (the ``hallcal`` folder):
    qualified name -> (lines without the docstring, whether it is compiled by numba)."""
    found: dict[str, tuple[int, bool]] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                name = f"{prefix}.{child.name}"
                njit = any("njit" in ast.unparse(d) for d in child.decorator_list)
                lines = child.end_lineno - child.lineno + 1
                first = child.body[0]
                if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                    if isinstance(first.value.value, str):  # the docstring
                        lines -= first.end_lineno - first.lineno + 1
                found[name] = (lines, njit)
                visit(child, name)
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}.{child.name}")

    for part in NUMERIC_CORE:
        for path in sorted((root / part).rglob("*.py")):
            module = ".".join(path.relative_to(root.parent).with_suffix("").parts)
            visit(ast.parse(path.read_text(encoding="utf-8")), module)
    return found


def _too_long(functions: dict[str, tuple[int, bool]]) -> dict[str, int]:
    return {
        name: lines
        for name, (lines, _) in functions.items()
        if lines > MAX_FUNCTION_LINES and name not in LONG_NUMBA_KERNELS
    }


def test_no_function_in_the_numeric_core_is_longer_than_the_limit():
    assert _too_long(_functions(SRC)) == {}, (
        f"split into named steps (at most {MAX_FUNCTION_LINES} lines of code each)"
    )


def test_the_exempt_kernels_are_long_numba_kernels():
    """The exemption names real numba kernels that still need it (else it leaves the list)."""
    functions = _functions(SRC)
    for name in sorted(LONG_NUMBA_KERNELS):
        lines, njit = functions[name]
        assert njit and lines > MAX_FUNCTION_LINES, name


def test_the_length_check_sees_a_planted_long_function(tmp_path):
    """The check can fail: a method of 81 code lines in a layer-1 module is reported, 80 are
    not, whatever the length of its docstring."""
    doc = '        """' + "\n".join(["Doc."] + ["        more"] * 40) + '"""\n'
    body = "\n".join(f"        x{i} = {i}" for i in range(79))
    source = f"class A:\n    def long(self):\n{doc}{body}\n\n    def short(self):\n        pass\n"
    planted = tmp_path / "hallcal" / "sensor" / "planted.py"
    planted.parent.mkdir(parents=True)
    planted.write_text(source, encoding="utf-8")
    functions = _functions(tmp_path / "hallcal")
    assert functions == {
        "hallcal.sensor.planted.A.long": (80, False),
        "hallcal.sensor.planted.A.short": (2, False),
    }
    assert _too_long(functions) == {}
    planted.write_text(source.replace("x0 = 0", "x0 = 0\n        x = 1"), encoding="utf-8")
    assert _too_long(_functions(tmp_path / "hallcal")) == {"hallcal.sensor.planted.A.long": 81}


# ------------------------------------------------------------------------------------------------
# Size: modules a reader can take in, functions a reader can hold in mind
# ------------------------------------------------------------------------------------------------

#: Longest module [lines].
MAX_MODULE_LINES = 1200

#: Modules allowed above MAX_MODULE_LINES, each with its reason. An entry whose module has come
#: under the limit fails the test too, so the list only ever shrinks.
LARGE_MODULES: dict[str, str] = {}

#: Longest function of the output layer and the front [lines of code, its docstring not
#: counted]. C templates are string constants, not functions, and do not count.
MAX_OUTPUT_FUNCTION_LINES = 100
FUNCTION_RULE_PARTS = ("output", "fleet")


def _module_lines() -> dict[str, int]:
    return {
        _module_name(p): len(p.read_text(encoding="utf-8").splitlines())
        for p in sorted(SRC.rglob("*.py"))
    }


def _long_functions(path: Path, limit: int, name: str | None = None) -> list[str]:
    """Functions (and methods) of ``path`` longer than ``limit`` lines, docstrings not counted."""
    module = name or _module_name(path)
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            continue
        first = min([node.lineno] + [d.lineno for d in node.decorator_list])
        lines = node.end_lineno - first + 1
        body = node.body
        if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
            if isinstance(body[0].value.value, str):  # the docstring
                lines -= body[0].end_lineno - body[0].lineno + 1
        if lines > limit:
            found.append(f"{module}.{node.name} ({lines} lines)")
    return found


def test_no_module_is_too_long():
    sizes = _module_lines()
    too_long = [
        f"{m} ({n} lines)"
        for m, n in sizes.items()
        if n > MAX_MODULE_LINES and m not in LARGE_MODULES
    ]
    assert too_long == [], "split them by job, or list them in LARGE_MODULES with a reason"
    stale = [m for m in LARGE_MODULES if sizes.get(m, 0) <= MAX_MODULE_LINES]
    assert stale == [], "remove these from LARGE_MODULES: they are within the limit now"


def test_no_long_function_in_the_output_layer():
    """Long functions of ``hallcal.output`` and ``hallcal.fleet`` become a few named steps."""
    paths = [p for p in sorted(SRC.rglob("*.py")) if _part(_module_name(p)) in FUNCTION_RULE_PARTS]
    assert any("codegen" in str(p) for p in paths)  # the rule sees the output layer's packages
    long = [f for p in paths for f in _long_functions(p, MAX_OUTPUT_FUNCTION_LINES)]
    assert long == []


def test_the_size_checks_see_a_planted_long_function(tmp_path):
    """The check can fail: a 101-line function is reported; a docstring does not count (the
    ``def`` line and 99 statements under a 50-line docstring make 100 lines)."""
    body = "\n".join(f"    x{i} = {i}" for i in range(100))
    doc = '    """' + "\n".join(["Doc."] * 50) + '"""'
    short = body[: body.rfind("\n")]  # 99 lines
    planted = tmp_path / "planted.py"
    planted.write_text(f"def long():\n{body}\n\n\ndef documented():\n{doc}\n{short}\n")
    assert _long_functions(planted, MAX_OUTPUT_FUNCTION_LINES, "planted") == [
        "planted.long (101 lines)"
    ]

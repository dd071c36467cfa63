"""Meta-tests: nothing the user can set is accepted and then ignored.

Modelled on python-control's ``kwargs_test``: every command-line option of every ``hallcal``
subcommand is used by the function behind it, and every key the setup parser accepts is read
somewhere in the package outside the parser. Each check is also run on a planted defect, so it
is known to fail when it should.
"""

from __future__ import annotations

import ast
import inspect
import re
import textwrap
from pathlib import Path

import click

from hallcal.cli import cli
from hallcal.io import setup as setup_parser

SRC = Path(__file__).resolve().parents[1] / "src" / "hallcal"


def _unused_parameters(func) -> list[str]:
    """Parameters of `func` that its body never reads (by name)."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(func)))
    fdef = next(n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef))
    params = [a.arg for a in fdef.args.args + fdef.args.kwonlyargs]
    used = {n.id for stmt in fdef.body for n in ast.walk(stmt) if isinstance(n, ast.Name)}
    return [p for p in params if p not in used]


def _commands() -> dict[str, click.Command]:
    return dict(cli.commands)


def test_every_cli_option_is_used_by_its_command():
    unused = {}
    for name, cmd in _commands().items():
        func = inspect.unwrap(cmd.callback)
        missing = _unused_parameters(func)
        if missing:
            unused[name] = missing
    assert unused == {}


def test_the_option_check_catches_a_planted_unused_option():
    @click.command()
    @click.option("--used")
    @click.option("--ignored")
    def planted(used, ignored):
        print(used)

    assert _unused_parameters(inspect.unwrap(planted.callback)) == ["ignored"]


def _setup_keys() -> list[tuple[str, str]]:
    return [
        (table, key)
        for table, keys in setup_parser._SETUP_KEYS.items()
        for key in keys
        if table and key not in setup_parser._SETUP_KEYS  # sub-tables are checked as tables
    ]


def _read_outside_the_parser(table: str, key: str, sources: dict[Path, str]) -> bool:
    """Whether some module other than the setup parser reads attribute ``.key`` of the spec of
    ``[table]``: the file reads ``.key`` and refers to the table (``setup.model``, ``.bench``...)
    or to its class (``BenchConfig`` reads the ``[bench]`` keys it inherits from ``BenchSpec``).
    """
    attribute = re.compile(rf"\.{re.escape(key)}\b")
    spec = re.compile(rf"\.{re.escape(table)}\b|\b{re.escape(table.capitalize())}Config\b")
    return any(
        attribute.search(text) and spec.search(text)
        for path, text in sources.items()
        if path.name != "setup.py"
    )


def _sources() -> dict[Path, str]:
    return {p: p.read_text(encoding="utf-8") for p in SRC.rglob("*.py")}


def test_every_setup_key_is_read_somewhere():
    sources = _sources()
    unread = [f"{t}.{k}" for t, k in _setup_keys() if not _read_outside_the_parser(t, k, sources)]
    assert unread == []


def test_the_setup_key_check_catches_a_planted_unused_key():
    sources = _sources()
    assert not _read_outside_the_parser("model", "planted_key_nobody_reads", sources)
    assert not _read_outside_the_parser("planted_table", "max_iterations", sources)
    assert _read_outside_the_parser("model", "max_iterations", sources)


# --- no merge left half done -------------------------------------------------------------------

_MARKER = re.compile(r"^(<{7} |>{7} |={7}$)", re.M)
_TEXT_SUFFIXES = {".py", ".md", ".toml", ".txt", ".c", ".h", ".cfg", ".yml", ".yaml", ".html"}


def conflict_markers(text: str) -> list[int]:
    """Line numbers (1-based) of git merge-conflict markers in ``text``."""
    return [text.count("\n", 0, m.start()) + 1 for m in _MARKER.finditer(text)]


def test_no_merge_conflict_markers_in_the_tree():
    """Merge-conflict lines once reached the README; none may stay in the tree."""
    root = Path(__file__).resolve().parents[1]
    files = [root / "README.md", *root.joinpath("docs").rglob("*")]
    for part in ("src", "tests", "benchmarks", ".ci"):
        files += root.joinpath(part).rglob("*")
    found = {}
    for path in files:
        if path.is_file() and (path.suffix in _TEXT_SUFFIXES or path.name == "run"):
            lines = conflict_markers(path.read_text(encoding="utf-8", errors="replace"))
            if lines:
                found[str(path.relative_to(root))] = lines
    assert not found, f"merge-conflict markers left in: {found}"


def test_the_conflict_marker_check_catches_a_planted_conflict():
    planted = "a\n<<<<<<< HEAD\nb\n=======\nc\n>>>>>>> main\nd\n"
    assert conflict_markers(planted) == [2, 4, 6]
    assert conflict_markers("a\n======= not a marker\n<<<<<<<x\n") == []

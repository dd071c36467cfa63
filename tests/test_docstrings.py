"""Meta-test: the numpydoc of every public function documents what it takes and returns.

Modelled on python-control's ``docstrings_test``. "Public" means: a function named in the
``__all__`` of a ``hallcal`` module (or of the lazy front door ``hallcal.__all__``), and the
public methods of a class named there. The rules:

- a public module-level function that takes parameters has a ``Parameters`` section that lists
  every one of them;
- a public method that has a ``Parameters`` section lists every parameter in it; a public method
  taking two or more parameters (besides ``self``/``cls``) must have one. A hand-written
  ``__init__`` may be documented in the class docstring instead (numpydoc's convention);
- no section documents a parameter that is not in the signature (stale documentation); this
  includes a ``Parameters`` section in the docstring of a dataclass, checked against the
  generated constructor;
- a public module-level function has a ``Returns`` or ``Yields`` section unless it is annotated
  ``-> None``.

Parameters whose name starts with ``_`` are private hooks and may go undocumented; ``*args`` and
``**kwargs`` are documented under that spelling; numpydoc's ``Other Parameters`` section counts
as part of ``Parameters``. The parser is deliberately small (no numpydoc dependency): a section
is a title line underlined with dashes, and a parameter entry is a line of the section at its
least indentation, ``name : type`` or ``name1, name2 : type``. The checker is also run on
planted defects, so it is known to fail when it should.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import pkgutil
import re
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

import hallcal

SRC = Path(hallcal.__file__).resolve().parent


# --- a small numpydoc parser ---------------------------------------------------------------------


def sections(doc: str | None) -> dict[str, list[str]]:
    """The sections of a numpydoc docstring: ``{title: body lines}``.

    Parameters
    ----------
    doc : str or None
        The raw docstring (``func.__doc__``); None gives no sections.

    Returns
    -------
    dict of str to list of str
        Each section's title (``"Parameters"``, ``"Returns"``, ...) mapped to the lines between
        its dashed underline and the next section's title, indentation kept.
    """
    lines = inspect.cleandoc(doc or "").splitlines()
    out: dict[str, list[str]] = {}
    current: list[str] | None = None
    i = 0
    while i < len(lines):
        title = lines[i].strip()
        underline = lines[i + 1].strip() if i + 1 < len(lines) else ""
        if title and re.fullmatch(r"-{3,}", underline) and len(underline) >= len(title) - 1:
            current = out.setdefault(title, [])
            i += 2
            continue
        if current is not None:
            current.append(lines[i])
        i += 1
    return out


def documented_names(body: list[str]) -> list[str]:
    """The parameter names listed in the body of a ``Parameters`` section.

    Parameters
    ----------
    body : list of str
        The section's lines, as returned by :func:`sections`.

    Returns
    -------
    list of str
        The names in order, ``*``/``**`` prefixes kept (``"*args"``); ``"a, b : float"``
        gives ``["a", "b"]``.
    """
    entries = [line for line in body if line.strip()]
    if not entries:
        return []
    indent = min(len(line) - len(line.lstrip()) for line in entries)
    names: list[str] = []
    for line in entries:
        if len(line) - len(line.lstrip()) != indent:
            continue  # a description line
        head = line.strip().split(" : ", 1)[0].rstrip(" :")
        names.extend(n.strip() for n in head.split(",") if n.strip())
    return names


def signature_names(func: Callable) -> list[str]:
    """The parameters a docstring must document: ``*args``/``**kwargs`` spelled so, no self/cls.

    Parameters
    ----------
    func : callable
        A plain Python function (methods unwrapped from classmethod/staticmethod).

    Returns
    -------
    list of str
        Parameter names in signature order, without ``self``, ``cls`` and private (``_x``)
        ones.
    """
    names = []
    for p in inspect.signature(func).parameters.values():
        if p.name in ("self", "cls") or p.name.startswith("_"):
            continue
        prefix = {p.VAR_POSITIONAL: "*", p.VAR_KEYWORD: "**"}.get(p.kind, "")
        names.append(prefix + p.name)
    return names


def _private(name: str) -> bool:
    return name.lstrip("*").startswith("_")


def problems(
    func: Callable,
    *,
    module_level: bool,
    class_doc: str | None = None,
) -> list[str]:
    """What is wrong with the docstring of `func` under the rules of this module.

    Parameters
    ----------
    func : callable
        The function or (unwrapped) method to check.
    module_level : bool
        True for a public module-level function: its ``Parameters`` section is required as soon
        as it takes a parameter, and its ``Returns``/``Yields`` section unless it is annotated
        ``-> None``. False for a method: the section is required from two parameters on.
    class_doc : str or None
        For ``__init__``: the class docstring, whose ``Parameters`` section may document the
        constructor instead.

    Returns
    -------
    list of str
        One human-readable finding per defect; empty when the docstring is complete.
    """
    wanted = signature_names(func)
    secs = sections(func.__doc__)
    if "Parameters" not in secs and class_doc is not None:
        secs = {**sections(class_doc), **secs}
    found: list[str] = []
    if "Parameters" in secs:
        listed = documented_names(secs["Parameters"] + secs.get("Other Parameters", []))
        missing = [n for n in wanted if n not in listed]
        stale = [n for n in listed if n not in wanted and not _private(n)]
        if missing:
            found.append(f"parameters not documented: {missing}")
        if stale:
            found.append(f"documented but not in the signature: {stale}")
    elif wanted and (module_level or len(wanted) >= 2):
        found.append(f"no Parameters section (takes {wanted})")
    if module_level and not ({"Returns", "Yields"} & set(secs)):
        annotation = inspect.signature(func).return_annotation
        if annotation not in (None, "None"):
            found.append("no Returns section and not annotated -> None")
    return found


# --- what is public ------------------------------------------------------------------------------


def _hand_written(func: Callable) -> bool:
    """False for functions generated by dataclasses/enum (their code lives in ``<string>``)."""
    code = getattr(func, "__code__", None)
    return code is not None and Path(code.co_filename).resolve().is_relative_to(SRC)


def _modules() -> Iterator[object]:
    yield hallcal
    for info in pkgutil.walk_packages(hallcal.__path__, "hallcal."):
        yield importlib.import_module(info.name)


def public_callables() -> Iterator[tuple[str, Callable, bool, str | None]]:
    """Every public function and method, once: ``(qualified name, function, module_level,
    class docstring for __init__)``.

    Returns
    -------
    iterator of tuple
        As above; functions re-exported by a package are yielded once, under their defining
        module's name.
    """
    seen: set[int] = set()
    for module in _modules():
        for name in getattr(module, "__all__", []):
            obj = getattr(module, name, None)
            if inspect.isfunction(obj):
                obj = inspect.unwrap(obj)  # contextmanager & co. keep the original's docstring
            if id(obj) in seen:
                continue
            seen.add(id(obj))
            if inspect.isfunction(obj) and _hand_written(obj):
                yield f"{obj.__module__}.{obj.__qualname__}", obj, True, None
            elif inspect.isclass(obj) and obj.__module__.startswith("hallcal"):
                init = vars(obj).get("__init__")
                generated = not (inspect.isfunction(init) and _hand_written(init))
                if generated and "Parameters" in sections(obj.__doc__):
                    # a dataclass documenting its generated (or inherited) constructor
                    yield f"{obj.__module__}.{obj.__qualname__}", obj.__init__, False, obj.__doc__
                for mname, member in vars(obj).items():
                    if mname.startswith("_") and mname != "__init__":
                        continue
                    if isinstance(member, (classmethod, staticmethod)):
                        member = member.__func__
                    if inspect.isfunction(member):
                        member = inspect.unwrap(member)
                    if inspect.isfunction(member) and _hand_written(member):
                        class_doc = obj.__doc__ if mname == "__init__" else None
                        qual = f"{obj.__module__}.{member.__qualname__}"
                        yield qual, member, False, class_doc


def all_problems() -> dict[str, list[str]]:
    """``{qualified name: findings}`` for every public callable with a finding.

    Returns
    -------
    dict of str to list of str
        Empty when every public docstring follows the rules.
    """
    out = {}
    for qual, func, module_level, class_doc in public_callables():
        found = problems(func, module_level=module_level, class_doc=class_doc)
        if found:
            out[qual] = found
    return out


# --- the checks ----------------------------------------------------------------------------------


def test_every_public_function_documents_its_parameters_and_result():
    found = all_problems()
    report = "\n".join(f"{q}: {'; '.join(f)}" for q, f in sorted(found.items()))
    assert found == {}, "incomplete numpydoc:\n" + report


def test_the_walk_finds_the_public_api():
    names = {q for q, *_ in public_callables()}
    assert len(names) > 250
    assert "hallcal.api.calibrate" in names  # reached through the lazy front door as well
    assert "hallcal.sim.lti.ContinuousTF.discretize" in names  # a public method
    assert "hallcal.sensor.lut.LUT.from_arrays" in names  # a classmethod
    assert "hallcal.io.files.atomic_write" in names  # a context manager, unwrapped
    assert not any(q.endswith("BenchConfig.__init__") for q in names)  # dataclass-generated


def _planted_missing(y0, d, *, n_m=11):
    """Planted defect: `n_m` is not documented.

    Parameters
    ----------
    y0 : numpy.ndarray
        Mechanical angle [rad].
    d : numpy.ndarray
        Hall signals.

    Returns
    -------
    float
        Nothing useful.
    """
    return 0.0


def _planted_stale(y0):
    """Planted defect: documents a parameter it no longer takes, and no Returns.

    Parameters
    ----------
    y0 : numpy.ndarray
        Mechanical angle [rad].
    theta : numpy.ndarray
        Gone from the signature.
    """
    return y0


def _planted_good(y0, d, *args, _hook=None, **kwargs) -> None:
    """Complete.

    Parameters
    ----------
    y0, d : numpy.ndarray
        Mechanical angle [rad] and Hall signals.
    *args
        Ignored.
    **kwargs
        Ignored.
    """


def _planted_no_section(y0) -> None:
    """No Parameters section at all."""


class _Planted:
    def one(self, y0):
        """One parameter: may go without a section."""

    def two(self, y0, d):
        """Two parameters: needs a section."""


@pytest.mark.parametrize(
    ("func", "module_level", "expected"),
    [
        (_planted_missing, True, ["parameters not documented: ['n_m']"]),
        (
            _planted_stale,
            True,
            [
                "documented but not in the signature: ['theta']",
                "no Returns section and not annotated -> None",
            ],
        ),
        (_planted_good, True, []),
        (_planted_no_section, True, ["no Parameters section (takes ['y0'])"]),
        (_Planted.one, False, []),
        (_Planted.two, False, ["no Parameters section (takes ['y0', 'd'])"]),
    ],
)
def test_the_checker_catches_planted_defects(func, module_level, expected):
    assert problems(func, module_level=module_level) == expected


def test_a_dataclass_docstring_is_checked_against_its_fields():
    @dataclasses.dataclass
    class Planted:
        """A result.

        Parameters
        ----------
        y0 : float
            Mechanical angle [rad].
        eta : float
            No longer a field.
        """

        y0: float
        d: float

    found = problems(Planted.__init__, module_level=False, class_doc=Planted.__doc__)
    assert found == [
        "parameters not documented: ['d']",
        "documented but not in the signature: ['eta']",
    ]


def test_an_init_may_be_documented_in_the_class_docstring():
    class Documented:
        """A class.

        Parameters
        ----------
        y0 : float
            Mechanical angle [rad].
        d : float
            A Hall signal.
        """

        def __init__(self, y0, d):
            self.y0, self.d = y0, d

    init = Documented.__init__
    assert problems(init, module_level=False, class_doc=Documented.__doc__) == []
    assert problems(init, module_level=False, class_doc=None) != []

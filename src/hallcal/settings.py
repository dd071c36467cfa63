"""The declarative schema of the setup file: one :class:`Setting` per key, declared once.

A key's type, accepted range or choices, default, unit and one-line meaning are declared where
its value lives: on the field of the spec dataclass that holds it (:func:`setting`, e.g.
:class:`hallcal.io.setup.ModelSpec`, :class:`hallcal.sim.bench_spec.BenchSpec`), or, for the
tables held by other types (top level, ``[controller]``, ``[plant]``), in a tuple of
:class:`Setting` in :mod:`hallcal.io.setup`. The same declaration drives the parser's checks and
its messages (:mod:`hallcal.io.setup`), the defaults of the bench
(:class:`hallcal.sim.bench.BenchConfig`) and the tables of ``docs/setup-reference.md``
(:func:`render_table`). This module declares and renders; it reads and writes nothing.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Literal

__all__ = [
    "REQUIRED",
    "Setting",
    "render_table",
    "setting",
    "settings_of",
    "toml_value",
]


class _Required:
    """The default of a key that has none (the setup must give it)."""

    def __repr__(self) -> str:
        return "REQUIRED"


#: Default of a required key.
REQUIRED: Any = _Required()

#: How the parser reads a key. "custom": the table's parser checks it itself (the schema still
#: gives its default, type text, accepted values and meaning).
Kind = Literal["integer", "number", "boolean", "choice", "numbers", "table", "custom"]

_KIND_TEXT = {
    "integer": "integer",
    "number": "number",
    "boolean": "boolean",
    "choice": "string",
    "table": "table",
}


@dataclass(frozen=True)
class Setting:
    """One key of the setup file.

    Attributes
    ----------
    name : str
        The key, as written in its table.
    kind : {"integer", "number", "boolean", "choice", "numbers", "table", "custom"}
        How it is read (see ``Kind``).
    default : object
        The value when the key is absent; :data:`REQUIRED` when it must be given.
    doc : str
        One line: what the key means (the reference's "meaning" column).
    unit : str
        Unit of the value ("" when it has none).
    minimum : float or None
        Smallest accepted value (integers and numbers; ``positive`` makes it exclusive 0).
    positive : bool
        The value must be > 0.
    limit : float or None
        hallcal's resource limit (:mod:`hallcal.limits`): a larger value (absolute value for
        numbers) is refused as "above the limit".
    choices : tuple of str
        Accepted strings of a "choice".
    length, max_length : int or None
        Exact and largest length of a "numbers" list.
    only : tuple of (str, str) or None
        ``(key, value)``: the key applies only when that key of the same table has that value.
    type_text : str
        The reference's type cell when the kind alone does not say it.
    accepts : str
        The reference's accepted-values cell when the range alone does not say it.
    default_text : str
        The reference's default cell when the default is not a value (``None``, a table).
    """

    name: str
    kind: Kind
    default: Any = REQUIRED
    doc: str = ""
    unit: str = ""
    minimum: float | None = None
    positive: bool = False
    limit: float | None = None
    choices: tuple[str, ...] = ()
    length: int | None = None
    max_length: int | None = None
    only: tuple[str, str] | None = None
    type_text: str = ""
    accepts: str = ""
    default_text: str = ""

    @property
    def required(self) -> bool:
        """Whether the setup must give the key."""
        return self.default is REQUIRED

    def type_cell(self) -> str:
        """The reference's "type, unit" cell."""
        if self.type_text:
            text = self.type_text
        elif self.kind == "numbers":
            text = "list of numbers" if self.length is None else f"list of {self.length} numbers"
        else:
            text = _KIND_TEXT[self.kind]
        return f"{text}, {self.unit}" if self.unit else text

    def default_cell(self) -> str:
        """The reference's default cell: the TOML literal, "required" or a stated text."""
        if self.default_text:
            return self.default_text
        if self.required:
            return "required"
        return f"`{toml_value(self.default)}`"

    def accepts_cell(self) -> str:
        """The reference's accepted-values cell, from the range unless stated."""
        if self.accepts:
            text = self.accepts
        elif self.kind == "boolean":
            text = "`true`, `false`"
        elif self.kind == "choice":
            text = ", ".join(f'`"{c}"`' for c in self.choices)
        elif self.kind == "table":
            text = f"see `[{self.name}]`"
        elif self.kind == "numbers":
            text = "finite"
        elif self.positive:
            text = "> 0"
        elif self.minimum is not None:
            text = f"≥ {self.minimum:g}"
        else:
            text = "any finite number"
        if self.only is not None:
            text += f"; only with `{self.only_text()}`"
        return text

    def only_text(self) -> str:
        """The condition under which the key applies, as TOML (``basis = "kernel"``)."""
        if self.only is None:
            return ""
        key, value = self.only
        return f"{key} = {toml_value(value)}"


def setting(default: Any = REQUIRED, **declaration: Any) -> Any:
    """A dataclass field that is a setup key: its default and its :class:`Setting`.

    Parameters
    ----------
    default : object
        The key's default (:data:`REQUIRED`: the field has no default either).
    **declaration
        The other attributes of :class:`Setting` (``kind`` at least); the name is the field's.

    Returns
    -------
    dataclasses.Field
    """
    meta = {"setting": Setting(name="", default=default, **declaration)}
    if default is REQUIRED:
        return dataclasses.field(metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def settings_of(spec: type) -> tuple[Setting, ...]:
    """The settings declared on the fields of a dataclass (:func:`setting`), in field order.

    Parameters
    ----------
    spec : type
        A dataclass whose setup keys are declared with :func:`setting`.

    Returns
    -------
    tuple of Setting
        One per declared field, named after it; fields without a declaration are left out.
    """
    return tuple(
        dataclasses.replace(f.metadata["setting"], name=f.name)
        for f in dataclasses.fields(spec)
        if "setting" in f.metadata
    )


def toml_value(value: Any) -> str:
    """The TOML literal of a setup value.

    Parameters
    ----------
    value : bool, int, float, str, or a list or tuple of them
        The value.

    Returns
    -------
    str
        Its TOML text (``true``, ``7.5e-06``, ``"auto"``, ``[1, 2]``).

    Raises
    ------
    TypeError
        For any other type.
    """
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def render_table(settings: Iterable[Setting]) -> str:
    """The reference's markdown table of one setup table (``docs/setup-reference.md``).

    Parameters
    ----------
    settings : iterable of Setting
        The table's keys, in the order they are listed.

    Returns
    -------
    str
        A markdown table (no trailing newline): key, type and unit, default, accepted values,
        meaning.
    """
    lines = [
        "| key | type, unit | default | accepted values | meaning |",
        "| --- | --- | --- | --- | --- |",
    ]
    for s in settings:
        cells = (f"`{s.name}`", s.type_cell(), s.default_cell(), s.accepts_cell(), s.doc)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)

"""The pieces a variant is assembled from: the context every builder gets, and optional sections.

A variant (float or fixed point) is its lean templates filled from a :class:`_Context`, plus the
optional :class:`Section` objects that apply to it (the anticogging feed-forward, the power-up
identification of the pole pair).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from hallcal.output.firmware import FirmwareDesign


@dataclass(frozen=True)
class Section:
    """An optional piece of a generated variant.

    Attributes
    ----------
    name : str
        Short name (reported in :attr:`ExportResult.sections`).
    header : str
        Declarations for the header (inside ``extern "C"``).
    source : str
        Definitions for the source file.
    notes : tuple of str
        Lines for the banner comment.
    hooks : mapping of str to str
        Text for the variant's insertion points (:data:`FLOAT_HOOKS`; the fixed-point variant
        has none), e.g. members of the state or another ``init``.
    """

    name: str
    header: str
    source: str
    notes: tuple[str, ...] = ()
    hooks: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class _Context:
    """What every piece of a variant needs."""

    artifact: Mapping[str, Any]
    design: FirmwareDesign
    pfx: str
    PFX: str
    variant: str  # "float" or "fixed"
    subs: Mapping[str, Any] = field(default_factory=dict)  # the lean templates' substitutions
    powerup: Any = None  # hallcal.output.firmware.PowerUpFirmware
    adc_scale: float = 1.0  # ADC counts per unit of the artifact's Hall signals

"""What limits a table's predicted error, typed: the offset, a few harmonics, unmodelled motion.

The adequacy check (:func:`hallcal.fit.adequacy.assess`) finds what carries the predicted
variance of the table (:func:`hallcal.fit.adequacy.error_sources`: cov(theta) propagated to the
table's correction eta, :func:`hallcal.fit.sem.angle_error_gradient`) and the bias unmodelled
motion may put in it (:func:`hallcal.fit.adequacy.motion_bias`); the status policy
(:func:`hallcal.pipeline.verdict.decide`) chooses a refusal's remedies on
:attr:`ErrorSources.kinds` rather than on the wording of the phrase that names them. Kept apart
from the adequacy check so that the policy names the type without importing the numeric core.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

__all__ = ["ErrorSource", "ErrorSources"]


class ErrorSource(enum.StrEnum):
    """What carries the table's predicted error (:class:`ErrorSources`), so that a remedy is
    chosen on a type rather than on the wording of a message."""

    #: the table's constant offset (the phase of the fundamental), which only the start of the
    #: run informs
    OFFSET = "offset"
    #: a few flux harmonics of the basis (fewer harmonics, or a longer run, help)
    HARMONICS = "harmonics"
    #: unmodelled motion may have put part of the correction into poorly determined directions
    #: (:func:`hallcal.fit.adequacy.motion_bias`)
    MOTION = "motion"


@dataclass(frozen=True)
class ErrorSources:
    """What limits the table's predicted error: the shares of its variance the covariance puts
    on the offset and on a few harmonics (:func:`hallcal.fit.adequacy.error_sources`) and, with
    unmodelled motion, the bias the motion may carry (:func:`hallcal.fit.adequacy.motion_bias`).

    Attributes
    ----------
    offset_share : float
        Share of the predicted variance carried by the table's constant offset; 0 when it is
        under a quarter (not named).
    harmonics : tuple of int
        The fewest harmonics (at most three) that carry at least half of it, () when none do.
    harmonics_share : float
        The share they carry (0 when ``harmonics`` is empty).
    motion_cost : float
        The cost ratio (cost over its noise level) when unmodelled motion is counted, NaN else.
    motion_bias : float
        RMS [rad] of the correction the motion may have put in poorly determined directions
        (counted in the predicted error); 0: none.
    """

    offset_share: float = 0.0
    harmonics: tuple[int, ...] = ()
    harmonics_share: float = 0.0
    motion_cost: float = math.nan
    motion_bias: float = 0.0

    @property
    def kinds(self) -> frozenset[ErrorSource]:
        """The sources named (empty when nothing stands out)."""
        named = {
            ErrorSource.OFFSET: self.offset_share > 0.0,
            ErrorSource.HARMONICS: bool(self.harmonics),
            ErrorSource.MOTION: self.motion_bias > 0.0,
        }
        return frozenset(k for k, on in named.items() if on)

    @property
    def text(self) -> str:
        """One phrase for the user, e.g. "the table's constant offset carries 45 % of it;
        harmonics 16, 17, 18 carry 80 %" ("" when nothing stands out); the motion's bias
        first."""
        parts = []
        if self.motion_bias > 0.0:
            parts.append(
                f"unmodelled motion (cost {self.motion_cost:.3g}x the noise level) may have put "
                f"{1e3 * self.motion_bias:.3g} mrad RMS of the correction into directions the "
                "run determines poorly (counted in the predicted error)"
            )
        if self.offset_share > 0.0:
            parts.append(
                f"the table's constant offset carries {100 * self.offset_share:.0f} % of it"
            )
        if self.harmonics:
            many = len(self.harmonics) > 1
            named = ", ".join(str(v) for v in self.harmonics)
            parts.append(f"harmonic{'s' if many else ''} {named} carr{'y' if many else 'ies'} "
                         f"{100 * self.harmonics_share:.0f} %")  # fmt: skip
        return "; ".join(parts)

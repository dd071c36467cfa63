"""Numeric design of the generated firmware: the lean table, plausibility windows, error budget.

:mod:`hallcal.output.codegen` writes C; this module decides the numbers it writes, so that they
can be checked here without a C compiler:

* :func:`design_firmware` reads a calibration artifact (checked by the one validator,
  :func:`hallcal.io.validate_artifact`) and returns a :class:`FirmwareDesign`:
  the correction table resampled to a uniform grid over one mechanical revolution, the
  plausibility windows of the samples, the step limit and the error budget.
* The correction table: the cheapest (:func:`hallcal.sensor.firmware_tables.choose_table`)
  whose difference to the artifact's interpolant is within the budget: a tenth of the
  calibration's noise floor (so the table adds at most 0.5 % to the RMS error in quadrature),
  and never more than 1e-5 rad. Its numerics (least squares, exact error, int16/int8 rounding)
  live in the numeric core, :mod:`hallcal.sensor.firmware_tables`.
* The anticogging table (:func:`cogging_table`, :func:`hallcal.sim.cogging.tabulate`) and the
  power-up decoder's single-precision numbers (:func:`design_powerup`).
* Plausibility (:class:`Plausibility`, :mod:`hallcal.output.plausibility`): the channel
  ranges, the alpha/beta radius window, the consistency window along the projection's null
  vector, and the step rule with its fault count.

Units: angles in rad unless a name says turns (1 turn = 2 pi rad); "electrical" angles are
n_m times the mechanical ones. Hall signals are in the artifact's unit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from hallcal._constants import DEFAULT_FAULT_AFTER, DEFAULT_TOLERANCE, TWO_PI
from hallcal.errors import HallcalInputError
from hallcal.io.artifact import ArtifactData, validate_artifact
from hallcal.messages import Outcome
from hallcal.output.plausibility import (
    DEFAULT_SPEED,
    Plausibility,
    _plausibility,
)
from hallcal.sensor.absolute import (
    GRID_CHOICES,
    IdentifiabilityReport,
    PowerUpDecoder,
)
from hallcal.sensor.firmware_tables import (
    MAX_TABLE_POINTS,
    CorrectionTable,
    choose_table,
    exp2_poly,
    fit_table,
    newton_seed,
    newton_steps,
    table_sizes,
    tangent_range,
)
from hallcal.sensor.flux import FluxModel
from hallcal.sensor.lut import LUT
from hallcal.sim.cogging import CoggingTable, CoggingTorque, tabulate

__all__ = [
    "DEFAULT_BUDGET",
    "DEFAULT_FAULT_AFTER",
    "DEFAULT_SPEED",
    "DEFAULT_TOLERANCE",
    "table_sizes",
    "MAX_TABLE_POINTS",
    "CorrectionTable",
    "FirmwareDesign",
    "Plausibility",
    "PowerUpCode",
    "PowerUpFirmware",
    "design_firmware",
    "cogging_table",
    "design_powerup",
    "fit_table",
]

#: Budget for the table's difference to the artifact's interpolant [rad] when the artifact
#: states no noise floor.
DEFAULT_BUDGET = 1e-6
#: Budget never above this [rad] (the acceptance bound of the firmware against Python).
MAX_BUDGET = 1e-5
#: Fraction of the noise floor the table may use.
BUDGET_FRACTION = 0.1


@dataclass(frozen=True)
class FirmwareDesign:
    """Everything the generated C needs, in double precision.

    Attributes
    ----------
    pole_pairs : int
    projection : ndarray, shape (2, 3)
    offset : ndarray, shape (3,)
    rejects_common_mode : bool
        Whether each row of the projection sums to zero (then the firmware rejects a common
        mode exactly).
    lut : LUT
        The artifact's table (the reference: ``hallcal reconstruct``).
    table : CorrectionTable
    plausibility : Plausibility
    noise_floor : float or None
        RMS angle error the Hall noise causes [rad], from the artifact.
    budget : float
        What the table may differ from the artifact's interpolant [rad].
    sample_time : float
        From the artifact's setup [s] (1.0: time in samples).
    sha256 : str
        Of the artifact's canonical JSON.
    messages : tuple of str
    flux : FluxModel or None
        The artifact's flux model (the power-up decoder's tables come from it).
    """

    pole_pairs: int
    projection: NDArray[np.float64]
    offset: NDArray[np.float64]
    rejects_common_mode: bool
    lut: LUT
    table: CorrectionTable
    plausibility: Plausibility
    noise_floor: float | None
    budget: float
    sample_time: float
    sha256: str
    messages: tuple[str, ...] = ()
    flux: FluxModel | None = None


# --------------------------------------------------------------------------------------------
# Reading the artifact
# --------------------------------------------------------------------------------------------


def _bad(source: str, key: str, why: str) -> HallcalInputError:
    return HallcalInputError(f"{source}: key '{key}' {why}")


def _lut(art: ArtifactData, source: str) -> LUT:
    """The artifact's table; the firmware keeps y_star within half a turn of f_init's
    revolution, so it takes corrections below pi/2 only (the validator allows up to pi)."""
    if np.max(np.abs(art.eta)) >= math.pi / 2:
        raise _bad(
            source, "lut.eta", "has corrections of pi/2 rad or more (the firmware takes less)"
        )
    return art.lut()


def _noise_floor(diag: Mapping[str, Any]) -> float | None:
    """The calibration's noise floor [rad] (closed loop, or the constant-speed estimate)."""
    value = diag.get("noise_floor")
    if value is None and isinstance(diag.get("constant_speed"), Mapping):
        value = diag["constant_speed"].get("angle_noise_floor")
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    value = float(value)
    return value if math.isfinite(value) and 0.0 < value < 1.0 else None


# --------------------------------------------------------------------------------------------
# The design
# --------------------------------------------------------------------------------------------


def _check_options(tolerance: float, fault_after: int, max_speed: float | None) -> None:
    if isinstance(tolerance, bool) or not (0.0 <= float(tolerance) <= 0.9):
        raise HallcalInputError(f"tolerance must be in [0, 0.9], got {tolerance!r}")
    if (
        isinstance(fault_after, bool)
        or not isinstance(fault_after, int)
        or not (4 <= fault_after <= 1000)
    ):
        raise HallcalInputError(f"fault_after must be an integer in 4..1000, got {fault_after!r}")
    if max_speed is not None and not (math.isfinite(max_speed) and max_speed > 0.0):
        raise HallcalInputError(f"max_speed must be a positive number, got {max_speed!r}")


def _table(lut: LUT, table_points: int | None, budget: float) -> tuple[CorrectionTable, list[str]]:
    """The table of ``table_points`` intervals, or the cheapest within the budget; and what to
    say about its size or its error."""
    n = lut.pole_pairs
    if table_points is not None:
        if (
            isinstance(table_points, bool)
            or not isinstance(table_points, int)
            or table_points not in table_sizes(n)
        ):
            raise HallcalInputError(
                f"table_points must be n_m 2^k in 64..{MAX_TABLE_POINTS} ({n} 2^k here), "
                f"got {table_points!r}"
            )
        table = fit_table(lut, table_points, quadratic=True)
        if table.error > budget:
            return table, [
                f"table of {table_points} points differs by {table.error:.2g} rad from the "
                f"calibration, more than the budget {budget:.2g} rad"
            ]
        return table, []
    table = choose_table(lut, budget)
    if table.error > budget:
        return table, [
            f"even {table.points} points differ by {table.error:.2g} rad from the "
            f"calibration, more than the budget {budget:.2g} rad"
        ]
    if table.nbytes > 4096:
        return table, [
            f"the budget {budget:.2g} rad needs {table.points} points ({table.nbytes} bytes)"
        ]
    return table, []


def design_firmware(
    artifact: Mapping | ArtifactData,
    *,
    source: str = "<calibration artifact>",
    table_points: int | None = None,
    tolerance: float = DEFAULT_TOLERANCE,
    max_speed: float | None = None,
    fault_after: int = DEFAULT_FAULT_AFTER,
    sha256: str = "",
) -> FirmwareDesign:
    """Decide the numbers of the generated firmware from a calibration artifact.

    Parameters
    ----------
    artifact : mapping or ArtifactData
        The artifact as read from JSON (``"format": "hallcal-calibration/1"``), checked here by
        :func:`hallcal.io.validate_artifact`, or its checked view.
    source : str, keyword-only
        Name of the artifact for error messages.
    table_points : int, keyword-only
        M = n_m 2^k (64..16384, a quadratic table); default the cheapest table within the
        budget.
    tolerance : float, keyword-only
        Relative widening of the calibrated amplitude windows, in [0, 0.9].
    max_speed : float, keyword-only
        Largest mechanical speed [rad/s] (with the setup's ``sample_time``); None: the default
        speed limit of 22.5 electrical degrees per sample.
    fault_after : int, keyword-only
        Consecutive rejected samples before the fault flag, 4..1000 (single glitches hold at
        most two samples; fewer when that count could alias, see :func:`alias_holds`).
    sha256 : str, keyword-only
        The artifact's hash, carried into the design.

    Returns
    -------
    FirmwareDesign

    Raises
    ------
    HallcalInputError
        An artifact the validator refuses (the key named), corrections the firmware cannot
        take, a sensor map without a usable amplitude window, or an option out of range.
    """
    art = validate_artifact(artifact, source)
    _check_options(tolerance, fault_after, max_speed)
    n, P, o = art.pole_pairs, art.projection, art.offset
    lut = _lut(art, source)
    flux = art.flux()
    floor = _noise_floor(art.diagnostics)
    ts = art.setup.sample_time
    rows = np.abs(P.sum(axis=1))
    rejects = bool(np.all(rows <= 1e-9 * np.abs(P).sum(axis=1)))

    messages: list[str] = []
    budget = DEFAULT_BUDGET if floor is None else min(BUDGET_FRACTION * floor, MAX_BUDGET)
    if floor is None:
        messages.append(f"the artifact states no noise floor: table budget {DEFAULT_BUDGET:g} rad")
    table, table_messages = _table(lut, table_points, budget)
    messages += table_messages
    plaus = _plausibility(flux, n, P, o, floor, float(tolerance), max_speed, ts, fault_after,
                          source)  # fmt: skip
    if plaus.fault_after < fault_after != DEFAULT_FAULT_AFTER:  # the default: the banner says it
        messages.append(
            f"the fault flag latches after {plaus.fault_after} rejected samples in a row, not "
            f"{fault_after}: after a longer outage a rotor at up to twice the speed limit "
            "could be a pole pitch off"
        )
    return FirmwareDesign(
        pole_pairs=n,
        projection=P,
        offset=o,
        rejects_common_mode=rejects,
        lut=lut,
        table=table,
        plausibility=plaus,
        noise_floor=floor,
        budget=budget,
        sample_time=ts,
        sha256=sha256,
        messages=tuple(messages),
        flux=flux,
    )


def cogging_table(
    cogging: Mapping[str, Any], *, source: str = "<calibration artifact>"
) -> CoggingTable:
    """Tabulate the artifact's cogging map for the firmware (:func:`hallcal.sim.cogging.tabulate`).

    ``cogging`` is the artifact's ``"cogging"`` entry as :func:`hallcal.io.validate_artifact`
    checks it (distinct orders >= 0, one ``a`` and ``b`` per order).

    Parameters
    ----------
    cogging : mapping
        The artifact's ``"cogging"`` entry.
    source : str, keyword-only
        Name of the artifact for error messages.

    Returns
    -------
    CoggingTable

    Raises
    ------
    HallcalInputError
        No orders, coefficients single precision cannot hold, or no table up to 65536 points
        reaches the accuracy (the key named).
    """
    a = np.array(cogging["a"], dtype=np.float64)
    b = np.array(cogging["b"], dtype=np.float64)
    if a.size and float(np.max(np.abs(np.concatenate([a, b])))) > 1e30:
        raise _bad(source, "cogging.a", "has an implausible scale")
    try:
        return tabulate(CoggingTorque(tuple(int(v) for v in cogging["orders"]), a, b))
    except ValueError as exc:
        raise _bad(source, "cogging.orders", str(exc)) from None


# --------------------------------------------------------------------------------------------
# Power-up identification of the pole pair (artifact key "identifiability")
# --------------------------------------------------------------------------------------------

#: Largest decoder table the exporter writes (points of each of R and Z).
MAX_POWERUP_TABLE = 65536
#: The exponent of 2^-x is built from its bits for x < this; beyond, the term is dropped
#: (it is below 2^-126, against a lock threshold of at least 2^-40).
EXP2_CUT = 126


class PowerUpCode(Outcome):
    """Whether the exported float variant identifies the pole pair at power-up."""

    EMITTED = "emitted"  # the decoder is in the float variant
    NO_ANALYSIS = "no_analysis"  # the artifact has no "identifiability" entry
    NOT_IDENTIFIABLE = "not_identifiable"  # the analysis says the magnets are too alike
    UNSUPPORTED = "unsupported"  # a grid the C cannot index with shifts, or a huge table
    SINGLE_POLE_PAIR = "single_pole_pair"  # nothing to identify: f_init's frame is absolute
    DISABLED = "disabled"  # left out on request (export_c(powerup=False), --no-powerup)


@dataclass(frozen=True)
class PowerUpFirmware:
    """The numbers of the power-up decoder in the float variant (module doc of
    :mod:`hallcal.sensor.absolute`, "Decoder specification").

    Costs are in noise-sigma units: every length (rho, zeta, R, Z) is divided by ``sigma``, the
    Gram terms multiplied by ``sigma^2``, so the numbers of the C are of order 1 to 10^5 and a
    sample's cost is the Python reference's exactly (in exact arithmetic).

    Attributes
    ----------
    status : PowerUpCode
    message : str
        One line: the verdict, or why no decoder is written.
    report : IdentifiabilityReport or None
        The artifact's analysis.
    decoder : PowerUpDecoder or None
        The Python decoder it was built from (``reconstruct --absolute`` rebuilds the same).
    sigma : float
        Noise sigma the costs are normalized by (artifact unit).
    radius, zero : ndarray of float32, shape (M + 1,)
        R[q] / sigma and Z[q] / sigma, the last entry repeating the first (wrap-around).
    null : ndarray, shape (3,)
        nv / sigma; ``zeta = null . d - null_offset`` in sigmas.
    null_offset : float
        nv . o / sigma.
    gram_a, gram_b, gram_c :
        A sigma^2 (2 x 2), B sigma^2 (2), C sigma^2.
    rsqrt_seed : tuple of float
        ``c0 - c1 r2`` approximates 1/sqrt(r2) on the amplitude window ``rsqrt_window``.
    rsqrt_steps : int
        Newton steps ``y (3/2 - r2 y^2 / 2)`` after the seed.
    rsqrt_error : float
        Relative error after them (before rounding).
    tangent_window : tuple of float
        Range of tt = t' S t over all table positions (sigmas^2 per electrical rad^2), widened.
    tangent_seed, tangent_steps, tangent_error :
        Seed ``c0 - c1 tt`` of 1/tt, Newton steps ``r (2 - tt r)``, relative error after them.
    slope : float
        L / (2 pi): table intervals per electrical rad.
    cost_cap, threshold : float
        The censoring level c and the lock threshold alpha / (1 - alpha).
    exp2 : ndarray
        Polynomial of 2^-f on [0, 1] (ascending powers).
    exp2_error : float
        Its largest relative error.
    """

    status: PowerUpCode
    message: str
    report: IdentifiabilityReport | None = None
    decoder: PowerUpDecoder | None = field(default=None, repr=False)
    sigma: float = 0.0
    radius: NDArray[np.float32] = field(default_factory=lambda: np.zeros(0, np.float32), repr=False)
    zero: NDArray[np.float32] = field(default_factory=lambda: np.zeros(0, np.float32), repr=False)
    null: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3), repr=False)
    null_offset: float = 0.0
    gram_a: NDArray[np.float64] = field(default_factory=lambda: np.zeros((2, 2)), repr=False)
    gram_b: NDArray[np.float64] = field(default_factory=lambda: np.zeros(2), repr=False)
    gram_c: float = 0.0
    rsqrt_seed: tuple[float, float] = (0.0, 0.0)
    rsqrt_window: tuple[float, float] = (0.0, 0.0)
    rsqrt_steps: int = 0
    rsqrt_error: float = 0.0
    tangent_window: tuple[float, float] = (0.0, 0.0)
    tangent_seed: tuple[float, float] = (0.0, 0.0)
    tangent_steps: int = 0
    tangent_error: float = 0.0
    slope: float = 0.0
    cost_cap: float = 0.0
    threshold: float = 0.0
    exp2: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0), repr=False)
    exp2_error: float = 0.0

    @property
    def emitted(self) -> bool:
        return self.status.success

    @property
    def pole_pairs(self) -> int:
        return 0 if self.decoder is None else self.decoder.pole_pairs

    @property
    def grid(self) -> int:
        """L, table points per electrical period."""
        return 0 if self.decoder is None else self.decoder.grid

    @property
    def table_bytes(self) -> int:
        """Flash of the two float tables (M + 1 points each)."""
        return 8 * int(self.radius.size)


def design_powerup(
    artifact: Mapping | ArtifactData,
    design: FirmwareDesign,
    *,
    source: str = "<calibration artifact>",
) -> PowerUpFirmware:
    """Decide whether the float variant identifies the pole pair at power-up, and its numbers.

    No decoder (and the homing API) when the artifact has no ``"identifiability"`` entry, when
    its verdict is "not identifiable", or when its grid is not a power of two or its tables
    would pass :data:`MAX_POWERUP_TABLE` points; none either for one pole pair, where f_init
    from y = 0 already gives the calibration's frame (modulo one revolution). The decoder is
    the one ``hallcal reconstruct --absolute`` rebuilds from the same artifact
    (:meth:`IdentifiabilityReport.decoder`), so its tables are bit-identical to Python's before
    the conversion to single precision.

    Parameters
    ----------
    artifact : mapping or ArtifactData
        The parsed calibration artifact (checked by :func:`hallcal.io.validate_artifact`), or
        its checked view.
    design : FirmwareDesign
        The correction table's design (pole pairs, projection, flux model).
    source : str, keyword-only
        Name of the artifact in error messages.

    Returns
    -------
    PowerUpFirmware
        The verdict (a :class:`PowerUpCode`) and, when a decoder is written, its constants and
        tables in noise-sigma units.

    Raises
    ------
    HallcalInputError
        The artifact is refused by :func:`hallcal.io.validate_artifact`, or its
        ``"identifiability"`` entry is malformed (named).
    """
    entry = validate_artifact(artifact, source).data.get("identifiability")
    if entry is None:
        return PowerUpFirmware(
            PowerUpCode.NO_ANALYSIS,
            "the artifact has no identifiability analysis (made before power-up identification "
            "existed; calibrate again)",
        )
    try:
        report = IdentifiabilityReport.from_dict(entry)
    except ValueError as exc:
        raise HallcalInputError(f"{source}: {exc}") from None
    no_decoder = _without_decoder(report, design)
    if no_decoder is not None:
        return no_decoder
    if not (math.isfinite(report.noise_std) and report.noise_std > 0.0):
        raise _bad(source, "identifiability.noise_std", "must be a positive number")
    if design.flux is None:  # pragma: no cover - design_firmware always sets it
        raise ValueError("the design has no flux model")
    try:
        dec = report.decoder(design.flux, design.lut)
    except ValueError as exc:
        raise HallcalInputError(f"{source}: identifiability: {exc}") from None
    return _decoder_numbers(report, dec, design.plausibility, source)


def _without_decoder(
    report: IdentifiabilityReport, design: FirmwareDesign
) -> PowerUpFirmware | None:
    """Why the float variant gets no decoder (one pole pair, the verdict, a grid or tables the
    C cannot take), or None."""
    if design.pole_pairs == 1:
        return PowerUpFirmware(
            PowerUpCode.SINGLE_POLE_PAIR,
            "one pole pair: f_init from y = 0 is in the frame of the calibration after any "
            "power-up (init with revolutions 0 and angle 0)",
            report,
        )
    if not report.status.success:
        return PowerUpFirmware(PowerUpCode.NOT_IDENTIFIABLE, report.message, report)
    L = report.grid
    if L not in GRID_CHOICES and not (4 <= L <= 65536 and L & (L - 1) == 0):
        return PowerUpFirmware(
            PowerUpCode.UNSUPPORTED,
            f"the decoder's grid ({L} points per electrical period) is not a power of two",
            report,
        )
    if design.pole_pairs * L + 1 > MAX_POWERUP_TABLE:
        return PowerUpFirmware(
            PowerUpCode.UNSUPPORTED,
            f"the decoder's tables would have {design.pole_pairs * L} points, more than "
            f"{MAX_POWERUP_TABLE}",
            report,
        )
    return None


def _decoder_numbers(
    report: IdentifiabilityReport, dec: PowerUpDecoder, pl: Plausibility, source: str
) -> PowerUpFirmware:
    """The decoder's tables and metric in noise-sigma units, and the seeds and Newton steps of
    its reciprocals over the windows they see."""
    sigma = dec.noise_std
    s2 = sigma * sigma
    A, B, C = dec.gram_a * s2, dec.gram_b * s2, float(dec.gram_c * s2)
    radius = np.append(dec.radius, dec.radius[0]) / sigma
    zero = np.append(dec.zero, dec.zero[0]) / sigma
    if (
        not (np.all(np.isfinite(radius)) and np.all(np.isfinite(zero)))
        or float(np.max(np.abs(np.concatenate([radius, zero])))) > 1e30
    ):
        raise _bad(source, "identifiability.noise_std", "is implausible for the signals")
    # 1/sqrt(r2) on the amplitude window the lean code admits
    w_lo, w_hi = pl.radius_lo**2, pl.radius_hi**2
    c0, c1, e0 = newton_seed(w_lo, w_hi, root=True)
    rs_steps, rs_err = newton_steps(e0, 1.5 + e0)
    # 1/tt on the range of tt over the table, widened by 10 % both ways
    t_lo, t_hi = tangent_range(dec, sigma, A, B, C)
    t_lo, t_hi = 0.9 * t_lo, 1.1 * t_hi
    r0, r1, re0 = newton_seed(t_lo, t_hi)
    tt_steps, tt_err = newton_steps(re0, 1.0)
    poly, p_err = exp2_poly()
    return PowerUpFirmware(
        status=PowerUpCode.EMITTED,
        message=report.message,
        report=report,
        decoder=dec,
        sigma=sigma,
        radius=radius.astype(np.float32),
        zero=zero.astype(np.float32),
        null=dec.null / sigma,
        null_offset=float(dec.null @ dec.offset) / sigma,
        gram_a=A,
        gram_b=B,
        gram_c=C,
        rsqrt_seed=(c0, c1),
        rsqrt_window=(w_lo, w_hi),
        rsqrt_steps=rs_steps,
        rsqrt_error=rs_err,
        tangent_window=(t_lo, t_hi),
        tangent_seed=(r0, r1),
        tangent_steps=tt_steps,
        tangent_error=tt_err,
        slope=dec.grid / TWO_PI,
        cost_cap=float(dec.cost_cap),
        threshold=float(dec.lock_threshold),
        exp2=poly,
        exp2_error=p_err,
    )

"""Sanity checks before the expensive steps, each with the fix named.

A wrong pole-pair count, Hall columns in the wrong order or a controller and plant that do not
form a stable loop all make the simulation-error minimization fail after a long computation with
a message that points nowhere ("diverged", "not bijective"). These checks look at the data and the
setup first, in well under a second, and say what is wrong and what to change:

- :func:`check_pole_pairs`: the data reveal n_m. With a mechanical reference (the loop's reference
  ``r`` or an encoder ``y_ref``) the electrical cycles of the Hall signals per revolution of the
  reference are n_m; without one, the magnets' signature (each pole pair's slightly different
  amplitude and offset) repeats every n_m electrical cycles.
- :func:`check_direction`: the Hall angle must increase with the reference, or the loop as
  modelled has positive feedback (sensor columns in the other order than the drive's).
- :func:`check_loop`: the closed-loop poles of the discretized loop (exact zero-order hold with
  the input delay, :mod:`hallcal.sim.lti`) of ``[controller]`` and the plant.
- :func:`check_bla_fit`: the fitted plant model has no unstable poles and no poles the measured
  band cannot determine.
- :func:`check_recording`: the recording's own plausibility, before any of the above: the ``t``
  column against ``sample_time`` (:func:`check_sample_time`), the angle columns' unit against
  the Hall signals' electrical angle / n_m (:func:`check_angle_units`: degrees logged as rad),
  and whether the Hall signals move at all (:func:`check_hall_motion`).

Every check returns a typed result (:class:`CheckStatus`, a one-line message, the fix and the
setup key at fault); :meth:`Check.raise_if_failed` turns a failure into
:class:`~hallcal.errors.HallcalInputError` (exit status 2 on the command line).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from hallcal._constants import TWO_PI
from hallcal.errors import HallcalInputError
from hallcal.io.dataset import Dataset
from hallcal.messages import Message, MessageCode, Severity
from hallcal.sensor.reconstruction import f_init
from hallcal.sim.lti import ContinuousTF, DiscreteTF

if TYPE_CHECKING:  # the BLA module (scipy.optimize) is loaded only when a BLA is checked
    from hallcal.identify.parametric import ParametricBLA

__all__ = [
    "BLAFitCheck",
    "Check",
    "CheckStatus",
    "DirectionCheck",
    "LoopCheck",
    "PolePairCheck",
    "check_angle_units",
    "check_bla_fit",
    "check_direction",
    "check_hall_motion",
    "check_recording",
    "check_sample_time",
    "check_loop",
    "check_pole_pairs",
    "closed_loop_poles",
    "Signature",
    "pole_pairs_from_signature",
    "raise_if_failed",
]

#: |z| above 1 + this is an unstable closed-loop pole. A cancelled integrator (the paper's C(q)
#: has a zero at q = 1) gives |z| = 1 to about 1e-9 in the eigenvalues; 1e-6 is a mode that grows
#: by at most 10 % over 1e5 samples, the length of a calibration run.
UNSTABLE_MARGIN = 1e-6

#: A pole-pair estimate within this of an integer counts as that integer (tracking lag and
#: f_init's periodic error move the measured ratio by far less; a wrong count is off by >= 1).
INTEGER_TOLERANCE = 0.15

#: Minimum mechanical travel of the reference for the pole-pair check [revolutions]: over half a
#: revolution a count off by one differs by half an electrical cycle, far above the tracking lag.
MIN_REVOLUTIONS = 0.5

#: Significance (p-value of the F test) for the magnets' signature to override ``pole_pairs``,
#: and how much stronger than at ``pole_pairs`` it must be: at a multiple of the true count the
#: statistic is about the true one divided by the multiple (0.43 at 50 for 25 on the ring jig).
SIGNATURE_P_VALUE = 1e-6
SIGNATURE_RATIO = 2.0

#: Relative difference of the ``t`` column's median step from ``sample_time`` above which the
#: two disagree: a drive's logged time stamps jitter by far less than 2 % in the median, and a
#: wrong rate is off by a factor (2x, 10x, 1000x for ms).
SAMPLE_TIME_TOLERANCE = 0.02

#: Factor within which a column's travel, divided by the Hall angle / n_m, counts as one unit
#: factor (180/pi: degrees). The loop's tracking lag and a multisine's untracked part move the
#: ratio of r by tens of percent at most; the factors told apart (1, 57.3, 57.3 n_m) are 57x
#: apart, and a wrong pole-pair count gives a ratio n/n_true that is named by the pole-pair check.
UNIT_FACTOR_TOLERANCE = 1.3

#: The encoder y_ref and f_init's y measure the same rotor angle, so y_ref moves 1 (or -1) times
#: y; outside this factor it is in another unit (revolutions: 0.16, counts: hundreds and more).
#: A looser bound than for r, whose multisine part the loop does not track.
ENCODER_RATIO = 2.0

#: Least electrical travel of the Hall angle [rad] for the unit check: the Hall noise moves it by
#: a few mrad, so one radian determines a column's ratio to it within about 1 %.
MIN_HALL_TRAVEL = 1.0

#: Lag-1 autocorrelation of the Hall signals (offsets removed) below which they are noise around
#: a fixed point, i.e. the rotor stood still: white noise gives 0, a sinusoid sampled at 8 or more
#: samples per cycle cos(2 pi / 8) = 0.71 and more.
STANDSTILL_CORRELATION = 0.5

#: A fitted pole faster than this multiple of the highest measured frequency is not determined by
#: the data (its effect in the band is a small phase lag, which the delay can take as well).
FAR_POLE_FACTOR = 10.0


class CheckStatus(enum.StrEnum):
    """Outcome of a check: ``ok``, ``warning`` (go on, but look), ``failed`` or ``skipped``."""

    OK = "ok"
    WARNING = "warning"
    FAILED = "failed"
    SKIPPED = "skipped"

    @property
    def success(self) -> bool:
        """True unless the check failed."""
        return self is not CheckStatus.FAILED


@dataclass(frozen=True)
class Check:
    """Result of one check.

    Attributes
    ----------
    status : CheckStatus
    message : str
        What was found, one line.
    fix : str
        What to change (empty when nothing needs to change).
    key : str or None
        The setup key (dotted) or column at fault, if any.
    """

    status: CheckStatus
    message: str
    fix: str = ""
    key: str | None = None

    @property
    def body(self) -> str:
        """Message and fix as one line."""
        return self.message if not self.fix else f"{self.message}; {self.fix}"

    @property
    def text(self) -> str:
        """Message and fix as one line, labelled ``warning:`` for warnings."""
        return self.to_message().line() if self.status is CheckStatus.WARNING else self.body

    def to_message(self, code: MessageCode = MessageCode.PREFLIGHT_CHECK) -> Message:
        """The check for the user: a warning when it warned, else a note."""
        severity = Severity.WARNING if self.status is CheckStatus.WARNING else Severity.NOTE
        return Message(severity, code, self.body)

    def raise_if_failed(self, source: str | None = None) -> None:
        """Raise :class:`HallcalInputError` (with ``source`` first) when the check failed."""
        if self.status is CheckStatus.FAILED:
            text = self.text if source is None else f"{source}: {self.text}"
            raise HallcalInputError(text, key=self.key)


def raise_if_failed(checks: Iterable[Check], source: str | None = None) -> None:
    """Raise for the first failed check of ``checks``.

    Parameters
    ----------
    checks : iterable of Check
        Checks in the order they should be reported.
    source : str, optional
        The file the checks are about, named in the message.

    Raises
    ------
    HallcalInputError
        The first check whose status is FAILED (its message and fix).
    """
    for c in checks:
        c.raise_if_failed(source)


# ------------------------------------------------------------------------------------------------
# pole pairs and direction


@dataclass(frozen=True)
class PolePairCheck(Check):
    """Pole pairs measured in the data against ``pole_pairs`` of the setup.

    Attributes
    ----------
    pole_pairs : int
        The setup's n_m.
    estimate : float
        Measured electrical cycles per revolution (NaN when not measurable).
    suggested : int or None
        The count the data support, when it differs from ``pole_pairs``.
    electrical_cycles, revolutions : float
        Net electrical cycles of the Hall signals and revolutions of the reference (signed).
    method : str
        ``"reference r"``, ``"encoder y_ref"``, ``"magnet signature"`` or ``""``.
    """

    pole_pairs: int = 0
    estimate: float = math.nan
    suggested: int | None = None
    electrical_cycles: float = math.nan
    revolutions: float = math.nan
    method: str = ""


@dataclass(frozen=True)
class DirectionCheck(Check):
    """Whether the Hall angle moves the same way as the reference.

    Attributes
    ----------
    sign : int
        +1 same direction, -1 opposite, 0 unknown (no reference or no motion).
    """

    sign: int = 0


def _hall_matrix(dataset: Dataset) -> NDArray[np.float64]:
    d = np.asarray(dataset.d, dtype=np.float64)
    return d - np.mean(d, axis=0)  # raw ADC offsets cancel to first order


def unwrapped_electrical_angle(dataset: Dataset) -> NDArray[np.float64]:
    """Unwrapped electrical angle of the Hall signals (Clarke + atan2, offsets removed) [rad]."""
    return f_init(_hall_matrix(dataset), 1)


def _reference(dataset: Dataset) -> tuple[NDArray[np.float64], str] | None:
    """The mechanical reference of a recording: the encoder when logged, else r."""
    for name, method in (("y_ref", "encoder y_ref"), ("r", "reference r")):
        if name in dataset:
            return np.asarray(dataset[name], dtype=np.float64), method
    return None


@dataclass(frozen=True)
class _Slope:
    slope: float  # electrical rad per mechanical rad
    cycles: float
    revolutions: float
    method: str


def _electrical_per_mechanical(dataset: Dataset) -> _Slope | None:
    ref = _reference(dataset)
    if ref is None:
        return None
    mech, method = ref
    if mech.size < 8 or not np.all(np.isfinite(mech)):
        return None
    psi = unwrapped_electrical_angle(dataset)
    span = float(np.ptp(mech))
    if span / TWO_PI < MIN_REVOLUTIONS:
        return _Slope(math.nan, float(psi[-1] - psi[0]) / TWO_PI, span / TWO_PI, method)
    # least squares: psi = a + slope * mech (the loop's lag behind r is about constant on a ramp)
    m = mech - mech.mean()
    slope = float(np.dot(m, psi - psi.mean()) / np.dot(m, m))
    return _Slope(
        slope, float(psi[-1] - psi[0]) / TWO_PI, float(mech[-1] - mech[0]) / TWO_PI, method
    )


def check_pole_pairs(dataset: Dataset, pole_pairs: int) -> PolePairCheck:
    """Compare ``pole_pairs`` with the electrical cycles per revolution the data show.

    With a mechanical reference (``y_ref``, else ``r``) over at least half a revolution the
    electrical angle of the Hall signals is regressed on it: the slope is n_m (its sign the
    direction, :func:`check_direction`). Without one, the magnets' signature is used
    (:func:`pole_pairs_from_signature`). A count that differs from ``pole_pairs`` fails with the
    measured one suggested (or a warning when the measurement is not near an integer).

    Parameters
    ----------
    dataset : Dataset
        Columns d1..d3 and, if available, ``r`` or ``y_ref`` [rad, mechanical].
    pole_pairs : int
        The setup's n_m.

    Returns
    -------
    PolePairCheck
    """
    n = int(pole_pairs)
    fit = _electrical_per_mechanical(dataset)
    if fit is None:
        return _signature_check(dataset, n)
    if not math.isfinite(fit.slope):
        return PolePairCheck(
            CheckStatus.SKIPPED,
            f"pole pairs not checked: the {fit.method} moves {abs(fit.revolutions):.2f} "
            f"revolutions (at least {MIN_REVOLUTIONS} needed)",
            pole_pairs=n,
            method=fit.method,
        )
    est = abs(fit.slope)
    where = (
        f"the Hall signals turn {abs(fit.cycles):.1f} electrical cycles while the {fit.method} "
        f"moves {abs(fit.revolutions):.2f} revolutions: {est:.2f} cycles per revolution"
    )
    common: dict[str, Any] = dict(
        pole_pairs=n,
        estimate=est,
        electrical_cycles=fit.cycles,
        revolutions=fit.revolutions,
        method=fit.method,
    )
    nearest = int(round(est))
    if abs(est - n) <= INTEGER_TOLERANCE:
        return PolePairCheck(CheckStatus.OK, f"pole pairs: {where}", **common)
    unit_hint = f" (or check that {fit.method.split()[-1]} is in mechanical rad)"
    if nearest >= 1 and abs(est - nearest) <= INTEGER_TOLERANCE:
        return PolePairCheck(
            CheckStatus.FAILED,
            f"pole_pairs = {n} does not match the data: {where}",
            f"set pole_pairs = {nearest}{unit_hint}",
            key="pole_pairs",
            suggested=nearest,
            **common,
        )
    return PolePairCheck(
        CheckStatus.WARNING,
        f"pole_pairs = {n} is not confirmed by the data: {where}",
        f"check pole_pairs and that the reference tracks the rotor{unit_hint}",
        key="pole_pairs",
        **common,
    )


def check_direction(dataset: Dataset) -> DirectionCheck:
    """The Hall angle must increase when the reference does (closed-loop recordings).

    The positive direction of f_init is the one in which the sensors' electrical phases follow
    the order d1, d2, d3. If the drive's firmware numbered its sensors differently, the recorded
    columns make f_init run against the reference and the loop as modelled has positive feedback.

    Parameters
    ----------
    dataset : Dataset
        A closed-loop recording with r and d1, d2, d3.

    Returns
    -------
    DirectionCheck
        OK (sign +1), FAILED (sign -1, with the fix) or SKIPPED when the reference does not
        move.
    """
    fit = _electrical_per_mechanical(dataset)
    if fit is None or not math.isfinite(fit.slope) or fit.slope == 0.0:
        return DirectionCheck(CheckStatus.SKIPPED, "direction not checked (no reference motion)")
    if fit.slope > 0:
        return DirectionCheck(
            CheckStatus.OK, "direction: the Hall angle follows the reference", sign=1
        )
    return DirectionCheck(
        CheckStatus.FAILED,
        f"the Hall angle runs against the {fit.method} ({fit.cycles:+.1f} electrical cycles while "
        f"it moves {fit.revolutions:+.2f} revolutions): the sensor order d1, d2, d3 is the reverse "
        "of the drive's",
        "swap two Hall columns (e.g. d2 and d3) so that the order matches the drive's f_init",
        key="d2",
        sign=-1,
    )


@dataclass(frozen=True)
class Signature:
    """How strongly the Hall signals' per-cycle features repeat with each period.

    Attributes
    ----------
    cycles : int
        Complete electrical cycles used.
    f_statistic : dict of int to float
        F statistic (between-group over within-group variance) for every period q tried.
    dof : dict of int to tuple of int
        Its degrees of freedom.
    """

    cycles: int
    f_statistic: dict[int, float]
    dof: dict[int, tuple[int, int]]

    @property
    def best(self) -> int | None:
        """The period with the largest F statistic."""
        return max(self.f_statistic, key=lambda q: self.f_statistic[q], default=None)

    def p_value(self, q: int) -> float:
        """p-value of the F test for period q (NaN if not tried)."""
        if q not in self.f_statistic:
            return math.nan
        from scipy.special import fdtrc  # survival function of the F distribution

        return float(fdtrc(*self.dof[q], self.f_statistic[q]))


def pole_pairs_from_signature(d: NDArray[np.float64]) -> Signature:
    """The period (in electrical cycles) of the magnets' signature in the Hall signals.

    Each pole pair of a real rotor is slightly different (strength, shape, position), so the
    peak-to-peak amplitude and the mean of each Hall signal over one electrical cycle repeat every
    n_m cycles. For each candidate period q (2 up to half the complete cycles: two revolutions are
    needed) the cycles are grouped by ``cycle mod q`` and the F statistic (between-group against
    within-group variance of six standardized features, a line removed from each first) says how
    strongly the features repeat with period q. Multiples of n_m repeat as well, but with more
    groups for the same structure, so the statistic peaks at n_m (measured on the ring jig:
    116-269 at 25 pole pairs, 50-118 at 50, at most 4 at other periods above 5).

    Parameters
    ----------
    d : ndarray, shape (N, 3)
        Hall signals (any offset and unit).

    Returns
    -------
    Signature
    """
    x = np.asarray(d, dtype=np.float64)
    x = x - x.mean(axis=0)
    psi = f_init(x, 1)
    if psi[-1] < psi[0]:
        psi = -psi
    cycle = np.floor((psi - psi[0]) / TWO_PI).astype(np.int64)
    ids = np.arange(int(cycle.min()) + 1, int(cycle.max()))  # complete cycles only
    if ids.size < 4:
        return Signature(int(ids.size), {}, {})
    order = np.argsort(cycle, kind="stable")
    bounds = np.searchsorted(cycle[order], np.concatenate([ids, [ids[-1] + 1]]))
    feats = np.empty((ids.size, 6))
    for i in range(ids.size):
        seg = x[order[bounds[i] : bounds[i + 1]]]
        if seg.shape[0] < 3:
            return Signature(int(ids.size), {}, {})
        feats[i, :3] = np.ptp(seg, axis=0)
        feats[i, 3:] = seg.mean(axis=0)
    # slow trends (speed, temperature) are not a signature: remove a line per feature
    t = np.arange(ids.size, dtype=np.float64)
    coef = np.polynomial.polynomial.polyfit(t, feats, 1)
    feats = feats - np.polynomial.polynomial.polyval(t, coef).T
    scale = feats.std(axis=0)
    feats = feats[:, scale > 0] / scale[scale > 0]
    n_cycles, n_feat = feats.shape
    f_stat: dict[int, float] = {}
    dof: dict[int, tuple[int, int]] = {}
    for q in range(2, n_cycles // 2 + 1):
        groups = np.arange(n_cycles) % q
        means = np.stack([feats[groups == g].mean(axis=0) for g in range(q)])
        within = float(np.sum((feats - means[groups]) ** 2))
        between = float(np.sum(np.bincount(groups)[:, None] * means**2))
        dof_b, dof_w = (q - 1) * n_feat, (n_cycles - q) * n_feat
        if within <= 0.0 or dof_w <= 0 or n_feat == 0:
            continue
        f_stat[q] = (between / dof_b) / (within / dof_w)
        dof[q] = (dof_b, dof_w)
    return Signature(int(n_cycles), f_stat, dof)


def _signature_check(dataset: Dataset, n: int) -> PolePairCheck:
    sig = pole_pairs_from_signature(np.asarray(dataset.d, dtype=np.float64))
    method = "magnet signature"
    best = sig.best
    common: dict[str, Any] = dict(pole_pairs=n, electrical_cycles=float(sig.cycles), method=method)
    if best is None:
        return PolePairCheck(
            CheckStatus.SKIPPED,
            "pole pairs not checked: no reference (r or y_ref) and fewer than 4 complete "
            "electrical cycles",
            **common,
        )
    if n not in sig.f_statistic:
        return PolePairCheck(
            CheckStatus.SKIPPED,
            f"pole pairs not checked: {sig.cycles} complete electrical cycles are fewer than two "
            f"revolutions at pole_pairs = {n}",
            **common,
        )
    f_best, f_n = sig.f_statistic[best], sig.f_statistic[n]
    p_best = sig.p_value(best)
    if best == n or p_best > SIGNATURE_P_VALUE or f_best < SIGNATURE_RATIO * f_n:
        return PolePairCheck(
            CheckStatus.OK,
            f"pole pairs: the magnets' signature repeats every {best} electrical cycles "
            f"(F = {f_best:.3g}; at {n}: {f_n:.3g})",
            estimate=float(best),
            **common,
        )
    return PolePairCheck(
        CheckStatus.FAILED,
        f"pole_pairs = {n} does not match the data: the magnets' signature (amplitude and offset "
        f"per electrical cycle) repeats every {best} cycles (F = {f_best:.3g}, "
        f"p {'< 1e-12' if p_best < 1e-12 else f'= {p_best:.1g}'}), "
        f"not every {n} (F = {f_n:.3g})",
        f"set pole_pairs = {best}",
        key="pole_pairs",
        estimate=float(best),
        suggested=best,
        **common,
    )


# ------------------------------------------------------------------------------------------------
# the recording itself: time stamps, angle units, motion


def check_sample_time(dataset: Dataset, sample_time: float | None) -> Check:
    """The ``t`` column against ``sample_time``: increasing, and stepping by it.

    Parameters
    ----------
    dataset : Dataset
        A recording; without a ``t`` column nothing is checked.
    sample_time : float or None
        The setup's T_s [s]; None or 1.0 (the setup's "rate unknown, times in samples") checks
        only that ``t`` increases.

    Returns
    -------
    Check
        FAILED (key ``t``) when ``t`` is constant or steps back anywhere (shuffled or reversed
        rows), FAILED (key ``sample_time``) when its median step differs from ``sample_time`` by
        more than :data:`SAMPLE_TIME_TOLERANCE`, naming both values; else OK or SKIPPED.
    """
    if "t" not in dataset or dataset.n_samples < 2:
        return Check(CheckStatus.SKIPPED, "sample time not checked: no t column")
    t = np.asarray(dataset["t"], dtype=np.float64)
    dt = np.diff(t)
    bad = dt <= 0.0
    if not np.any(dt != 0.0):
        return Check(
            CheckStatus.FAILED,
            f"the t column is constant (t = {t[0]:.6g} s in every row)",
            "log the time of each sample in t [s], or drop the column",
            key="t",
        )
    if np.any(bad):
        i = int(np.argmax(bad))
        how = (
            "decreases at every row (reversed?)"
            if np.all(dt < 0.0)
            else (f"steps back or stands still at {int(bad.sum())} of {dt.size} rows")
        )
        return Check(
            CheckStatus.FAILED,
            f"the t column is not increasing: it {how}, first at row {i + 2} "
            f"(t = {t[i]:.6g} -> {t[i + 1]:.6g} s)",
            "keep the rows in the order they were sampled (sort by t), or drop the column",
            key="t",
        )
    step = float(np.median(dt))
    if sample_time is None or sample_time == 1.0:
        return Check(CheckStatus.OK, f"sample time: the t column steps {step:.6g} s")
    ts = float(sample_time)
    if abs(step - ts) <= SAMPLE_TIME_TOLERANCE * ts:
        return Check(CheckStatus.OK, f"sample time: the t column steps {step:.6g} s = sample_time")
    ratio = step / ts
    hint = ""
    for factor, unit in ((1e3, "ms"), (1e6, "us")):
        if abs(ratio / factor - 1.0) <= SAMPLE_TIME_TOLERANCE:
            hint = f" (or t is in {unit}: log it in s)"
    return Check(
        CheckStatus.FAILED,
        f"sample_time = {ts:.6g} s in the setup, but the t column steps {step:.6g} s (median; "
        f"{ratio:.4g}x)",
        f"set sample_time = {step:.6g}{hint}",
        key="sample_time",
    )


def hall_lag_correlation(dataset: Dataset) -> float:
    """Lag-1 autocorrelation of the Hall signals with their means removed (channels pooled).

    About 0 when they are white noise around a fixed point (the rotor at rest), near 1 when the
    rotor turns (a sinusoid of m samples per cycle gives cos(2 pi / m)).

    Parameters
    ----------
    dataset : Dataset
        A recording with d1, d2, d3.

    Returns
    -------
    float
        The correlation, in [-1, 1] (0 for constant signals).
    """
    x = _hall_matrix(dataset)
    den = float(np.sum(x * x))
    return float(np.sum(x[1:] * x[:-1]) / den) if den > 0.0 else 0.0


def check_hall_motion(dataset: Dataset, *, lag_correlation: float | None = None) -> Check:
    """Whether the Hall signals move, or are noise around a fixed point (a standstill).

    Parameters
    ----------
    dataset : Dataset
        A recording with d1, d2, d3.
    lag_correlation : float, optional, keyword-only
        :func:`hall_lag_correlation` of ``dataset`` when the caller has it already.

    Returns
    -------
    Check
        FAILED (key ``d1``) when the lag-1 autocorrelation of the signals is below
        :data:`STANDSTILL_CORRELATION`: f_init of noise turns at random, so neither a rotation
        nor a calibration can be read from such a recording.
    """
    rho = hall_lag_correlation(dataset) if lag_correlation is None else lag_correlation
    if rho >= STANDSTILL_CORRELATION:
        return Check(CheckStatus.OK, f"the Hall signals move (lag-1 correlation {rho:.3f})")
    d = np.asarray(dataset.d, dtype=np.float64)
    level = ", ".join(f"{v:.4g}" for v in d.mean(axis=0))
    spread = ", ".join(f"{v:.2g}" for v in d.std(axis=0))
    return Check(
        CheckStatus.FAILED,
        f"the Hall signals do not move: they hold d = ({level}) with sample-to-sample noise "
        f"({spread} RMS; lag-1 correlation {rho:.2f}): the rotor stood still",
        "a calibration needs a run in which the rotor turns (docs/recording-guide.md)",
        key="d1",
    )


def _unit_name(ratio: float, pole_pairs: int) -> str | None:
    """The unit that a column moving ``ratio`` times the mechanical rad looks like, if any."""
    if not (math.isfinite(ratio) and ratio != 0.0):  # a column that does not move: no unit
        return None
    deg = 180.0 / math.pi
    for factor, name in ((deg, "degrees"), (deg * pole_pairs, "electrical degrees")):
        if pole_pairs >= 1 and abs(math.log(abs(ratio) / factor)) < math.log(UNIT_FACTOR_TOLERANCE):
            return name
    return None


def check_angle_units(
    dataset: Dataset,
    pole_pairs: int,
    *,
    columns: tuple[str, ...] = ("r", "y", "y_ref"),
    lag_correlation: float | None = None,
) -> Check:
    """The angle columns must be in mechanical rad: their travel against the Hall angle / n_m.

    f_init of the Hall signals (:func:`unwrapped_electrical_angle`) divided by n_m is a mechanical
    angle in rad whatever the drive logged; each of ``columns`` present is regressed on it, and a
    slope near 180/pi (or 180 n_m / pi) is a column logged in degrees (electrical degrees). The
    columns are also compared with ``y`` directly (no n_m involved), so a column in another unit
    than ``y`` is found with a wrong ``pole_pairs`` too.

    Parameters
    ----------
    dataset : Dataset
    pole_pairs : int
        The setup's n_m.
    columns : tuple of str, keyword-only
        The angle columns to check (those absent are skipped).
    lag_correlation : float, optional, keyword-only
        :func:`hall_lag_correlation` of ``dataset`` when the caller has it already.

    Returns
    -------
    Check
        FAILED (key: the first column at fault) naming the column, the ratio and the fix;
        SKIPPED when the Hall signals do not move by :data:`MIN_HALL_TRAVEL` or stand still.
    """
    present = [c for c in columns if c in dataset]
    if not present or dataset.n_samples < 8:
        return Check(CheckStatus.SKIPPED, "angle units not checked: no angle column")
    rho = hall_lag_correlation(dataset) if lag_correlation is None else lag_correlation
    if rho < STANDSTILL_CORRELATION:
        return Check(CheckStatus.SKIPPED, "angle units not checked: the Hall signals stand still")
    psi = unwrapped_electrical_angle(dataset)
    if float(np.ptp(psi)) < MIN_HALL_TRAVEL:
        return Check(CheckStatus.SKIPPED, "angle units not checked: the rotor hardly moved")
    n = max(int(pole_pairs), 1)
    base = psi / n
    found: dict[str, float] = {}
    for c in present:
        ratio = _slope(np.asarray(dataset[c], dtype=np.float64), base)
        if _unit_name(ratio, n) is not None:
            found[c] = ratio
    if "y" in dataset and "y" not in found:
        y = np.asarray(dataset["y"], dtype=np.float64)
        for c in present:
            if c != "y" and c not in found and float(np.ptp(y)) > 0.0:
                ratio = _slope(np.asarray(dataset[c], dtype=np.float64), y)
                if _unit_name(ratio, 1) == "degrees":
                    found[c] = ratio
    if not found and "y_ref" in present and "y" in dataset and float(np.ptp(dataset["y"])) > 0.0:
        # the encoder and f_init measure the same rotor angle: slope 1 (+-1 mounted reversed)
        ratio = _slope(np.asarray(dataset["y_ref"], dtype=np.float64), dataset["y"])
        if math.isfinite(ratio) and not 1.0 / ENCODER_RATIO <= abs(ratio) <= ENCODER_RATIO:
            revs = abs(math.log(abs(ratio) * TWO_PI)) < math.log(UNIT_FACTOR_TOLERANCE)
            unit = "revolutions" if revs else "another unit (encoder counts?)"
            return Check(
                CheckStatus.FAILED,
                f"y_ref looks like {unit}: it moves {abs(ratio):.4g} times y (1 for mechanical "
                "rad)",
                "log the encoder angle y_ref in mechanical rad, like y",
                key="y_ref",
            )
    if not found:
        return Check(CheckStatus.OK, f"angle units: {', '.join(present)} in mechanical rad")
    first = next(iter(found))
    ratio = found[first]
    unit = _unit_name(ratio, n) or "degrees"
    others = [c for c in found if c != first]
    also = f" (so do {', '.join(others)})" if others else ""
    return Check(
        CheckStatus.FAILED,
        f"{first} looks like {unit}{also}: it moves {abs(ratio):.4g} times the Hall signals' "
        f"angle / pole_pairs ({n}), which is 1 for mechanical rad",
        f"log {', '.join(found)} in mechanical rad (multiply by pi/180"
        + (f" and divide by {n}" if unit == "electrical degrees" else "")
        + ")",
        key=first,
    )


def _slope(x: NDArray[np.float64], base: NDArray[np.float64]) -> float:
    """Least-squares slope of x on base (NaN when base does not vary)."""
    b = base - base.mean()
    den = float(np.dot(b, b))
    return float(np.dot(b, x - x.mean()) / den) if den > 0.0 else math.nan


def check_recording(
    dataset: Dataset,
    *,
    pole_pairs: int,
    sample_time: float | None,
    angles: tuple[str, ...] = ("r", "y", "y_ref"),
    motion: bool = False,
    lag_correlation: float | None = None,
) -> list[Check]:
    """The recording's plausibility checks, in the order a failure is reported.

    One entry point for ``calibrate``, ``bla``, ``inspect`` and ``reconstruct``: the ``t``
    column against ``sample_time`` (:func:`check_sample_time`), the Hall signals' motion when
    ``motion`` is asked for (:func:`check_hall_motion`) and the angle columns' unit
    (:func:`check_angle_units`). All take well under a second on a calibration run.

    Parameters
    ----------
    dataset : Dataset
    pole_pairs : int
        n_m of the setup or the artifact.
    sample_time : float or None
        T_s [s]; None skips the comparison with ``t`` (its order is still checked).
    angles : tuple of str, keyword-only
        The angle columns whose unit is checked.
    motion : bool, keyword-only
        Require the Hall signals to move (a calibration run).
    lag_correlation : float, optional, keyword-only
        :func:`hall_lag_correlation` of ``dataset`` when the caller has it already (computed
        at most once here otherwise).

    Returns
    -------
    list of Check
    """
    out = [check_sample_time(dataset, sample_time)]
    rho = lag_correlation
    if motion and {"d1", "d2", "d3"} <= set(dataset.names):
        rho = hall_lag_correlation(dataset) if rho is None else rho
        out.append(check_hall_motion(dataset, lag_correlation=rho))
    if {"d1", "d2", "d3"} <= set(dataset.names):
        out.append(check_angle_units(dataset, pole_pairs, columns=angles, lag_correlation=rho))
    return out


# ------------------------------------------------------------------------------------------------
# loop stability


@dataclass(frozen=True)
class LoopCheck(Check):
    """Closed-loop poles of controller x plant (discretized exactly, delay included).

    Attributes
    ----------
    poles : ndarray of complex
        Closed-loop poles in z, largest magnitude first.
    max_abs : float
        Largest |z|.
    """

    poles: NDArray[np.complex128] = field(default_factory=lambda: np.zeros(0, complex), repr=False)
    max_abs: float = math.nan


def closed_loop_poles(
    controller: DiscreteTF, plant: ContinuousTF, sample_time: float
) -> NDArray[np.complex128]:
    """Poles (in z) of the loop u = C(q) (r - y), y = G u, G discretized with its delay.

    The plant is the exact zero-order-hold equivalent with the input delay as extra states
    (:meth:`ContinuousTF.discretize`), so the delay's phase lag is in the poles exactly. The
    measured angle is taken as the plant output (f_init linearized: gain 1).

    Parameters
    ----------
    controller : DiscreteTF
        C(q), eq. (controller).
    plant : ContinuousTF
        G(s) with its input delay.
    sample_time : float
        T_s [s].

    Returns
    -------
    ndarray of complex
        The closed-loop poles in z, largest magnitude first (stable: all inside the unit
        circle).
    """
    p = plant.discretize(sample_time)
    c = controller.state_space(sample_time)
    if p.D != 0.0:
        raise ValueError("the discretized plant has a direct feedthrough")
    ng, nc = p.order, c.order
    a = np.zeros((ng + nc, ng + nc))
    a[:ng, :ng] = p.A - c.D * np.outer(p.B, p.C)
    if nc:
        a[:ng, ng:] = np.outer(p.B, c.C)
        a[ng:, :ng] = -np.outer(c.B, p.C)
        a[ng:, ng:] = c.A
    # eigvals returns float64 when every eigenvalue is real: complex always, as documented
    z = np.linalg.eigvals(a).astype(np.complex128) if a.size else np.zeros(0, np.complex128)
    return z[np.argsort(-np.abs(z))]


def _pole_text(z: complex, sample_time: float) -> str:
    mag = abs(z)
    where = f"z = {z.real:.4g}" + (
        f" {'+' if z.imag >= 0 else '-'} {abs(z.imag):.3g}j" if abs(z.imag) > 1e-12 else ""
    )
    rate = math.log(mag) / sample_time if mag > 0 else -math.inf
    freq = abs(math.atan2(z.imag, z.real)) / (TWO_PI * sample_time)
    what = f"an oscillation at {freq:.3g} Hz" if freq > 0 else "a mode"
    if rate > 0:
        return f"{where} (|z| = {mag:.4g}: {what} growing e-fold every {1e3 / rate:.3g} ms)"
    return f"{where} (|z| = {mag:.4g})"


def check_loop(
    controller: DiscreteTF | None,
    plant: ContinuousTF,
    sample_time: float,
    *,
    plant_name: str = "[plant]",
) -> LoopCheck:
    """Stability of the closed loop of ``controller`` and ``plant`` before anything simulates it.

    Parameters
    ----------
    controller : DiscreteTF or None
        C(q) of the setup (None: skipped).
    plant : ContinuousTF
        G(s) with its delay.
    sample_time : float
        Ts [s].
    plant_name : str
        How the message names the plant (``"[plant]"``, ``"the BLA of bla.csv"``, ...).

    Returns
    -------
    LoopCheck
        Failed when a pole has ``|z| > 1 + UNSTABLE_MARGIN``.
    """
    if controller is None:
        return LoopCheck(CheckStatus.SKIPPED, "loop not checked: no [controller]")
    try:
        z = closed_loop_poles(controller, plant, sample_time)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return LoopCheck(
            CheckStatus.FAILED,
            f"the loop of [controller] and {plant_name} cannot be formed: {exc}",
            "check [controller] and the plant",
            key="controller",
        )
    max_abs = float(np.max(np.abs(z))) if z.size else 0.0
    if max_abs <= 1.0 + UNSTABLE_MARGIN:
        return LoopCheck(
            CheckStatus.OK,
            f"loop: [controller] with {plant_name} is stable (largest closed-loop |z| = "
            f"{max_abs:.6g})",
            poles=z,
            max_abs=max_abs,
        )
    worst = complex(z[0])
    return LoopCheck(
        CheckStatus.FAILED,
        f"the closed loop of [controller] and {plant_name} is unstable: pole at "
        f"{_pole_text(worst, sample_time)}",
        "check the sign and scaling of [controller] num/den (torque command per rad of position "
        f"error at this sample_time) and the gain, poles and delay of {plant_name}: the loop that "
        "recorded the data was stable, so its model must be too",
        key="controller",
        poles=z,
        max_abs=max_abs,
    )


# ------------------------------------------------------------------------------------------------
# the fitted plant model


@dataclass(frozen=True)
class BLAFitCheck(Check):
    """Plausibility of a parametric plant model fitted to the BLA.

    Attributes
    ----------
    poles : tuple of complex
        Poles other than the integrators [rad/s].
    unstable : tuple of complex
        Those in the right half-plane.
    far : tuple of complex
        Stable poles faster than ``FAR_POLE_FACTOR`` times the highest measured frequency.
    """

    poles: tuple[complex, ...] = ()
    unstable: tuple[complex, ...] = ()
    far: tuple[complex, ...] = ()


def _s_text(p: complex) -> str:
    if abs(p.imag) < 1e-9 * max(abs(p), 1.0):
        return f"{p.real:+.3g} rad/s"
    return f"{p.real:+.3g} {'+' if p.imag >= 0 else '-'} {abs(p.imag):.3g}j rad/s"


def check_bla_fit(
    fit: ParametricBLA,
    *,
    denominator_order: int,
    max_frequency: float,
    suggestion: int | None = None,
    chosen_from_data: bool = False,
) -> BLAFitCheck:
    """Unstable or undetermined poles of a parametric BLA, with the fix named.

    Parameters
    ----------
    fit : ParametricBLA
    denominator_order : int
        The order that was fitted (the setup's ``[bla] denominator_order`` or the chosen one).
    max_frequency : float
        Highest frequency of the BLA data [Hz].
    suggestion : int, optional
        A denominator order the data support
        (from :func:`~hallcal.identify.parametric.select_order`).
    chosen_from_data : bool
        Whether the order was chosen from the data (``"auto"``): then an unstable model means no
        candidate was stable.

    Returns
    -------
    BLAFitCheck
        FAILED with unstable poles, WARNING with poles far above the data's band, else OK; the
        poles in s [rad/s].
    """
    from hallcal.identify.parametric import model_poles

    poles = tuple(complex(p) for p in model_poles(fit))
    unstable = tuple(p for p in poles if p.real >= 0.0)
    w_max = TWO_PI * float(max_frequency)
    far = tuple(p for p in poles if p.real < 0.0 and abs(p) > FAR_POLE_FACTOR * w_max)
    if unstable:
        listed = ", ".join(_s_text(p) for p in unstable)
        if chosen_from_data:
            fix = (
                "no model order from 0 to 3 gives a stable fit: look at the Bode plot (bla.png) "
                "and the [bla] experiment (band, rms, periods), or give [plant] instead"
            )
        elif suggestion is not None and suggestion != denominator_order:
            fix = (
                f"lower [bla] denominator_order (now {denominator_order}) to {suggestion}, or set "
                'denominator_order = "auto" to choose it from the data'
            )
        else:
            fix = (
                f"change [bla] denominator_order (now {denominator_order}) or set "
                'denominator_order = "auto"'
            )
        return BLAFitCheck(
            CheckStatus.FAILED,
            f"the plant model fitted to the BLA is unstable: pole at {listed}",
            fix,
            key="bla.denominator_order",
            poles=poles,
            unstable=unstable,
            far=far,
        )
    if far:
        listed = ", ".join(_s_text(p) for p in far)
        return BLAFitCheck(
            CheckStatus.WARNING,
            f"the plant model has a pole at {listed}, more than {FAR_POLE_FACTOR:g} times above "
            f"the highest measured frequency ({w_max:.4g} rad/s): the data do not determine it",
            f"lower [bla] denominator_order (now {denominator_order})"
            if not chosen_from_data
            else "widen the [bla] band if the motor really has it",
            key="bla.denominator_order",
            poles=poles,
            far=far,
        )
    return BLAFitCheck(
        CheckStatus.OK,
        "plant model: stable"
        + (", poles at " + ", ".join(_s_text(p) for p in poles) if poles else ""),
        poles=poles,
    )

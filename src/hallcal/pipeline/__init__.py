"""Algorithm 1 of van Meer et al. end to end, on top of the numeric packages.

Steps (Algorithm 1): (1) the calibration data (closed-loop ramp with f_init feedback, or an
open-loop constant-speed spin); (2) the plant: ``[plant]`` or the BLA of multisine experiments
with its gain correction c_hat (:mod:`~hallcal.pipeline.plant`); (3) simulation-error
minimization of g_theta; (4) the lookup table and f_star; (5) validation against an encoder when
one was logged (:mod:`~hallcal.pipeline.closed_loop`, :mod:`~hallcal.pipeline.open_loop`).

No printing and no plotting here: it takes :class:`~hallcal.io.Dataset` and
:class:`~hallcal.io.Setup` objects and returns a :class:`Calibration`; the command line, the
report and the front door :func:`hallcal.calibrate` sit on top. ``progress`` callbacks receive
one short message per step.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from hallcal.io.dataset import Dataset
from hallcal.io.setup import Setup
from hallcal.messages import Message, MessageCode
from hallcal.pipeline.calibration import (
    Calibration,
    CalibrationStatus,
    Reconstruction,
    Validation,
    calibration_from_artifact,
    reconstruct,
    validate,
)
from hallcal.pipeline.simulate import bench_config, simulate

if TYPE_CHECKING:
    from hallcal.pipeline.plant import (
        BLAIdentification,
        BLAStatus,
        GainCorrection,
        PlantModel,
        estimate_gain,
        identify_bla,
        plant_model,
    )

#: Names of :mod:`~hallcal.pipeline.plant`, imported on first use: it loads the closed-loop
#: simulation (numba), which reading an artifact and reconstructing angles do not need.
_PLANT_NAMES = frozenset(
    {
        "BLAIdentification",
        "BLAStatus",
        "GainCorrection",
        "PlantModel",
        "estimate_gain",
        "identify_bla",
        "plant_model",
    }
)


def __getattr__(name: str) -> Any:
    if name in _PLANT_NAMES:
        from hallcal.pipeline import plant

        value = getattr(plant, name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'hallcal.pipeline' has no attribute {name!r}")


__all__ = [
    "BLAIdentification",
    "BLAStatus",
    "Calibration",
    "CalibrationStatus",
    "GainCorrection",
    "PlantModel",
    "Reconstruction",
    "Validation",
    "bench_config",
    "calibrate",
    "calibration_from_artifact",
    "estimate_gain",
    "identify_bla",
    "plant_model",
    "reconstruct",
    "simulate",
    "validate",
]


def calibrate(
    dataset: Dataset,
    setup: Setup,
    *,
    bla_dataset: Dataset | None = None,
    bla: BLAIdentification | None = None,
    progress: Callable[[str], None] | None = None,
) -> Calibration:
    """Algorithm 1: from calibration data (and a BLA experiment) to the table f_star.

    Parameters
    ----------
    dataset : Dataset
        Calibration run (closed loop: r, y, d1..d3; constant speed: d1..d3).
    setup : Setup
        ``[trajectory] kind`` chooses the closed-loop (the paper) or the constant-speed route.
    bla_dataset : Dataset, optional
        Multisine experiment for step 2 (closed loop).
    bla : BLAIdentification, optional
        An already identified BLA.
    progress : callable, optional
        Called with a short message at each step.

    Returns
    -------
    Calibration
        Check :attr:`Calibration.status`: a refused calibration carries its reason in
        :attr:`Calibration.refusal`.
    """
    from hallcal.limits import one_blas_thread

    # The route's modules are imported before the limit: it applies to the BLAS libraries loaded
    # at that moment, and SciPy brings its own OpenBLAS (loaded with scipy.linalg), which would
    # otherwise keep two threads (a 5 x 5 matrix exponential then took 25 ms instead of 0.2 ms
    # on the busy 2-core machine).
    if setup.trajectory.kind == "constant-speed":
        from hallcal.pipeline.open_loop import calibrate_open_loop
    else:
        from hallcal.pipeline.closed_loop import calibrate_closed_loop

    # One BLAS thread throughout: the products here are small or tall-and-thin, and with two
    # BLAS threads on a busy 2-core machine an eigendecomposition of 177 x 177 took 0.1-0.3 s
    # instead of 3 ms. Where two cores pay, the numeric code runs blocks in threads itself.
    with one_blas_thread():
        if setup.trajectory.kind == "constant-speed":
            cal = calibrate_open_loop(dataset, setup, progress=progress)
            if bla_dataset is not None or bla is not None:
                note = Message.warning(
                    MessageCode.UNUSED_INPUT,
                    "the BLA experiment is not used: a constant-speed calibration "
                    '(trajectory.kind = "constant-speed") needs no plant model',
                )
                status = cal.status
                if status is CalibrationStatus.OK:
                    status = CalibrationStatus.WARNING
                cal = cal.with_note(note, status)
            return cal
        return calibrate_closed_loop(
            dataset, setup, bla_dataset=bla_dataset, bla=bla, progress=progress
        )

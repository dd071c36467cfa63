"""Resource limits: the largest inputs hallcal accepts, each with the reason for its number.

Every limit is checked before anything of that size is allocated or computed, and a violation is
one line naming the file or key and the limit. The numbers are chosen so that no real motor or
recording is refused (harmonics up to a few hundred, 100+ pole pairs, 10 M samples) while a
hostile or corrupt input cannot make hallcal allocate tens of gigabytes or run for hours.

This module is at the bottom of the package (layer 0, like :mod:`hallcal.errors`): the readers
(:mod:`hallcal.io`) check files and setup keys against it, the numeric core checks the memory of
its largest work arrays with :func:`check_work_memory`.
"""

from __future__ import annotations

import functools
import math
import os
import sys
from typing import Any

__all__ = [
    "BYTES_PER_SAMPLE",
    "COMMAND_MEMORY_BYTES",
    "MAX_ABS_VALUE",
    "MAX_BENCH_ELECTRICAL_HARMONICS",
    "MAX_COGGING_ORDERS",
    "MAX_COLUMNS",
    "MAX_DATASET_VALUES",
    "MAX_DELAY_SAMPLES",
    "MAX_HARMONIC",
    "MAX_HARMONICS",
    "MAX_ITERATIONS",
    "MAX_JSON_BYTES",
    "MAX_JSON_CONTAINERS",
    "MAX_JSON_DEPTH",
    "MAX_KERNEL_POINTS",
    "MAX_LENGTHSCALE",
    "MAX_LUT_POINTS",
    "MAX_PLAN_SAMPLES",
    "MAX_PLAN_SPEEDS",
    "MAX_POLE_PAIRS",
    "MAX_POWERUP_GRID",
    "MAX_PROJECTION_CONDITION",
    "MAX_REALIZATIONS",
    "MAX_SAMPLES",
    "MAX_SETUP_BYTES",
    "MAX_TF_ORDER",
    "MAX_TEXT_FIELD",
    "MAX_WORK_BYTES",
    "MIN_HALL_MAGNITUDE",
    "MIN_LENGTHSCALE",
    "MIN_LUT_POINTS",
    "SPIKE_RATIO",
    "check_command_samples",
    "check_hall_scale",
    "check_work_memory",
    "one_blas_thread",
    "work_memory_budget",
]

# ---- The motor and the model ---------------------------------------------------------------

#: Pole pairs n_m. Direct-drive torque motors with Hall sensors have up to about a hundred pole
#: pairs (a 1 m rotor with 15 mm poles has ~100); 256 leaves a margin of 2.5x. The model check
#: examines every mechanical harmonic up to 8 n_m (the 7th electrical harmonic and its pole-to-pole
#: sidebands) with a dense O(H^3) solve, which is seconds at H = 8 * 256 = 2048 and hours at
#: H = 8 * 10^4; the firmware keeps one table entry per pole pair.
MAX_POLE_PAIRS = 256

#: Highest mechanical harmonic of ``[model] harmonics`` (and of the bench's flux): 8 x
#: MAX_POLE_PAIRS, the highest one the model check examines (see MAX_POLE_PAIRS). The time of
#: that check grows as N H + H^3 with the highest harmonic H, whatever the count.
MAX_HARMONIC = 8 * MAX_POLE_PAIRS

#: Number of harmonics of a Fourier model. A rotor whose magnets differ in shape has energy at
#: all harmonics up to several n_m: a few hundred for the largest motors. Each harmonic adds 6
#: SEM parameters: at 512 (3075 parameters) the Gauss-Newton system is 76 MB and its solve
#: 3e10 flops per iteration, and the sensitivity pass over the paper's 104 000 samples carries
#: 3075 sensitivities per state and sample: minutes per iteration, the most that is useful.
MAX_HARMONICS = 512

#: Orders of ``[model] cogging = [...]`` (periods per revolution, each at most MAX_HARMONIC).
#: A motor's cogging sits at the least common multiple of slots and poles and a few of its
#: multiples: a handful of orders; 64 keeps every message that lists them (and the artifact's
#: texts, at most MAX_TEXT_FIELD characters) short, and the joint fit's 2 per order small.
MAX_COGGING_ORDERS = 64

#: Memory budget of one command that runs over a recording sample by sample [bytes]: the
#: recording and the step's work arrays, beyond the interpreter and its libraries.
COMMAND_MEMORY_BYTES = 1_500_000_000

#: Peak resident bytes per sample of those commands, measured on this machine (peak RSS at 1e6
#: and 4e6 samples, the slope, rounded up; benchmarks/bench_memory.txt): the recording's eight
#: columns, the angles, the validation's sort and spectrum. Without ``y_ref`` reconstruct
#: streams through the recording in blocks and keeps only the Hall columns and the two angles
#: (10 M samples from a mapped .npz: 680 MB peak, benchmarks/bench_cli.txt: 68 B/sample).
#: ``--absolute`` evaluates the power-up likelihood of every pole pair at every sample.
BYTES_PER_SAMPLE: dict[str, int] = {
    "reconstruct": 200,
    "reconstruct without y_ref": 80,
    "reconstruct --absolute": 1300,
    "inspect": 240,
    "simulate": 110,
}


def check_command_samples(
    samples: float, command: str, *, hint: str = "split the recording"
) -> None:
    """Raise :class:`ValueError` when `samples` would take `command` over its memory budget.

    Parameters
    ----------
    samples : float
        Samples of the recording (or of the run to simulate).
    command : str
        A key of :data:`BYTES_PER_SAMPLE`.
    hint : str, keyword-only
        What the user can change.

    Raises
    ------
    ValueError
        ``"N samples: COMMAND needs about X GB for them, above its budget of 1.5 GB (at most M
        samples)"``.
    """
    per = BYTES_PER_SAMPLE[command]
    if not samples * per <= COMMAND_MEMORY_BYTES:
        most = COMMAND_MEMORY_BYTES // per
        raise ValueError(
            f"{samples:.4g} samples: {command} needs about {samples * per / 1e9:.2g} GB for "
            f"them, above its memory budget of {COMMAND_MEMORY_BYTES / 1e9:g} GB (at most "
            f"{most} samples: {hint})"
        )


#: ``hallcal plan``: candidate speeds, and samples simulated over all of them (each candidate
#: simulates its whole ramp: about a million samples a second, 100 bytes a sample at peak).
MAX_PLAN_SPEEDS = 100
MAX_PLAN_SAMPLES = 20_000_000

#: Range of a fixed kernel lengthscale l [rad] (``[model] lengthscale``). The kernel's distances
#: |x - x'| of x = [sin y, cos y] are at most 2: l = 1e3 is a constant kernel to 1e-6 and
#: l = 1e-3 is below the spacing 2 pi / m of the largest m; beyond, 1 / l^2 under- or
#: overflows (l = 1e-300 divided by zero, 1e300 overflowed).
MIN_LENGTHSCALE = 1e-3
MAX_LENGTHSCALE = 1e3

#: Kernel centres m (``[model] points``). The kernel model is a Fourier model with harmonics up to
#: m / 2, so m = 2 x MAX_HARMONIC reaches the same highest harmonic; the paper used 400.
MAX_KERNEL_POINTS = 2 * MAX_HARMONIC

#: Lookup-table nodes per revolution, smallest and largest. 16 nodes are the least that still
#: describe a correction (the interpolation error scales as (2 pi / M)^2); 65000 keeps every node
#: index of the firmware's bucket table in 16 bits (hallcal.output.codegen) and is an
#: interpolation error of 1e-9 of eta'' (below any Hall noise floor).
MIN_LUT_POINTS = 16
MAX_LUT_POINTS = 65000

#: SEM iterations (``[model] max_iterations``). Levenberg-Marquardt on exact sensitivities
#: converges in 3-30 iterations on this problem (docs/design.md); 1000 is a thousand Jacobian
#: passes, about ten minutes at the paper's size, and no more can help.
MAX_ITERATIONS = 1000

#: Order (degree of the denominator) of the plant G(s) and the controller C(q). Motion plants are
#: order 2-4; a controller with PID, a few notches and low-pass filters stays below 16. The loop
#: simulation and its sensitivities cost O(states^2 x parameters) per sample.
MAX_TF_ORDER = 16

#: Input delay of ``[plant]`` in samples (delay / sample_time). Each sample of delay adds one state
#: to the discrete loop (exact ZOH with the delay chain); real drives have 0.5-3 samples of
#: computation and PWM delay, and a position loop with 64 samples of delay has no phase margin
#: left at any useful bandwidth.
MAX_DELAY_SAMPLES = 64

#: Multisine realizations of a BLA experiment (``[bla] realizations``). Pintelon & Schoukens use
#: 4-20; each one is a separate experiment on the motor.
MAX_REALIZATIONS = 1000

#: Electrical harmonics of the virtual bench's flux (``[bench] electrical_harmonics``): trapezoidal
#: or saturated flux has odd harmonics 3, 5, 7, ...; 64 pairs describe any realistic shape.
MAX_BENCH_ELECTRICAL_HARMONICS = 64

#: Grid points per electrical period of the power-up decoder (an artifact's
#: ``identifiability.grid``). The calibration chooses among 32 .. 1024 (hallcal.sensor.absolute
#: GRID_CHOICES); the decoder's table holds pole_pairs x grid points, so 4096 (4x the largest
#: choice) bounds it at 1 M entries for 256 pole pairs.
MAX_POWERUP_GRID = 4096

# ---- Datasets ------------------------------------------------------------------------------

#: Rows (samples) of one dataset, and of a simulated run. An hour at 4 kHz is 14.4 M samples;
#: 20 M rows of the 9 known columns are 1.4 GB as float64.
MAX_SAMPLES = 20_000_000

#: Columns of one dataset: the 9 known ones plus whatever else the drive logged.
MAX_COLUMNS = 256

#: Values (rows x columns) of one dataset: 200 M float64 values are 1.6 GB, about what 10 M
#: samples of 20 logged signals need; more does not fit beside the solver's work arrays.
MAX_DATASET_VALUES = 200_000_000

#: Largest magnitude of any value in a dataset or an artifact. Hall signals are volts,
#: normalized units or ADC counts (a 32-bit converter counts to 4.3e9); angles are rad
#: (1e12 rad is 1.6e11 revolutions); times are s. A larger value is a corrupt file or a wrong
#: unit, and squares of such values in the solvers leave no precision.
MAX_ABS_VALUE = 1e12

#: Smallest magnitude of a nonzero Hall signal value. No converter, unit or scaling produces
#: Hall readings of 1e-30 (in volts that is far below one electron's charge on any capacitor);
#: random bytes read as float64 do, half of the time, and so does a dataset scaled by 1e-300,
#: whose squares underflow to zero in the angle's derivative.
MIN_HALL_MAGNITUDE = 1e-30

#: A value further than this many times the column's typical magnitude (its median absolute
#: value) from zero is not a measurement but a corrupt value: a Hall sensor saturates at a few
#: times its amplitude and an angle or time column does not jump by a factor of 10^6 in one row.
SPIKE_RATIO = 1e6

# ---- Text files: JSON artifacts, setup files -----------------------------------------------

#: Size of a JSON file (artifact, BLA result). The largest artifact hallcal writes (65000 table
#: nodes, 512 harmonics, 4096 kernel weights, the cost history) is below 10 MB.
MAX_JSON_BYTES = 64 * 2**20

#: Nesting depth of JSON and TOML files. The artifact nests 5 levels (diagnostics.adequacy...);
#: the parsers recurse per level, so a deeply nested file would exhaust the stack.
MAX_JSON_DEPTH = 32

#: JSON objects and arrays of one file (counted as ``{`` and ``[`` before parsing): Python
#: takes about 100 bytes for each, so 64 MiB of ``{},`` would parse to 2 GB; an artifact holds
#: a few hundred.
MAX_JSON_CONTAINERS = 1_000_000

#: Size of a setup file (TOML): a setup is a few dozen lines.
MAX_SETUP_BYTES = 2**20

#: Length of a free-text field of an artifact (version, messages): a sentence, not a file.
MAX_TEXT_FIELD = 4096

# ---- The artifact's f_init and the firmware ------------------------------------------------

#: Condition number of the 2x3 projection of f_init. Three sensors at any spacing that is not
#: within a fraction of an electrical degree of one another give less than 100 (0/120/240 and
#: 0/60/120 degrees: 1); a relative error e of (d - offset) moves the angle by up to kappa e, so at
#: kappa = 1e4 the ADC's quantization alone is radians of error: no angle can be read.
MAX_PROJECTION_CONDITION = 1e4

# ---- Work memory of the numeric core -------------------------------------------------------

#: Largest single work array of the numeric core (the Gauss-Newton system with its buffers,
#: a least-squares design matrix): 8 GiB, and never more than half of the machine's memory or of
#: the process's address-space limit (see :func:`work_memory_budget`).
MAX_WORK_BYTES = 8 * 2**30


def work_memory_budget() -> int:
    """Bytes one work array of the numeric core may take on this machine, in this process.

    The smallest of :data:`MAX_WORK_BYTES`, half of the physical memory and half of the
    address-space limit (``RLIMIT_AS``) when one is set: the rest is for the data, the other
    work arrays and the interpreter.

    Returns
    -------
    int
        Bytes.
    """
    budget = MAX_WORK_BYTES
    try:
        physical = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        if physical > 0:
            budget = min(budget, physical // 2)
    except (ValueError, OSError, AttributeError):  # not POSIX: keep the fixed budget
        pass
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft != resource.RLIM_INFINITY and soft > 0:
            budget = min(budget, soft // 2)
    except (ImportError, ValueError, OSError):
        pass
    return int(budget)


def check_work_memory(nbytes: float, what: str, hint: str) -> None:
    """Raise :class:`ValueError` before allocating `nbytes` when that exceeds the budget.

    Parameters
    ----------
    nbytes : float
        Size of the array about to be allocated.
    what : str
        What it is, with its dimensions (e.g. ``"the SEM Jacobian (104000 samples x 3 x 69
        parameters)"``).
    hint : str
        What the user can change (e.g. ``"use fewer harmonics or a shorter recording"``).

    Raises
    ------
    ValueError
        When ``nbytes > work_memory_budget()``; the message gives both sizes.
    """
    budget = work_memory_budget()
    if not math.isfinite(nbytes) or nbytes > budget:
        raise ValueError(
            f"{what} would need {_gib(nbytes)}, above the limit of {_gib(budget)} for one work "
            f"array on this machine: {hint}"
        )


def one_blas_thread() -> Any:
    """One thread in every BLAS library loaded now, within a ``with`` block.

    threadpoolctl's ``threadpool_limits(limits=1, user_api="blas")`` (the numeric core's
    products are small or tall-and-thin: on a busy 2-core machine a second BLAS thread only
    spins), from one ``ThreadpoolController`` kept while no module was imported since it looked
    the libraries up: ``threadpool_limits`` looks them up at every call (every loaded shared
    object, 2-6 ms on the 2-core machine; about 15 calls per ``hallcal calibrate``). A BLAS
    library is loaded by importing an extension module (NumPy, SciPy), so the libraries found
    are those loaded at the call, as with ``threadpool_limits``.

    Returns
    -------
    context manager
        Restores each library's thread count on exit.
    """
    return _blas_controller(len(sys.modules)).limit(limits=1, user_api="blas")


@functools.lru_cache(maxsize=1)
def _blas_controller(modules: int) -> Any:
    """The thread pools of the libraries loaded while ``modules`` modules are imported."""
    from threadpoolctl import ThreadpoolController  # loaded by the commands that compute only

    return ThreadpoolController()


def _gib(nbytes: float) -> str:
    if not math.isfinite(nbytes):
        return "unbounded memory"
    return f"{nbytes / 2**30:.3g} GiB"


def check_hall_scale(largest: float) -> None:
    """Raise :class:`ValueError` when Hall signals are too small or too large to hold an angle.

    The angle's derivative divides by alpha^2 + beta^2, which underflows to zero for signals
    below about 1e-154 and overflows above 1e154; :data:`MIN_HALL_MAGNITUDE` and
    :data:`MAX_ABS_VALUE` keep well inside.

    Parameters
    ----------
    largest : float
        The largest magnitude of the Hall signals (``max |d|``).

    Raises
    ------
    ValueError
        When `largest` is outside ``MIN_HALL_MAGNITUDE .. MAX_ABS_VALUE`` (or not finite).
    """
    if not MIN_HALL_MAGNITUDE <= largest <= MAX_ABS_VALUE:
        raise ValueError(
            f"the Hall signals' largest magnitude is {largest:.3g}, outside "
            f"{MIN_HALL_MAGNITUDE:g} .. {MAX_ABS_VALUE:g}: no angle can be computed from them "
            "(rescale d)"
        )

"""hallcal: self-calibration of analog linear Hall sensors without an encoder.

The method of van Meer et al., "Self-Calibrating Position Measurements: Applied to Imperfect
Hall Sensors" (Algorithm 1). Curated public API; the subpackages hold the details, one per step:

- :mod:`hallcal.sensor`: f_init, flux models g_theta, the lookup table f_star, error metrics
- :mod:`hallcal.sim`: transfer functions, the closed loop and its sensitivities, the virtual bench
- :mod:`hallcal.identify`: multisines and the BLA of the plant
- :mod:`hallcal.fit`: simulation-error minimization, model choice and adequacy, open-loop fit
- :mod:`hallcal.io`: files; :mod:`hallcal.pipeline`: Algorithm 1 end to end
- :mod:`hallcal.output`: figures, HTML report, C export
"""

from importlib.metadata import PackageNotFoundError, version

from hallcal.errors import HallcalInputError
from hallcal.fit.sem import SEMResult, solve_sem
from hallcal.sensor.flux import FluxModel, FourierBasis, sinusoidal_theta
from hallcal.sensor.lut import LUT, NotBijectiveError, StarReconstructor, build_lut
from hallcal.sensor.metrics import angle_error, spatial_spectrum
from hallcal.sensor.reconstruction import (
    InitReconstructor,
    clarke_matrix,
    f_init,
    projection_matrix,
)
from hallcal.sim.bench import BenchConfig, BenchRun, noise_floor, ramp_run, simulate_run
from hallcal.sim.loop import ClosedLoop, loop_jacobian, simulate_loop
from hallcal.sim.lti import ContinuousTF, DiscreteTF, StateSpace

try:
    __version__ = version("hallcal")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

__all__ = [
    "LUT",
    "BenchConfig",
    "BenchRun",
    "ClosedLoop",
    "ContinuousTF",
    "DiscreteTF",
    "FluxModel",
    "FourierBasis",
    "HallcalInputError",
    "InitReconstructor",
    "NotBijectiveError",
    "SEMResult",
    "StarReconstructor",
    "StateSpace",
    "__version__",
    "angle_error",
    "build_lut",
    "clarke_matrix",
    "f_init",
    "loop_jacobian",
    "noise_floor",
    "projection_matrix",
    "ramp_run",
    "simulate_loop",
    "simulate_run",
    "sinusoidal_theta",
    "solve_sem",
    "spatial_spectrum",
]

"""hallcal: self-calibration of analog linear Hall sensors without an encoder.

The method of van Meer et al., "Self-Calibrating Position Measurements: Applied to Imperfect
Hall Sensors" (Algorithm 1). Curated public API; the modules hold the details:

- :mod:`hallcal.reconstruction` f_init (eq. fimp); :mod:`hallcal.lut` the table and f_star
- :mod:`hallcal.flux` flux models; :mod:`hallcal.lti` and :mod:`hallcal.loop` the closed loop
- :mod:`hallcal.bench` the virtual bench; :mod:`hallcal.excitation`, :mod:`hallcal.bla` the BLA
- :mod:`hallcal.sem` simulation-error minimization; :mod:`hallcal.metrics` validation
- :mod:`hallcal.io` files; :mod:`hallcal.pipeline` Algorithm 1 end to end
"""

from importlib.metadata import PackageNotFoundError, version

from ._errors import HallcalInputError
from .bench import BenchConfig, BenchRun, noise_floor, ramp_run, simulate_run
from .flux import FluxModel, FourierBasis, sinusoidal_theta
from .loop import ClosedLoop, loop_jacobian, simulate_loop
from .lti import ContinuousTF, DiscreteTF, StateSpace
from .lut import LUT, NotBijectiveError, StarReconstructor, build_lut
from .metrics import angle_error, spatial_spectrum
from .reconstruction import InitReconstructor, clarke_matrix, f_init, projection_matrix
from .sem import SEMResult, solve_sem

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

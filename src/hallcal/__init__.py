"""hallcal: self-calibration of analog linear Hall sensors without an encoder.

The method of van Meer et al., "Self-Calibrating Position Measurements: Applied to Imperfect
Hall Sensors" (Algorithm 1). The front door::

    import hallcal
    cal = hallcal.calibrate("cal.csv", "setup.toml", bla_data="bla.csv")
    print(cal.status, cal.predicted_error)
    cal.save("cal.json")
    angles = hallcal.load("cal.json").reconstruct("run.csv")

The subpackages hold the details, one per step of the method:

- :mod:`hallcal.sensor`: f_init, flux models g_theta, the lookup table f_star, error metrics
- :mod:`hallcal.sim`: transfer functions, the closed loop and its sensitivities, the virtual bench
- :mod:`hallcal.identify`: multisines and the BLA of the plant
- :mod:`hallcal.fit`: simulation-error minimization, model choice and adequacy, open-loop fit
- :mod:`hallcal.io`: files; :mod:`hallcal.pipeline`: Algorithm 1 end to end
- :mod:`hallcal.output`: figures, HTML report, C export

Names are loaded on first use, so ``import hallcal`` (and ``hallcal --help``) stays fast.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from hallcal.errors import CalibrationRefused, HallcalError, HallcalInputError

if TYPE_CHECKING:
    from hallcal._version import __version__
    from hallcal.api import Calibration, calibrate, load
    from hallcal.io import Dataset, Setup, read_dataset, read_setup
    from hallcal.pipeline import CalibrationStatus, Reconstruction, Validation
    from hallcal.sensor.flux import FluxModel, FourierBasis
    from hallcal.sensor.lut import LUT, StarReconstructor
    from hallcal.sensor.metrics import angle_error, spatial_spectrum
    from hallcal.sensor.reconstruction import InitReconstructor, f_init
    from hallcal.sim.bench import BenchConfig, noise_floor, simulate_run
    from hallcal.sim.lti import ContinuousTF, DiscreteTF

#: Public name -> module that defines it (imported on first access).
_LAZY: dict[str, str] = {
    "__version__": "hallcal._version",
    "Calibration": "hallcal.api",
    "calibrate": "hallcal.api",
    "load": "hallcal.api",
    "Dataset": "hallcal.io",
    "Setup": "hallcal.io",
    "read_dataset": "hallcal.io",
    "read_setup": "hallcal.io",
    "CalibrationStatus": "hallcal.pipeline",
    "Reconstruction": "hallcal.pipeline",
    "Validation": "hallcal.pipeline",
    "FluxModel": "hallcal.sensor.flux",
    "FourierBasis": "hallcal.sensor.flux",
    "LUT": "hallcal.sensor.lut",
    "StarReconstructor": "hallcal.sensor.lut",
    "angle_error": "hallcal.sensor.metrics",
    "spatial_spectrum": "hallcal.sensor.metrics",
    "InitReconstructor": "hallcal.sensor.reconstruction",
    "f_init": "hallcal.sensor.reconstruction",
    "BenchConfig": "hallcal.sim.bench",
    "noise_floor": "hallcal.sim.bench",
    "simulate_run": "hallcal.sim.bench",
    "ContinuousTF": "hallcal.sim.lti",
    "DiscreteTF": "hallcal.sim.lti",
}

__all__ = [
    "LUT",
    "BenchConfig",
    "Calibration",
    "CalibrationRefused",
    "CalibrationStatus",
    "ContinuousTF",
    "Dataset",
    "DiscreteTF",
    "FluxModel",
    "FourierBasis",
    "HallcalError",
    "HallcalInputError",
    "InitReconstructor",
    "Reconstruction",
    "Setup",
    "StarReconstructor",
    "Validation",
    "__version__",
    "angle_error",
    "calibrate",
    "f_init",
    "load",
    "noise_floor",
    "read_dataset",
    "read_setup",
    "simulate_run",
    "spatial_spectrum",
]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'hallcal' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))

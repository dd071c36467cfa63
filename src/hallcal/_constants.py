"""Numbers that several layers share, each defined once.

This module is at the bottom of the package (layer 0, like :mod:`hallcal.errors`) and imports
only :mod:`math`: the numeric core, the output layer and the command line (whose start-up and
``--help`` must not load NumPy or :mod:`hallcal.output`) all import from it.
"""

from __future__ import annotations

import math

__all__ = ["DEFAULT_C_PREFIX", "DEFAULT_FAULT_AFTER", "DEFAULT_TOLERANCE", "TWO_PI"]

#: One revolution [rad]: 2 pi (the same double as ``math.tau``), mechanical or electrical.
TWO_PI = 2.0 * math.pi

# The defaults of ``hallcal export-c``, for the CLI's options and the keyword defaults of
# :func:`hallcal.output.firmware.design_firmware` and :func:`hallcal.output.codegen.export_c`
# (docs/firmware.md).

#: Prefix of the generated C names (functions, types, macros) and files.
DEFAULT_C_PREFIX = "hallcal"
#: Relative widening of the calibrated amplitude windows (gain and magnet drift) [-].
DEFAULT_TOLERANCE = 0.25
#: Consecutive rejected samples after which the firmware's state flags a fault.
DEFAULT_FAULT_AFTER = 8

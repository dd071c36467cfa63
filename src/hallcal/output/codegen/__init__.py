"""Firmware export: eq. (f_final) as lean C99 for microcontrollers, in float and in fixed point.

``export_c(artifact, out_dir)`` writes ``<prefix>.h`` / ``<prefix>.c`` (single-precision float,
for MCUs with an FPU) and ``<prefix>_q.h`` / ``<prefix>_q.c`` (32-bit integers only: no float, no
64-bit arithmetic, no division; for Cortex-M0+/M3 and FPU-less M4). Both compute f_star of
eq. (f_final), y_star = f_init(d) + eta(f_init(d)), with f_init of eq. (fimp) running on its own
unwrap state, and both check each sample for plausibility first. The numbers come from
:func:`hallcal.output.firmware.design_firmware`; this module turns them into C.

What the generated code does per sample (no loop on the lean path, no libm, no double, no
division, no compiler builtin; the worst case measured in ``benchmarks/bench_cycles.txt``):

1. plausibility of the raw sample: each channel within its calibrated range, the component
   along the projection's null vector (the common mode of symmetric sensors) within its
   window (a stuck, clipped or disconnected channel), then the alpha/beta radius within its
   calibrated window;
2. alpha/beta = P (d - o); the float variant forms d2 - d1 and d3 - d1 when P's rows sum to zero,
   the fixed variant's integer rows sum to exactly zero, so a common mode cancels exactly;
3. the electrical angle: float: octant reduction on the IEEE bit patterns, a rotation by 45
   degrees above 22.5 degrees, a reciprocal by Newton steps from a linear seed valid on the
   radius window, and an odd minimax polynomial of atan on [-tan(pi/8), tan(pi/8)], then Q0.32
   turns; fixed: ``CORDIC_STEPS`` sign-magnitude CORDIC steps in unsigned arithmetic, then
   atan(y/x) ~ t - t^3/3 on the small residual with a 16-bit Newton reciprocal, all scaled to
   mechanical Q0.32 units;
4. the unwrap Gamma of eq. (fimp) (ties to -pi) in integers (a corrupt turn count is repaired
   and latches the fault), then the step rule of :mod:`hallcal.output.plausibility`: the step
   from the last accepted sample within what the speed limit allows after the samples held
   (no window before the first accepted sample after ``init``; one after ``set_angle``);
5. eta from the uniform table of M = n_m 2^k intervals (int16 values, linear, or with int8
   curvatures, quadratic) at f_init's angle within the revolution, found with shifts from the
   turn count and the electrical angle; y_star = revolutions + angle within the revolution;
6. a rejected sample (range, consistency, amplitude or step) is counted and the last reading
   held; when the count of rejected and unconfirmed samples reaches ``fault_after`` (at most
   what cannot alias at twice the speed limit) the fault flag latches until ``_clear_fault``
   and the angle is re-acquired;
7. the reading (revolutions, angle, flags, rejected count) is published into one of two
   buffers and a sequence counter advanced, so ``_read`` returns a consistent reading from any
   context (the main loop of an ISR's update, or a higher-priority interrupt).

Every export has the same API (``init`` without an angle, ``set_angle`` for a homed axis,
``update``, ``read``, ``clear_fault``), with or without the power-up identification.

Generated files contain only numbers and comment text that is sanitized so that it cannot end the
comment (:func:`comment_text`: hallcal's own text keeps its punctuation); file names and other
names from outside are reduced to their base name and to the characters ``A-Za-z0-9 ._-+=,:()[]``
(:func:`~hallcal.output.codegen.c_text.name_text`).
Optional parts are separate :class:`Section` objects added to a variant (see
:data:`~hallcal.output.codegen.export._SECTIONS`):
the anticogging feed-forward when the artifact has ``"cogging"``, and the power-up
identification of the pole pair when its ``"identifiability"`` verdict allows it (float variant:
the decoder of :mod:`hallcal.sensor.absolute` started by ``init``, the identification in the
reading; it fills the variant's insertion points, :data:`FLOAT_HOOKS`, and keeps the lean
path's code; see :func:`~hallcal.output.codegen.c_powerup._powerup_section`). Without it the
angle comes from ``set_angle`` (homing) and the header says why.

The modules, in the order the export uses them:

* :mod:`~hallcal.output.codegen.c_text`: sanitized comment text, C literals, banners;
* :mod:`~hallcal.output.codegen.numbers`: the constants of each variant and their stated bounds;
* :mod:`~hallcal.output.codegen.sections`: the context a builder gets, the optional sections;
* :mod:`~hallcal.output.codegen.c_float`, :mod:`~hallcal.output.codegen.c_fixed`: the templates
  of each variant and what fills them;
* :mod:`~hallcal.output.codegen.anticogging`, :mod:`~hallcal.output.codegen.c_powerup`: the
  optional sections;
* :mod:`~hallcal.output.codegen.export`: :func:`export_c`, :class:`ExportResult`.
"""

from __future__ import annotations

from hallcal.io import ARTIFACT_FORMAT
from hallcal.output.codegen.c_float import FLOAT_HOOKS
from hallcal.output.codegen.c_powerup import POWERUP_ATAN2_POLY, POWERUP_TERM_ERROR
from hallcal.output.codegen.c_text import comment_text
from hallcal.output.codegen.export import ExportResult, export_c
from hallcal.output.codegen.numbers import CORDIC_STEPS, MAX_TOTAL_ERROR
from hallcal.output.codegen.sections import Section

__all__ = [
    "ARTIFACT_FORMAT",
    "CORDIC_STEPS",
    "FLOAT_HOOKS",
    "MAX_TOTAL_ERROR",
    "POWERUP_ATAN2_POLY",
    "POWERUP_TERM_ERROR",
    "ExportResult",
    "Section",
    "comment_text",
    "export_c",
]

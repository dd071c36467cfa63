"""Shared test settings: deterministic hypothesis profile and small bench fixtures."""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings

settings.register_profile(
    "hallcal",
    derandomize=True,  # deterministic in CI
    deadline=None,  # numba compilation makes first examples slow
    max_examples=60,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "hallcal"))

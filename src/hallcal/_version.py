"""The installed package version (one place, used by the artifact, the C export and the CLI).

Looked up in the installed metadata on first use (``importlib.metadata`` costs about 20 ms to
import, which ``hallcal --help`` need not pay).
"""

from __future__ import annotations

import functools

__all__ = ["__version__"]

__version__: str  # provided by __getattr__ below


@functools.cache
def _installed_version() -> str:
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("hallcal")
    except PackageNotFoundError:  # pragma: no cover - a source tree without metadata
        return "0+unknown"


def __getattr__(name: str) -> str:
    if name == "__version__":
        return _installed_version()
    raise AttributeError(f"module 'hallcal._version' has no attribute {name!r}")

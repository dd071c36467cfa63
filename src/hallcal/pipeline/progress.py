"""The progress callback of the pipeline: one short message per step, or nothing."""

from __future__ import annotations

from collections.abc import Callable

__all__ = ["Progress", "say"]

#: Called with one short message per step; None reports nothing.
Progress = Callable[[str], None] | None


def say(progress: Progress, message: str) -> None:
    """Report one step to a progress callback, if there is one.

    Parameters
    ----------
    progress : callable or None
        The callback.
    message : str
        One short line.
    """
    if progress is not None:
        progress(message)

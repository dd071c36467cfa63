"""numba's start-up, begun in a background thread while a command reads its input.

The first call of any compiled kernel in a process, even one loaded from numba's on-disk cache,
fills numba's typing and target registries (it imports and installs the implementations of
NumPy's functions and of Python's built-ins): measured 0.14-0.2 s on the paper run, about a
tenth of ``hallcal calibrate``. It depends on nothing of the data, so :func:`start` runs it in a
thread while the caller reads the recording (a CSV parse, in which pyarrow releases the GIL);
the first kernel call then finds it done, or waits for it under numba's compiler lock. Loading
code changes no result: the kernels compute the same numbers whichever thread filled the
registries.
"""

from __future__ import annotations

import threading

__all__ = ["start"]


def _fill_registries() -> None:
    """What the first call of a kernel does before it loads the kernel (under the same lock)."""
    from numba.core.compiler_lock import global_compiler_lock
    from numba.core.registry import cpu_target

    with global_compiler_lock:
        cpu_target.target_context.refresh()
        cpu_target.typing_context.refresh()


def start() -> threading.Thread:
    """Begin numba's start-up in a daemon thread (see the module docstring).

    Returns
    -------
    threading.Thread
        The started thread (nothing to wait for: the first kernel call waits if it must).
    """
    thread = threading.Thread(target=_fill_registries, name="hallcal-numba-start", daemon=True)
    thread.start()
    return thread

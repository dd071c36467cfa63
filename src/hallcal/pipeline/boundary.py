"""The boundary between the numeric core and the pipeline: core errors get the input's name.

The numeric packages (layers 1-4) raise :class:`ValueError` with a clear message when an
argument cannot be used, without knowing where it came from; the pipeline does, and converts.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from hallcal.errors import HallcalError, HallcalInputError
from hallcal.formatting import one_line

__all__ = ["numeric_errors"]


@contextlib.contextmanager
def numeric_errors(source: str, key: str | None = None) -> Iterator[None]:
    """Name the input behind a :class:`ValueError` of the numeric core (the boundary of layer 6).

    The numeric packages (:mod:`hallcal.sensor`, :mod:`hallcal.sim`, :mod:`hallcal.identify`,
    :mod:`hallcal.fit`) raise :class:`ValueError` with a clear message when an argument cannot
    be used (or :class:`~hallcal.errors.HallcalInputError` naming a column or key, but not the
    file); here the pipeline knows which file or setup table the argument came from. Only
    ValueError is converted: any other exception is a bug and propagates.

    Parameters
    ----------
    source : str
        The file, or ``"setup"`` (the command line puts the setup file's name there).
    key : str, optional
        The setup table or key, shown after `source` (``"setup: [plant]: ..."``).

    Yields
    ------
    None
        The body runs inside the conversion.

    Raises
    ------
    HallcalInputError
        With ``"{source}: [key]: {message}"`` on one line.
    """
    where = f"{source}: [{key}]" if key else source
    try:
        yield
    except HallcalInputError as exc:
        if exc.source is not None or str(exc).startswith(f"{source}:"):
            raise
        # raised by the core, which knew the column or key but not the file
        text = one_line(exc)
        raise HallcalInputError(f"{where}: {text}", source=source, key=exc.key or key) from None
    except HallcalError:
        raise
    except ValueError as exc:
        text = one_line(exc)
        raise HallcalInputError(f"{where}: {text}", source=source, key=key) from None

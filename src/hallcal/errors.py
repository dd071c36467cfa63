"""The exceptions of hallcal: one family, so that a caller can catch :class:`HallcalError`.

The numeric core (:mod:`hallcal.sensor`, :mod:`hallcal.sim`, :mod:`hallcal.identify`,
:mod:`hallcal.fit`) raises :class:`ValueError` for arguments it cannot use; the readers and the
pipeline know which file, column or setup key the argument came from and raise
:class:`HallcalInputError` naming it; the command line turns a :class:`HallcalError` into one line
on stderr and its :attr:`~HallcalError.exit_status`.
"""

from __future__ import annotations

__all__ = ["CalibrationRefused", "HallcalError", "HallcalInputError"]


class HallcalError(Exception):
    """Base class of every error hallcal raises on purpose.

    Attributes
    ----------
    exit_status : int
        Exit status of the command line for this error (class attribute).
    source : str or None
        The file (or ``"setup"``, ``"<dataset>"``) the error is about, when known.
    key : str or None
        The column or the dotted setup key at fault, when known.

    Parameters
    ----------
    message : str
        One line for the user, naming the file, column or key when known.
    source : str, keyword-only, optional
        Stored as ``source``.
    key : str, keyword-only, optional
        Stored as ``key``.
    """

    exit_status: int = 1

    def __init__(self, message: str, *, source: str | None = None, key: str | None = None):
        super().__init__(message)
        self.source = source
        self.key = key


class HallcalInputError(HallcalError, ValueError):
    """A user mistake in an input file, column or setup key (exit status 2).

    The message is one line and names the file, the column or the key at fault. It is also a
    :class:`ValueError`, so code that validates arguments the Python way keeps working.
    """

    exit_status = 2


class CalibrationRefused(HallcalError):
    """The calibration ran, but its result must not be used (exit status 3).

    Raised when a refused calibration is asked for anyway (for example ``reconstruct`` with a
    table that is not bijective); the message says why and what to do.
    """

    exit_status = 3

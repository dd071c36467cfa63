"""Exceptions shared by the whole package."""

from __future__ import annotations


class HallcalInputError(ValueError):
    """A user mistake in an input file, column or setup key.

    The command line turns it into one line on stderr and exit status 2; the message must name the
    file, the column or the key at fault.
    """

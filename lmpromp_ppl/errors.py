"""Exceptions and warnings of lmpromp-ppl.

A :class:`LmprompError` is a user error (bad input, unreadable file, invalid
option): the command-line interface prints its message on one line and exits
with status 2.
"""

__all__ = ["LmprompError", "DataError", "ConvergenceWarning"]


class LmprompError(ValueError):
    """A user error with a message that names the problem."""


class DataError(LmprompError):
    """Demonstrations or a data file are invalid."""


class ConvergenceWarning(UserWarning):
    """An iterative engine stopped at its iteration limit before converging."""

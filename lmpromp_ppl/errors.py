"""Exceptions and warnings of lmpromp-ppl.

A :class:`LmprompError` is a user error (bad input, unreadable file, invalid
option): the command-line interface prints its message on one line and exits
with status 2.
"""

__all__ = ["LmprompError", "DataError", "EngineDivergedError", "ConvergenceWarning"]


class LmprompError(ValueError):
    """A user error with a message that names the problem."""


class DataError(LmprompError):
    """Demonstrations or a data file are invalid."""


class EngineDivergedError(LmprompError):
    """An engine's objective became non-finite (NaN or infinite bound), so the fit has no answer.

    A typed failure: callers that tolerate divergence (the reproduction's
    stress runs) catch this class instead of reading the message.
    """


class ConvergenceWarning(UserWarning):
    """An iterative engine stopped at its iteration limit before converging."""

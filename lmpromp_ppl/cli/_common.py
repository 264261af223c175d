"""Helpers shared by the sub-commands: option checks, output targets, engine warnings.

Numeric options are checked when the command line is parsed, before any work:
integers with typer's ``min=``/``max=`` ranges (``min=1`` for counts,
``min=0, max=SEED_MAX`` for seeds), floats with the callbacks below.  A value
out of range is a click usage error, which :func:`lmpromp_ppl.cli.main` prints
as one line and exits with status 2.

Output targets (``--out``) are prepared by :mod:`lmpromp_ppl.outputs`, which
the reports use too; this module re-exports them for the sub-commands.
"""

from __future__ import annotations

import math
import warnings
from contextlib import contextmanager

import typer

from lmpromp_ppl.errors import ConvergenceWarning
from lmpromp_ppl.outputs import (
    make_dirs,
    claim_out_dir,
    claim_out_file,
    remove_created_dirs,
    start_recording,
    stop_recording,
)

__all__ = [
    "SEED_MAX", "SEED_HELP", "positive", "open_fraction", "basis_size", "claim_out_dir", "claim_out_file",
    "make_dirs", "remove_created_dirs", "start_recording", "stop_recording", "caught_convergence_warnings",
]

#: Largest ``--seed``: jax keys hold 32-bit seeds (larger ones would collide).
SEED_MAX = 2**32 - 1
SEED_HELP = f"Seed for every random choice (0 to {SEED_MAX})."


def _float_check(requirement: str, accept):
    def callback(value):
        if value is None:
            return value
        if not (math.isfinite(value) and accept(value)):
            raise typer.BadParameter(f"must be {requirement}, got {value:g}")
        return value

    return callback


#: ``callback=`` of a float option that must be finite and > 0.
positive = _float_check("a positive number", lambda x: x > 0)
#: ``callback=`` of a float option that must lie strictly between 0 and 1.
open_fraction = _float_check("strictly between 0 and 1", lambda x: 0 < x < 1)


def basis_size(value: str | None):
    """``callback=`` of ``--num-basis``: an integer >= 2, or ``auto`` (chosen by the bound)."""
    if value is None or value == "auto":
        return value
    try:
        number = int(value)
    except ValueError:
        raise typer.BadParameter(f"must be an integer >= 2 or 'auto', got {value!r}") from None
    if number < 2:
        raise typer.BadParameter(f"must be an integer >= 2 or 'auto', got {value!r}")
    return number


def acceleration(value: str | None):
    """``callback=`` of ``--accelerate``: a name of :data:`lmpromp_ppl.inference.cavi.ACCELERATIONS`."""
    from lmpromp_ppl.errors import LmprompError
    from lmpromp_ppl.inference.cavi.state import check_acceleration

    if value is not None:
        try:
            check_acceleration(value)
        except LmprompError as error:
            raise typer.BadParameter(str(error)) from None
    return value


# --------------------------------------------------------------------------- engine warnings
@contextmanager
def caught_convergence_warnings():
    """Collect the engines' ConvergenceWarning messages instead of printing them; re-emit other warnings.

    ``with caught_convergence_warnings() as messages: ...``; ``messages`` is a list of strings.
    """
    messages: list[str] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ConvergenceWarning)
        yield messages
    for w in caught:
        if issubclass(w.category, ConvergenceWarning):
            messages.append(str(w.message))
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)

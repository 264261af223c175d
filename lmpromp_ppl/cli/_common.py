"""Helpers shared by the sub-commands: option checks, output targets, engine warnings.

Numeric options are checked when the command line is parsed, before any work:
integers with typer's ``min=``/``max=`` ranges (``min=1`` for counts,
``min=0, max=SEED_MAX`` for seeds), floats with the callbacks below.  A value
out of range is a click usage error, which :func:`lmpromp_ppl.cli.main` prints
as one line and exits with status 2.

Directories created by :func:`prepare_out_dir` and :func:`prepare_out_file`
while a command runs are recorded; when the command fails, :func:`lmpromp_ppl.cli.main`
removes those of them that are still empty (:func:`remove_created_dirs`), so a
failed command leaves no empty ``--out`` behind.  Nothing that existed before
the command, and no file, is ever removed.
"""

from __future__ import annotations

import math
import warnings
from contextlib import contextmanager
from pathlib import Path

import typer

from lmpromp_ppl.errors import ConvergenceWarning, LmprompError

__all__ = [
    "SEED_MAX", "SEED_HELP", "positive", "open_fraction", "basis_size", "prepare_out_dir", "prepare_out_file",
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


# --------------------------------------------------------------------------- output targets
_created: list[Path] | None = None


def start_recording() -> None:
    """Start recording the directories the command creates (called by ``main``)."""
    global _created
    _created = []


def stop_recording() -> None:
    """Stop recording and forget the record (the command succeeded)."""
    global _created
    _created = None


def remove_created_dirs() -> None:
    """Remove the recorded directories that are empty, deepest first; stop recording."""
    global _created
    created, _created = _created or [], None
    for path in sorted(set(created), key=lambda p: len(p.parts), reverse=True):
        try:
            path.rmdir()  # only succeeds on an empty directory
        except OSError:
            pass


def make_dirs(path: Path) -> None:
    """``mkdir -p`` that records every directory it creates."""
    missing = []
    for p in (path, *path.parents):
        if p.exists():
            break
        missing.append(p)
    path.mkdir(parents=True, exist_ok=True)
    if _created is not None:
        _created.extend(p.absolute() for p in missing)


def prepare_out_dir(out: Path, force: bool) -> Path:
    """Create ``out``; refuse an existing non-empty directory unless ``force``.

    With ``force`` the directory is kept and only the files the command writes
    are replaced: nothing else in it is deleted.
    """
    out = Path(out)
    if out.exists():
        if not out.is_dir():
            raise LmprompError(f"output {out} exists and is not a directory")
        if any(out.iterdir()) and not force:
            raise LmprompError(f"output directory {out} exists and is not empty; pass --force to overwrite")
    make_dirs(out)
    return out


def prepare_out_file(out: Path, force: bool) -> Path:
    """Refuse an existing file unless ``force``; create the parent directory."""
    out = Path(out)
    if out.exists() and not force:
        raise LmprompError(f"output {out} exists; pass --force to overwrite")
    if out.is_dir():
        raise LmprompError(f"output {out} is a directory")
    make_dirs(out.parent)
    return out


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

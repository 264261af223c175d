"""Helpers shared by the sub-commands: output targets and progress."""

from __future__ import annotations

from pathlib import Path

from lmpromp_ppl.errors import LmprompError

__all__ = ["prepare_out_dir", "prepare_out_file"]


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
    out.mkdir(parents=True, exist_ok=True)
    return out


def prepare_out_file(out: Path, force: bool) -> Path:
    """Refuse an existing file unless ``force``; create the parent directory."""
    out = Path(out)
    if out.exists() and not force:
        raise LmprompError(f"output {out} exists; pass --force to overwrite")
    if out.is_dir():
        raise LmprompError(f"output {out} is a directory")
    out.parent.mkdir(parents=True, exist_ok=True)
    return out

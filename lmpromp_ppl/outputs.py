"""Output targets of a command: directories and files that are never overwritten silently.

Directories created by :func:`claim_out_dir` and :func:`claim_out_file`
while a command runs are recorded; when the command fails,
:func:`lmpromp_ppl.cli.main` removes those of them that are still empty
(:func:`remove_created_dirs`), so a failed command leaves no empty ``--out``
behind.  Nothing that existed before the command, and no file, is ever removed.
Used by the CLI and by the reports it writes (a layer below the CLI).
"""

from __future__ import annotations

from pathlib import Path

from lmpromp_ppl.errors import LmprompError

__all__ = ["claim_out_dir", "claim_out_file", "make_dirs", "start_recording", "stop_recording",
           "remove_created_dirs"]

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


def claim_out_dir(out: Path, force: bool) -> Path:
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


def claim_out_file(out: Path, force: bool) -> Path:
    """Refuse an existing file unless ``force``; create the parent directory."""
    out = Path(out)
    if out.exists() and not force:
        raise LmprompError(f"output {out} exists; pass --force to overwrite")
    if out.is_dir():
        raise LmprompError(f"output {out} is a directory")
    make_dirs(out.parent)
    return out

"""When to draw progress bars."""

from __future__ import annotations

import sys
from contextlib import contextmanager

__all__ = ["show_progress_bars", "reporter", "line_reporter"]


def show_progress_bars(progress: bool) -> bool:
    """Whether to draw a progress bar: asked for, and stderr is a terminal.

    A bar redraws itself with carriage returns; in a log file or a pipe that is
    noise, so then there is none (line-by-line progress messages still appear).
    """
    if not progress:
        return False
    try:
        return bool(sys.stderr.isatty())
    except (AttributeError, ValueError):  # replaced or closed stderr
        return False


class _Bar:
    """A tqdm bar driven by ``(done, value)`` reports of an engine's callback."""

    def __init__(self, total: int, description: str, label: str):
        from tqdm.auto import tqdm

        self._bar = tqdm(total=total, desc=description, leave=False)
        self._done = 0
        self._label = label

    def __call__(self, done: int, value: float) -> None:
        self._bar.update(done - self._done)
        self._done = done
        self._bar.set_postfix({self._label: f"{value:.6g}"})

    def close(self) -> None:
        self._bar.close()


@contextmanager
def reporter(progress, total: int, description: str, label: str = "elbo"):
    """The progress callback ``(done, value) -> None`` an engine reports to, or None.

    ``progress`` is the user's callable (used as it is), or a bool: True draws a
    bar when :func:`show_progress_bars` allows, False gives None.  Engines call
    the callback and never draw anything themselves.
    """
    if callable(progress):
        yield progress
        return
    if not show_progress_bars(bool(progress)):
        yield None
        return
    bar = _Bar(total, description, label)
    try:
        yield bar
    finally:
        bar.close()


def line_reporter(progress, label: str, unit: str = "step", value: str = "mean loss"):
    """A callback ``(done, value) -> None`` that prints one line per report to stderr, or None.

    For engines whose reports are rare (SVI's chunks, one line per chunk
    instead of a bar that redraws itself).  ``progress`` is the user's callable
    (used as it is) or a bool; True prints only on a terminal, as
    :func:`show_progress_bars` decides: a log keeps the commands' one line per
    stage, not one per chunk.
    """
    if callable(progress):
        return progress
    if not show_progress_bars(bool(progress)):
        return None

    def report(done: int, current: float) -> None:
        print(f"{label}: {unit} {done}, {value} {current:.6g}", file=sys.stderr)

    return report

"""When to draw progress bars."""

from __future__ import annotations

import sys

__all__ = ["show_progress_bars"]


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

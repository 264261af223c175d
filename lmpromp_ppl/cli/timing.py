"""``lmpromp timing``: prediction with unknown timing on real and synthetic demonstrations (reports/timing/)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lmpromp_ppl.cli import app
from lmpromp_ppl.cli._common import SEED_HELP, SEED_MAX, claim_out_dir

__all__ = ["timing_command"]


@app.command("timing")
def timing_command(
    out: Path = typer.Option(..., "--out", help="Output directory (timing.md, timing.json)."),
    datasets: Optional[str] = typer.Option(None, help="Comma-separated dataset strings (default: synthetic durations, eight LASA shapes, GunPoint)."),
    max_folds: int = typer.Option(7, "--max-folds", min=1, help="Held-out demonstrations per recorded dataset (a synthetic set holds out each of its demonstrations in turn)."),
    seed: int = typer.Option(0, "--seed", min=0, max=SEED_MAX, help=SEED_HELP),
    force: bool = typer.Option(False, "--force", help="Write into an existing non-empty directory."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Predict the rest of held-out demonstrations from their first third with true, estimated and mean timing."""
    from lmpromp_ppl.data import load_dataset
    from lmpromp_ppl.reports import timing

    names = [x.strip() for x in datasets.split(",") if x.strip()] if datasets else list(timing.DEFAULT_DATASETS)
    for name in names:  # bad names fail before any work or any file
        load_dataset(name, seed=seed)
    target = claim_out_dir(out, force)
    rows = timing.timing_rows(names, max_folds=max_folds, seed=seed, echo=None if quiet else typer.echo)
    timing.write_report(target, rows, {"datasets": names, "max_folds": max_folds, "seed": seed})
    if not quiet:
        typer.echo(f"wrote {target / 'timing.md'}")

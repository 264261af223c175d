"""``lmpromp reproduce``: the thesis's experiments (Sec. 5) on LASA, GunPoint and synthetic data."""

from __future__ import annotations

from pathlib import Path

import typer

from lmpromp_ppl.cli import app
from lmpromp_ppl.cli._common import SEED_HELP, SEED_MAX, claim_out_dir

__all__ = ["reproduce_command"]


@app.command("reproduce")
def reproduce_command(
    name: str = typer.Argument(
        ..., help="priors, noise, sparsity, beta, c0, semantics, bimodal, latent-analysis, or all."
    ),
    out: Path = typer.Option(..., "--out", help="Output directory (JSON, markdown, PNG, claims.md)."),
    quick: bool = typer.Option(False, "--quick", help="Tiny sizes (seconds per experiment), for tests."),
    preset: str = typer.Option(
        "thesis", "--preset",
        help="thesis: the thesis's hyperparameters and basis (J = 10, width 2); default: the library's defaults.",
    ),
    seed: int = typer.Option(0, "--seed", min=0, max=SEED_MAX, help=SEED_HELP),
    force: bool = typer.Option(False, "--force", help="Write into an existing non-empty directory."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Run a thesis experiment and write its figure, numbers (JSON) and report section; rebuild claims.md."""
    from lmpromp_ppl.errors import LmprompError
    from lmpromp_ppl.reproduce import EXPERIMENTS, Context, run_many
    from lmpromp_ppl.reproduce._common import SETTINGS

    names = list(EXPERIMENTS) if name == "all" else [name]
    if name != "all" and name not in EXPERIMENTS:
        raise LmprompError(f"unknown experiment {name!r}; choose from {', '.join(EXPERIMENTS)} or all")
    if preset not in SETTINGS:
        raise LmprompError(f"unknown preset {preset!r}; choose from {', '.join(SETTINGS)}")
    target = claim_out_dir(out, force)
    context = Context(out=target, quick=quick, seed=seed, progress=not quiet, settings=SETTINGS[preset])
    run_many(names, context, echo=None if quiet else typer.echo)
    if not quiet:
        typer.echo(f"wrote {target / 'claims.md'} and {target / 'report.md'}")

"""``lmpromp compare``: fit one model with several engines and report how far VI is from NUTS."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lmpromp_ppl.basis import DEFAULT_NUM_BASIS
from lmpromp_ppl.cli import app
from lmpromp_ppl.cli._common import SEED_HELP, SEED_MAX, basis_size

__all__ = ["compare_command"]


@app.command("compare")
def compare_command(
    dataset: str = typer.Argument(..., help="Dataset string ('lasa:GShape?every=20', gunpoint, 'synthetic:latent?L=20&seed=0', file.npz); quote it when it holds ? or &."),
    out: Path = typer.Option(..., "--out", help="Output directory (report.md, report.html, metrics.json, figures, <engine>/posterior.nc)."),
    model: str = typer.Option("lmpromp", help="promp, lmpromp or mixture."),
    engines: str = typer.Option("auto", help="Comma-separated engines; 'svi' means all three SVI guides; nuts is required (the reference); auto: every engine offered for the model."),
    latent_dim: Optional[int] = typer.Option(None, "--latent-dim", "-V", min=1, help="Latent dimension V."),
    components: Optional[int] = typer.Option(None, "--components", "-K", min=1, help="Mixture components K."),
    num_basis: Optional[str] = typer.Option(
        None, "--num-basis", "-J", callback=basis_size,
        help=f"Basis functions per DoF, or 'auto' (chosen once by the CAVI bound, shared by every engine). "
             f"Default: auto for the mixture, {DEFAULT_NUM_BASIS} otherwise.",
    ),
    preset_name: str = typer.Option("proper", "--preset", help="Hyperparameter preset shared by every engine."),
    chains: Optional[int] = typer.Option(None, min=1, help="NUTS: chains."),
    warmup: Optional[int] = typer.Option(None, min=0, help="NUTS: warm-up iterations per chain."),
    samples: Optional[int] = typer.Option(None, min=1, help="NUTS: draws per chain."),
    steps: Optional[int] = typer.Option(None, min=1, help="SVI: maximum optimisation steps."),
    draws: int = typer.Option(1000, min=100, max=100_000, help="Draws per VI engine (compared and saved)."),
    seed: int = typer.Option(0, min=0, max=SEED_MAX, help=SEED_HELP),
    force: bool = typer.Option(False, "--force", help="Overwrite the files of an existing report."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Fit MODEL to DATASET with every engine (shared hyperparameters) and compare each VI engine with NUTS."""
    from lmpromp_ppl.reports import compare
    from lmpromp_ppl.reports.render import format_rhat

    metrics = compare(
        dataset, model, engines, out_dir=out, latent_dim=latent_dim, num_components=components,
        num_basis=num_basis, preset_name=preset_name, num_chains=chains, num_warmup=warmup,
        num_samples=samples, svi_steps=steps, num_draws=draws, seed=seed, force=force, progress=not quiet,
    )
    if not quiet:
        nuts = metrics["engines"]["nuts"]
        typer.echo(f"{model} on {metrics['dataset']}: NUTS max R-hat {format_rhat(nuts['rhat_max'])}, "
                   f"{nuts['divergences']} divergences; report in {out}/report.html")

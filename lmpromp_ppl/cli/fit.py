"""``lmpromp fit``: fit one model with one engine and write the result files."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lmpromp_ppl.cli import app
from lmpromp_ppl.cli._common import prepare_out_dir

__all__ = ["fit_command", "hyper_from_options"]


def hyper_from_options(
    preset_name: str,
    latent_dim: Optional[int],
    components: Optional[int],
    beta: Optional[float],
    learn_beta: bool,
):
    """Hyperparameters from a preset and the command-line overrides."""
    from lmpromp_ppl.models.hyper import preset

    changes = {}
    if latent_dim is not None:
        changes["latent_dim"] = latent_dim
    if components is not None:
        changes["num_components"] = components
    if beta is not None:
        changes["beta"] = beta
    if learn_beta:
        changes["learn_beta"] = True
    return preset(preset_name, **changes)


@app.command("fit")
def fit_command(
    dataset: str = typer.Argument(..., help="Dataset string (lasa:GShape, gunpoint, synthetic:latent?L=20, file.npz)."),
    out: Path = typer.Option(..., "--out", help="Output directory (posterior.nc, summary.json)."),
    model: str = typer.Option("lmpromp", help="promp, lmpromp or mixture."),
    engine: str = typer.Option("cavi", help="cavi, nuts, svi_meanfield, svi_autonormal or svi_lowrank."),
    latent_dim: Optional[int] = typer.Option(None, "--latent-dim", "-V", help="Latent dimension V."),
    components: Optional[int] = typer.Option(None, "--components", "-K", help="Mixture components K."),
    num_basis: int = typer.Option(10, "--num-basis", "-J", help="Basis functions per DoF."),
    preset_name: Optional[str] = typer.Option(None, "--preset", help="Hyperparameter preset: thesis or proper (default: thesis for CAVI, proper otherwise)."),
    beta: Optional[float] = typer.Option(None, help="Observation precision beta (standardised units)."),
    learn_beta: bool = typer.Option(False, "--learn-beta", help="Infer beta under its Gamma prior."),
    max_iter: Optional[int] = typer.Option(None, "--max-iter", help="CAVI: maximum iterations."),
    tol: Optional[float] = typer.Option(None, help="CAVI: relative ELBO tolerance."),
    restarts: Optional[int] = typer.Option(None, help="CAVI: restarts, best ELBO kept."),
    chains: Optional[int] = typer.Option(None, help="NUTS: chains."),
    warmup: Optional[int] = typer.Option(None, help="NUTS: warm-up iterations per chain."),
    samples: Optional[int] = typer.Option(None, help="NUTS: draws per chain."),
    steps: Optional[int] = typer.Option(None, help="SVI: maximum optimisation steps."),
    learning_rate: Optional[float] = typer.Option(None, "--learning-rate", help="SVI: Adam learning rate."),
    seed: int = typer.Option(0, help="Seed for every random choice."),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing output directory."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Fit MODEL to DATASET with ENGINE and write DIR/posterior.nc and DIR/summary.json."""
    from lmpromp_ppl.api import fit

    hyper = hyper_from_options(preset_name or ("thesis" if engine == "cavi" else "proper"), latent_dim, components, beta, learn_beta)
    options = {
        "max_iter": max_iter, "tol": tol, "num_restarts": restarts,
        "num_chains": chains, "num_warmup": warmup, "num_samples": samples,
        "num_steps": steps, "learning_rate": learning_rate,
    }
    options = {k: v for k, v in options.items() if v is not None}
    out_dir = prepare_out_dir(out, force)
    result = fit(dataset, model=model, engine=engine, hyper=hyper, num_basis=num_basis, seed=seed,
                 progress=not quiet, **options)
    result.save(out_dir, force=True, key=None)
    if not quiet:
        s = result.summary_dict()
        elbo = "" if s["elbo"] is None else f", ELBO {s['elbo']:.4g}"
        ari = f", ARI {s['ari']:.3f}" if s.get("ari") is not None else ""
        typer.echo(f"{model}/{engine} on {dataset}: {s['seconds']:.2f} s{elbo}{ari}; wrote {out_dir}")

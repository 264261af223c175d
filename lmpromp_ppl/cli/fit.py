"""``lmpromp fit``: fit one model with one engine and write the result files."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lmpromp_ppl.basis import DEFAULT_NUM_BASIS, DEFAULT_WIDTH
from lmpromp_ppl.cli import app
from lmpromp_ppl.cli._common import (
    SEED_HELP, SEED_MAX, acceleration, basis_size, caught_convergence_warnings, positive, claim_out_dir,
)

__all__ = ["convergence_note", "fit_command", "hyper_from_options"]


def hyper_from_options(
    preset_name: str,
    latent_dim: Optional[int],
    components: Optional[int],
    beta: Optional[float],
    learn_beta: Optional[bool],
):
    """Hyperparameters from a preset and the command-line overrides."""
    from lmpromp_ppl.models.hyper import preset

    changes = {}
    if latent_dim is not None:
        changes["latent_dim"] = latent_dim
    if components is not None:
        changes["num_components"] = components
    if beta is not None:  # a given beta is fixed unless --learn-beta says otherwise
        changes["beta"] = beta
        changes["learn_beta"] = False
    if learn_beta is not None:
        changes["learn_beta"] = learn_beta
    return preset(preset_name, **changes)


def convergence_note(result, messages: list[str]) -> str:
    """``did not converge in N sweeps (...)`` for a fit that stopped at its limit; ``""`` otherwise.

    ``messages`` are the engine's ConvergenceWarning texts, used when the summary
    does not say more.
    """
    s = result.summary
    if s.get("converged") is not False:
        return "; ".join(messages)
    n = s.get("iterations")
    if result.engine in ("cavi", "cavi_lr"):
        import inspect

        from lmpromp_ppl.inference import cavi

        tol = result.options.get("tol", inspect.signature(cavi.fit).parameters["tol"].default)
        trace = s.get("elbo_trace") or []
        unit = "sweep" if n == 1 else "sweeps"
        if len(trace) >= 2 and trace[-1] != 0:
            change = abs(trace[-1] - trace[-2]) / abs(trace[-1])
            return f"did not converge in {n} {unit} (relative ELBO change {change:.2g} > tol {tol:g})"
        return f"did not converge in {n} {unit} (tol {tol:g})"
    stop_tol = (getattr(result.state, "options", None) or {}).get("stop_tol")
    detail = f" (smoothed loss still changing by more than {stop_tol:g})" if stop_tol is not None else ""
    return f"did not converge in {n} steps{detail}; raise --steps"


@app.command("fit")
def fit_command(
    dataset: str = typer.Argument(..., help="Dataset string (lasa:GShape, gunpoint, 'synthetic:latent?L=20&seed=0', file.npz); quote it when it holds ? or &."),
    out: Path = typer.Option(..., "--out", help="Output directory (posterior.nc, summary.json)."),
    model: str = typer.Option("lmpromp", help="promp, lmpromp or mixture."),
    engine: str = typer.Option("cavi", help="cavi, cavi_lr, nuts, svi_meanfield, svi_autonormal or svi_lowrank."),
    latent_dim: Optional[int] = typer.Option(None, "--latent-dim", "-V", min=1, help="Latent dimension V."),
    components: Optional[int] = typer.Option(None, "--components", "-K", min=1, help="Mixture components K."),
    num_basis: Optional[str] = typer.Option(
        None, "--num-basis", "-J", callback=basis_size,
        help=f"Basis functions per DoF, or 'auto': the J with the highest CAVI bound (docs/defaults.md). "
             f"Default: auto for the mixture, {DEFAULT_NUM_BASIS} otherwise.",
    ),
    width: float = typer.Option(DEFAULT_WIDTH, "--width", callback=positive, help="Basis width (Gaussian variance in squared centre spacings; the thesis uses 2)."),
    align: Optional[str] = typer.Option(None, "--align", help="Align the demonstrations' phases before fitting: dtw (dynamic time warping to the medoid demonstration; stored with the fit). Default: time mapped linearly to [0, 1]."),
    preset_name: Optional[str] = typer.Option(None, "--preset", help="Hyperparameter preset: default, thesis or proper (default: default for CAVI, proper otherwise)."),
    beta: Optional[float] = typer.Option(None, callback=positive, help="Fix the observation precision beta (standardised units)."),
    learn_beta: Optional[bool] = typer.Option(None, "--learn-beta/--fixed-beta", help="Infer beta under its Gamma prior (the default presets do)."),
    max_iter: Optional[int] = typer.Option(None, "--max-iter", min=1, help="CAVI: maximum iterations."),
    tol: Optional[float] = typer.Option(None, callback=positive, help="CAVI: relative ELBO tolerance."),
    restarts: Optional[int] = typer.Option(None, min=1, help="CAVI: restarts, best ELBO kept."),
    accelerate: Optional[str] = typer.Option(None, "--accelerate", callback=acceleration, help="CAVI: scale (default: rescalings, rotation and over-relaxation, each keeping the bound non-decreasing), overrelax, or none (the thesis's plain sweeps)."),
    resample: Optional[str] = typer.Option(None, "--resample", help="cavi_lr: auto (default: resample by importance weights when their k-hat is below 0.7) or never."),
    refresh: Optional[int] = typer.Option(None, "--refresh", min=0, help="cavi_lr: exact-conditional Gibbs sweeps applied to every draw (default 60; 0: the linear-response draws as they are)."),
    chains: Optional[int] = typer.Option(None, min=1, help="NUTS: chains."),
    warmup: Optional[int] = typer.Option(None, min=0, help="NUTS: warm-up iterations per chain."),
    samples: Optional[int] = typer.Option(None, min=1, help="NUTS: draws per chain."),
    steps: Optional[int] = typer.Option(None, min=1, help="SVI: maximum optimisation steps."),
    learning_rate: Optional[float] = typer.Option(None, "--learning-rate", callback=positive, help="SVI: Adam learning rate."),
    seed: int = typer.Option(0, min=0, max=SEED_MAX, help=SEED_HELP),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing output directory."),
    quiet: bool = typer.Option(False, "--quiet", help="No output but errors (no progress, no result line)."),
) -> None:
    """Fit MODEL to DATASET with ENGINE and write DIR/posterior.nc and DIR/summary.json.

    Prints one result line; a fit that stopped at its iteration limit says so in it.
    """
    from lmpromp_ppl.api import fit
    from lmpromp_ppl.data.align import ALIGN_METHODS

    if align is not None and align not in ALIGN_METHODS:
        raise typer.BadParameter(f"choose from {', '.join(ALIGN_METHODS)}", param_hint="--align")
    hyper = hyper_from_options(preset_name or ("default" if engine in ("cavi", "cavi_lr") else "proper"), latent_dim, components, beta, learn_beta)
    options = {
        "max_iter": max_iter, "tol": tol, "num_restarts": restarts, "accelerate": accelerate,
        "resample": resample, "refresh": refresh, "num_chains": chains, "num_warmup": warmup, "num_samples": samples,
        "num_steps": steps, "learning_rate": learning_rate,
    }
    options = {k: v for k, v in options.items() if v is not None}
    out_dir = claim_out_dir(out, force)
    with caught_convergence_warnings() as messages:
        result = fit(dataset, model=model, engine=engine, hyper=hyper, num_basis=num_basis, width=width, seed=seed,
                     align=align, progress=not quiet, **options)
    result.save(out_dir, force=True)  # draws from q keyed by the seed
    if not quiet:
        s = result.summary_dict()
        elbo = "" if s["elbo"] is None else f", ELBO {s['elbo']:.6g}"
        ari = f", ARI {s['ari']:.3f}" if s.get("ari") is not None else ""
        note = convergence_note(result, messages)
        note = f"; {note}" if note else ""
        chosen = f", J = {result.num_basis} (by the bound)" if "num_basis_selection" in s else ""
        chosen += f", phases aligned ({align})" if align else ""
        if "linear_response" in s:
            khat = s["linear_response"]["psis_khat"]
            resampled = "importance-resampled" if s["linear_response"]["importance_resampled"] else "not resampled"
            sweeps = s["linear_response"].get("refresh_sweeps", 0)
            chosen += f", k-hat {'n/a' if khat is None else f'{khat:.2f}'} ({resampled}"
            chosen += f", {sweeps} Gibbs sweeps per draw)" if sweeps else ")"
        typer.echo(f"{model}/{engine} on {dataset}: {s['seconds']:.3g} s{elbo}{ari}{chosen}{note}; wrote {out_dir}")
        for warning in s.get("warnings", []):
            if not warning.startswith("not converged"):  # said in the result line
                typer.echo(f"warning: {warning}")

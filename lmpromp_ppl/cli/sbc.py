"""``lmpromp sbc`` and ``lmpromp sweep``: calibration and hyperparameter grids on dask.distributed."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Optional

import typer

from lmpromp_ppl.basis import DEFAULT_NUM_BASIS
from lmpromp_ppl.cli import app
from lmpromp_ppl.cli._common import SEED_MAX, make_dirs, open_fraction, positive
from lmpromp_ppl.errors import LmprompError

__all__ = ["sbc_command", "sweep_command", "parse_engines"]


def parse_engines(text: str, model: str) -> list[str]:
    """Engines offered for ``model`` among a comma list (``svi``: the three SVI guides; ``auto``: DEFAULT_ENGINES)."""
    from lmpromp_ppl.calibration.sbc import DEFAULT_ENGINES, ENGINES, MODEL_ENGINES

    if text.strip() == "auto":
        return list(DEFAULT_ENGINES[model])
    names = []
    for name in (n.strip() for n in text.split(",") if n.strip()):
        expanded = [e for e in ENGINES if e.startswith("svi_")] if name == "svi" else [name]
        for engine in expanded:
            if engine not in ENGINES:
                raise LmprompError(f"unknown engine {engine!r}; choose from {list(ENGINES)} or 'svi'")
            if engine in MODEL_ENGINES[model] and engine not in names:
                names.append(engine)
    return names


def _out_dir(out: Path, force: bool, resume: bool) -> Path:
    """Create ``out``; an existing non-empty one needs ``--resume`` (keep finished tasks) or ``--force`` (start over)."""
    out = Path(out)
    if out.exists():
        if not out.is_dir():
            raise LmprompError(f"output {out} exists and is not a directory")
        if any(out.iterdir()) and not (force or resume):
            raise LmprompError(
                f"output directory {out} exists and is not empty; pass --resume to continue it or --force to start over"
            )
        if force and not resume and (out / "tasks").is_dir():
            shutil.rmtree(out / "tasks")
    make_dirs(out)
    return out


def _progress(quiet: bool, total: int):
    done = [0]

    def report(task_id: str, record: dict) -> None:
        done[0] += 1
        if not quiet:
            status = "ok" if record.get("status") == "ok" else f"FAILED: {record.get('error')}"
            typer.echo(f"[{done[0]}/{total}] {task_id}: {status} ({record.get('seconds', 0.0):.1f} s)", err=True)

    return report


def _finish(run, quiet: bool) -> None:
    for task_id in run.failed:
        typer.echo(f"lmpromp: task {task_id} failed: {run.records[task_id].get('error')}", err=True)
    if not quiet:
        typer.echo(f"{len(run.computed)} tasks run, {len(run.reused)} reused, {len(run.failed)} failed", err=True)
    if run.failed:
        raise typer.Exit(1)


@app.command("sbc")
def sbc_command(
    out: Path = typer.Option(..., "--out", help="Report directory (figures, uniformity.md, calibration.json, tasks/)."),
    models: str = typer.Option("lmpromp,promp", "--models", help="Comma list of lmpromp and promp."),
    engines: str = typer.Option("auto", help="Comma list of engines ('svi' = all SVI guides; engines not offered for a model are skipped), or auto: lmpromp cavi,cavi_lr,nuts,svi_meanfield; promp nuts,svi_autonormal."),
    replicates: int = typer.Option(100, min=1, help="Simulated datasets per engine (NUTS, SVI)."),
    cavi_replicates: Optional[int] = typer.Option(None, "--cavi-replicates", min=1, help="Simulated datasets for CAVI and CAVI-LR (default: --replicates)."),
    svi_replicates: Optional[int] = typer.Option(None, "--svi-replicates", min=1, help="Simulated datasets per SVI engine (default: --replicates)."),
    cavi_batch: int = typer.Option(50, "--cavi-batch", min=1, help="CAVI (and CAVI-LR) replicates per vmapped task."),
    draws: int = typer.Option(99, min=1, help="Posterior draws per replicate (ranks lie in 0..draws)."),
    demos: int = typer.Option(8, min=1, help="Demonstrations per dataset (L)."),
    dofs: int = typer.Option(1, min=1, help="Degrees of freedom (D)."),
    num_basis: int = typer.Option(5, "--num-basis", "-J", min=2, help="Basis functions per DoF (J)."),
    steps: int = typer.Option(20, min=1, help="Observed phases per demonstration (T)."),
    latent_dim: int = typer.Option(2, "--latent-dim", "-V", min=1, help="Latent dimension V (LMProMP)."),
    beta: float = typer.Option(100.0, callback=positive, help="Observation precision beta."),
    warmup: int = typer.Option(300, min=0, help="NUTS: warm-up iterations per chain (2 chains)."),
    samples: int = typer.Option(300, min=1, help="NUTS: draws per chain before thinning to --draws."),
    svi_steps: int = typer.Option(5000, "--svi-steps", min=1, help="SVI: maximum optimisation steps."),
    vsbc_simulations: int = typer.Option(20, "--vsbc-simulations", min=0, help="numpyro vsbc_diagnostic simulations per model (0: skip)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Address of an existing dask scheduler (default: a LocalCluster on 127.0.0.1)."),
    workers: int = typer.Option(2, min=1, help="LocalCluster worker processes."),
    seed: int = typer.Option(0, min=0, max=SEED_MAX, help=f"Seed of the simulations, fits and PIT jitter (0 to {SEED_MAX})."),
    resume: bool = typer.Option(False, "--resume", help="Continue an existing DIR: finished tasks are not recomputed."),
    force: bool = typer.Option(False, "--force", help="Start over in an existing DIR (deletes DIR/tasks)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Simulation-based calibration of the engines on simulated datasets, through dask.distributed."""
    from lmpromp_ppl.calibration.report import write_sbc_report
    from lmpromp_ppl.calibration.runner import run_tasks
    from lmpromp_ppl.calibration.sbc import MODEL_ENGINES, SbcProblem, sbc_tasks

    tasks, problems = {}, {}
    for model in (m.strip() for m in models.split(",") if m.strip()):
        if model not in MODEL_ENGINES:
            raise LmprompError(f"SBC supports models {sorted(MODEL_ENGINES)}, got {model!r}")
        problem = SbcProblem(model=model, num_demos=demos, num_dofs=dofs, num_basis=num_basis, num_steps=steps,
                             latent_dim=latent_dim, beta=beta, num_draws=draws)
        problems[model] = problem.to_dict()
        options = {"nuts": {"num_warmup": warmup, "num_samples": samples},
                   **{e: {"num_steps": svi_steps} for e in ("svi_meanfield", "svi_autonormal", "svi_lowrank")}}
        chosen = parse_engines(engines, model)
        if not chosen:
            raise LmprompError(f"none of the engines {engines!r} is offered for model {model!r} "
                               f"(offered: {', '.join(MODEL_ENGINES[model])})")
        batched = [e for e in ("cavi", "cavi_lr") if e in chosen]
        if batched:
            tasks.update(sbc_tasks(problem, batched, cavi_replicates or replicates, seed=seed,
                                   cavi_batch=cavi_batch))
        if "nuts" in chosen:
            tasks.update(sbc_tasks(problem, ["nuts"], replicates, seed=seed, options=options))
        svi = [e for e in chosen if e.startswith("svi_")]
        if svi:
            tasks.update(sbc_tasks(problem, svi, svi_replicates or replicates, seed=seed, options=options))
        if vsbc_simulations > 0:
            tasks[f"vsbc-numpyro-{model}"] = {"kind": "vsbc_numpyro", "problem": problem.to_dict(), "seed": seed,
                                              "options": {"num_simulations": vsbc_simulations,
                                                          "num_svi_steps": svi_steps, "num_samples": draws + 1}}
    if not tasks:
        raise LmprompError("no (model, engine) pair to run; check --models and --engines")
    out_dir = _out_dir(out, force, resume)
    run = run_tasks(tasks, out_dir, scheduler=scheduler, num_workers=workers,
                    progress=_progress(quiet, len(tasks)))
    content = write_sbc_report(run.records, out_dir, problems=problems, num_draws=draws, seed=seed)
    if not quiet:
        typer.echo((out_dir / "uniformity.md").read_text())
        typer.echo(f"wrote {out_dir} ({len(content['rows'])} rows)")
    _finish(run, quiet)


@app.command("sweep")
def sweep_command(
    dataset: str = typer.Argument(..., help="Dataset string (lasa:GShape, 'synthetic:latent?L=20&seed=0', file.npz); quote it when it holds ? or &."),
    out: Path = typer.Option(..., "--out", help="Directory: sweep.json, sweep.md and tasks/."),
    grid: list[str] = typer.Option(..., "--grid", help="NAME=V1,V2 (repeatable): hyperparameter fields or num_basis."),
    metric: str = typer.Option("lpd", help="Held-out metric to rank by: lpd (higher is better) or rmse."),
    preset_name: str = typer.Option("default", "--preset", help="Hyperparameter preset the grid changes."),
    num_basis: int = typer.Option(DEFAULT_NUM_BASIS, "--num-basis", "-J", min=2, help="Basis functions per DoF (unless in the grid)."),
    test_fraction: float = typer.Option(0.25, "--test-fraction", callback=open_fraction, help="Fraction of demonstrations held out."),
    max_iter: int = typer.Option(2000, "--max-iter", min=1, help="CAVI: maximum sweeps."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Address of an existing dask scheduler (default: a LocalCluster on 127.0.0.1)."),
    workers: int = typer.Option(2, min=1, help="LocalCluster worker processes."),
    seed: int = typer.Option(0, min=0, max=SEED_MAX, help=f"Seed of the split and the fits (0 to {SEED_MAX})."),
    resume: bool = typer.Option(False, "--resume", help="Continue an existing DIR: finished tasks are not recomputed."),
    force: bool = typer.Option(False, "--force", help="Start over in an existing DIR (deletes DIR/tasks)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """CAVI fits over a hyperparameter grid, scored on held-out demonstrations, through dask.distributed."""
    from lmpromp_ppl.calibration.runner import run_tasks
    from lmpromp_ppl.results import to_json_value
    from lmpromp_ppl.calibration.sweep import METRICS, parse_grid, sweep_table, sweep_tasks
    from lmpromp_ppl.data import load_dataset

    if metric not in METRICS:
        raise LmprompError(f"unknown metric {metric!r}; choose from {sorted(METRICS)}")
    load_dataset(dataset)  # a bad dataset string is a user error here, not a failed task per grid point
    tasks = sweep_tasks(dataset, parse_grid(grid), preset_name=preset_name, num_basis=num_basis,
                        test_fraction=test_fraction, seed=seed, options={"max_iter": max_iter})
    out_dir = _out_dir(out, force, resume)
    run = run_tasks(tasks, out_dir, scheduler=scheduler, num_workers=workers, progress=_progress(quiet, len(tasks)))
    rows = sweep_table(run.records, metric)
    content = {"dataset": dataset, "metric": metric, "preset": preset_name, "rows": rows,
               "failed": {t: run.records[t].get("error") for t in run.failed}}
    (out_dir / "sweep.json").write_text(json.dumps(to_json_value(content), indent=1, allow_nan=False))
    names = list(parse_grid(grid))
    lines = ["| " + " | ".join(names + ["lpd", "rmse", "converged"]) + " |",
             "|" + "---|" * (len(names) + 3)]
    lines += ["| " + " | ".join([f"{row[n]:g}" for n in names] + [f"{row['lpd']:.4g}", f"{row['rmse']:.4g}",
                                                                   str(row["converged"])]) + " |" for row in rows]
    (out_dir / "sweep.md").write_text("\n".join(lines) + "\n")
    if not quiet:
        typer.echo("\n".join(lines))
    _finish(run, quiet)

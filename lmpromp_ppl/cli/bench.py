"""``lmpromp bench``: speed and scale of every engine, side by side (see benchmarks/README.md)."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from lmpromp_ppl.cli import app
from lmpromp_ppl.cli._common import SEED_HELP, SEED_MAX, positive, claim_out_file

__all__ = ["bench_command"]


@app.command("bench")
def bench_command(
    out: Path = typer.Option(..., "--out", help="Output JSON file."),
    quick: bool = typer.Option(False, "--quick", help="Only the default row (every engine); no batch row."),
    device: str = typer.Option("cpu", "--device", help="cpu or gpu (jax's default backend must match)."),
    svi_budget: float = typer.Option(20.0, "--svi-budget", callback=positive, help="SVI: optimisation seconds per guide and row."),
    svi_steps: int = typer.Option(20000, "--svi-steps", min=1, help="SVI: step budget per guide and row."),
    cavi_budget: float = typer.Option(60.0, "--cavi-budget", callback=positive, help="CAVI: seconds per fit when max_iter sweeps would take longer."),
    batch_size: int = typer.Option(1000, "--batch-size", min=0, help="Datasets of the batched-CAVI row (0 skips it)."),
    no_baseline: bool = typer.Option(False, "--no-baseline", help="Skip the ProMP baseline on LASA."),
    gpu_note: str = typer.Option("", "--gpu-note", help="On a CPU run: why no GPU run accompanies it."),
    seed: int = typer.Option(0, min=0, max=SEED_MAX, help=SEED_HELP),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing output file."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Time CAVI, SVI (meanfield, autonormal) and NUTS on the same data; print a table and write JSON."""
    from lmpromp_ppl.bench import DEFAULT_ROW, SCALING_ROWS, BenchConfig, SviSettings, format_table, run_benchmark
    from lmpromp_ppl.errors import LmprompError

    if device not in ("cpu", "gpu"):
        raise LmprompError(f"--device must be cpu or gpu, got {device!r}")
    target = claim_out_file(out, force)
    config = BenchConfig(
        rows=(DEFAULT_ROW,) if quick else (DEFAULT_ROW,) + SCALING_ROWS,
        svi=SviSettings(budget_s=svi_budget, max_steps=svi_steps),
        cavi_budget_s=cavi_budget,
        batch_size=0 if quick else batch_size,
        baseline_dataset="" if no_baseline else "lasa:GShape",
        seed=seed,
        progress=not quiet,
    )
    command = "lmpromp bench " + " ".join(
        part for part in (f"--out {out}", "--quick" if quick else "", f"--device {device}",
                          f"--svi-budget {svi_budget:g}", f"--svi-steps {svi_steps}", f"--cavi-budget {cavi_budget:g}",
                          f"--batch-size {batch_size}", "--no-baseline" if no_baseline else "",
                          f"--seed {seed}") if part
    )

    def write(document: dict) -> None:
        document["command"] = command
        target.write_text(json.dumps(document, indent=2, allow_nan=False) + "\n")

    result = run_benchmark(config, device=device, gpu_note=gpu_note, on_update=write)
    write(result)
    if not quiet:
        typer.echo(format_table(result))
        typer.echo(f"wrote {target}")

"""``lmpromp demo``: the main job on the bundled default dataset.

Plots the LASA ``GShape`` demonstrations and writes the approximation-quality
report (CAVI and the three SVI guides against NUTS) for the LMProMP on them.
``make demo`` runs it into ``demo-output/``.
"""

from __future__ import annotations

from pathlib import Path

import typer

from lmpromp_ppl.cli import app
from lmpromp_ppl.cli._common import SEED_HELP, SEED_MAX, claim_out_dir

__all__ = ["DEMO_DATASET", "demo_command"]

#: The bundled default dataset: LASA handwriting shape G, every 20th sample.
DEMO_DATASET = "lasa:GShape?every=20"


@app.command("demo")
def demo_command(
    out: Path = typer.Option(Path("demo-output"), "--out", help="Output directory."),
    latent_dim: int = typer.Option(2, "--latent-dim", "-V", min=1, help="Latent dimension V."),
    engines: str = typer.Option("cavi,svi,nuts", help="Engines to compare (nuts is the reference)."),
    seed: int = typer.Option(0, min=0, max=SEED_MAX, help=SEED_HELP),
    force: bool = typer.Option(False, "--force", help="Overwrite the files of an existing output."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Plot LASA GShape and compare CAVI and SVI with NUTS on it (report in OUT/compare)."""
    from lmpromp_ppl.cli.data import plot_demonstrations
    from lmpromp_ppl.data import load_dataset
    from lmpromp_ppl.reports import compare

    out_dir = claim_out_dir(out, force)
    demos = load_dataset(DEMO_DATASET)
    plot_demonstrations(demos).savefig(out_dir / "demonstrations.png", dpi=110)
    metrics = compare(DEMO_DATASET, "lmpromp", engines, out_dir=out_dir / "compare", latent_dim=latent_dim,
                      seed=seed, force=force, progress=not quiet)
    if not quiet:
        typer.echo(f"demo: {DEMO_DATASET}, engines {', '.join(metrics['engines'])}; "
                   f"report in {out_dir / 'compare' / 'report.html'}")

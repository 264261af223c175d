"""``lmpromp data``: list the named datasets and plot demonstrations.

``lmpromp data list`` prints one dataset name per line.
``lmpromp data show DATASET --out FILE.png`` draws one panel per DoF (position
over time, or over phase with ``--phase``), coloured by label with a legend,
and prints a one-line summary unless ``--quiet``.  Two-DoF data (LASA) get a
first panel with the path in the plane (x against y, equal aspect) unless
``--no-plane``.
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np
import typer
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from lmpromp_ppl.cli import app
from lmpromp_ppl.cli._common import SEED_MAX, claim_out_file
from lmpromp_ppl.data.core import Demonstrations
from lmpromp_ppl.data.registry import list_datasets, load_dataset
from lmpromp_ppl.errors import LmprompError

__all__ = ["data_app", "plot_demonstrations", "summary_line"]

data_app = typer.Typer(
    name="data",
    help="List the named datasets and plot demonstrations.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

_DATASET_HELP = (
    "lasa:<Shape>[?every=N], gunpoint[:train|:test|:all], synthetic:<name>[?key=value&...], "
    "or a path ending in .npz, .csv or .ts; quote it when it holds ? or & ('lasa:GShape?every=20')"
)


def plot_demonstrations(demos: Demonstrations, *, use_phase: bool = False, plane: bool | None = None) -> Figure:
    """One panel per DoF with every demonstration, coloured by label; for two DoF also the path in the plane.

    Parameters
    ----------
    demos : the demonstrations
    use_phase : plot over the phase in [0, 1] instead of the time
    plane : draw a first panel with the path in the plane (first DoF against
        the second, equal aspect); default: when there are exactly two DoF

    Returns
    -------
    matplotlib.figure.Figure
        An Agg-backed figure (no pyplot state), ready for ``savefig``.
    """
    num_dofs = demos.num_dofs
    plane = (num_dofs == 2) if plane is None else bool(plane)
    if plane and num_dofs != 2:
        raise LmprompError(f"the plane view needs two DoF, {demos.name} has {num_dofs}")
    panels = num_dofs + int(plane)
    ncols = min(panels, 3)
    nrows = math.ceil(panels / ncols)
    fig = Figure(figsize=(4.2 * ncols, 2.8 * nrows + 0.6) if not plane else (4.2 * ncols, 3.6), layout="constrained")
    FigureCanvasAgg(fig)
    all_axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    axes = all_axes[int(plane):]
    xs = demos.phases() if use_phase else demos.times
    if demos.labels is None:
        groups = {"demonstrations": np.arange(demos.num_demos)}
    else:
        groups = {label: np.flatnonzero(demos.labels == label) for label in np.unique(demos.labels)}
    if len(groups) <= 10:
        colours = [f"C{k}" for k in range(len(groups))]
    else:
        colours = [tuple(c) for c in colormaps["turbo"](np.linspace(0.0, 1.0, len(groups)))]
    alpha = 0.8 if demos.num_demos <= 20 else 0.45
    if plane:
        ax = all_axes[0]
        for colour, (label, index) in zip(colours, groups.items()):
            for i in index:
                ax.plot(demos.positions[i][:, 0], demos.positions[i][:, 1], color=colour, linewidth=0.9, alpha=alpha)
                ax.plot(*demos.positions[i][-1], "o", color=colour, markersize=3, alpha=alpha)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"{demos.dof_names[0]} (data units)")
        ax.set_ylabel(f"{demos.dof_names[1]} (data units)")
        ax.set_title("path (dot: end)", fontsize="medium")
        ax.grid(alpha=0.3)
    for k, ax in enumerate(axes[:num_dofs]):
        for colour, (label, index) in zip(colours, groups.items()):
            for n, i in enumerate(index):
                ax.plot(
                    xs[i], demos.positions[i][:, k], color=colour, linewidth=0.9, alpha=alpha,
                    label=str(label) if (k == 0 and n == 0) else None,
                )
        ax.set_ylabel(f"{demos.dof_names[k]} (data units)")
        ax.set_xlabel("phase" if use_phase else "time")
        ax.grid(alpha=0.3)
    for ax in axes[num_dofs:]:
        ax.set_visible(False)
    title = f"{demos.name} ({demos.num_demos} demonstrations)"
    fig.suptitle(textwrap.fill(title, width=45 * ncols, break_long_words=True), fontsize="medium")
    fig.legend(loc="outside lower center", ncols=min(len(groups), 6), frameon=False)
    return fig


def summary_line(demos: Demonstrations) -> str:
    """One line describing the demonstrations: count, DoF, lengths, labels."""
    lengths = demos.lengths
    samples = (
        f"{lengths[0]} samples each"
        if np.all(lengths == lengths[0])
        else f"{lengths.min()}-{lengths.max()} samples"
    )
    if demos.labels is None:
        labels = "no labels"
    else:
        names, counts = np.unique(demos.labels, return_counts=True)
        labels = "labels " + ", ".join(f"{n} ({c})" for n, c in zip(names, counts))
    return (
        f"{demos.name}: {demos.num_demos} demonstrations, {demos.num_dofs} DoF "
        f"({', '.join(demos.dof_names)}), {samples}, {labels}"
    )


@data_app.command("list")
def list_command() -> None:
    """Print the named datasets, one per line (files .npz, .csv, .ts load too)."""
    for name in list_datasets():
        typer.echo(name)


@data_app.command("show")
def show_command(
    dataset: str = typer.Argument(..., help=_DATASET_HELP),
    out: Path = typer.Option(..., "--out", help="Image file to write (.png, .pdf, .svg)."),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing --out."),
    quiet: bool = typer.Option(False, "--quiet", help="Do not print the summary line."),
    seed: int | None = typer.Option(None, "--seed", min=0, max=SEED_MAX, help="Seed of a synthetic generator."),
    phase: bool = typer.Option(False, "--phase", help="Plot over the phase in [0, 1] instead of time."),
    plane: bool = typer.Option(
        True, "--plane/--no-plane", help="Two-DoF data: add the path in the plane (x vs y, equal aspect)."
    ),
) -> None:
    """Plot DATASET's demonstrations, one panel per DoF, coloured by label (two DoF: also the path in the plane)."""
    suffix = out.suffix.lower().lstrip(".")
    supported = FigureCanvasAgg(Figure()).get_supported_filetypes()
    if suffix not in supported:
        raise LmprompError(
            f"cannot write a figure to {out}: unknown image type {suffix or '(none)'!r}; "
            f"use one of {', '.join(sorted(supported))}"
        )
    out = claim_out_file(out, force)
    demos = load_dataset(dataset, seed=seed)
    fig = plot_demonstrations(demos, use_phase=phase, plane=plane and demos.num_dofs == 2)
    fig.savefig(out, dpi=120)
    if not quiet:
        typer.echo(f"{summary_line(demos)} -> {out}")


app.add_typer(data_app, name="data")

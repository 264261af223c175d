"""PNG figures of the ``lmpromp compare`` report (matplotlib; arviz-plots for densities).

The figures are built with matplotlib's object API (:class:`matplotlib.figure.Figure`
saved through :class:`~matplotlib.backends.backend_agg.FigureCanvasAgg`), so
importing or calling this module never changes the pyplot backend a user or a
notebook has chosen, and never closes the user's figures.  Every axis is
labelled; layouts are constrained so titles stay clear of tick labels.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

__all__ = ["plot_traces", "plot_marginals", "plot_sd_ratios", "plot_predictive", "plot_latent"]


def _figure(ncols: int, size: tuple[float, float], nrows: int = 1):
    """A constrained-layout figure with an Agg canvas (no pyplot state) and its axes grid."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    return fig, fig.subplots(nrows, ncols, squeeze=False)


def _dof_label(demos, k: int) -> str:
    names = getattr(demos, "dof_names", ()) or ()
    return f"{names[k] if k < len(names) else f'DoF {k}'} (data units)"


def plot_traces(optimization: Mapping[str, Mapping[str, np.ndarray]], path: Path) -> Path | None:
    """ELBO traces (CAVI) and loss traces (SVI), one panel per engine; None when there are none."""
    traces = {(e, k): np.asarray(v, dtype=float) for e, opt in optimization.items() for k, v in opt.items() if len(v)}
    if not traces:
        return None
    fig, axes = _figure(len(traces), (4.2 * len(traces), 3.2))
    for ax, ((engine, name), values) in zip(axes[0], traces.items()):
        ax.plot(np.arange(1, values.size + 1), values, lw=1)
        ax.set_title(f"{engine}: {name}")
        ax.set_xlabel("iteration")
        ax.set_ylabel({"elbo": "ELBO", "loss": "loss (negative ELBO)"}.get(name, name))
        if name == "loss" and np.all(values > 0):
            ax.set_yscale("log")
    fig.savefig(path, dpi=90)
    return path


def plot_marginals(quantities: Mapping[str, Mapping[str, np.ndarray]], path: Path,
                   names=("alpha", "lam", "gram_eig", "b"), max_elements: int = 4) -> Path | None:
    """Marginal densities of every engine overlaid (``arviz_plots.plot_dist``).

    ``quantities``: engine -> name -> (num_draws, ...) flattened-sample draws.
    Each engine is subsampled to the same number of draws (arviz-plots
    overlays models of equal shape); at most ``max_elements`` elements per
    quantity are shown.
    """
    import arviz_plots
    import matplotlib.pyplot as plt  # arviz-plots draws through pyplot; the backend is left as it is
    import xarray as xr

    engines = list(quantities)
    names = [n for n in names if all(n in quantities[e] for e in engines)]
    if not names:
        return None
    num = min(next(iter(quantities[e].values())).shape[0] for e in engines)
    trees = {}
    for e in engines:
        data = {}
        for n in names:
            x = np.asarray(quantities[e][n], dtype=float)[:num].reshape(num, -1)[:, :max_elements]
            if x.shape[1] == 1:
                data[n] = (("chain", "draw"), x[None, :, 0])
            else:
                data[n] = (("chain", "draw", f"{n}_element"), x[None])
        trees[e] = xr.DataTree.from_dict({"posterior": xr.Dataset(data)})
    pc = arviz_plots.plot_dist(
        trees, var_names=names, backend="matplotlib", kind="kde",
        visuals={"credible_interval": False, "point_estimate": False, "point_estimate_text": False},
    )
    pc.add_legend("model")
    fig = pc.get_viz("figure")
    for ax in fig.axes:
        if not ax.get_xlabel():
            ax.set_xlabel(ax.get_title() or "value")
        if not ax.get_ylabel():
            ax.set_ylabel("density")
    pc.savefig(path, dpi=80)
    plt.close(fig)  # only this figure
    return path


def plot_sd_ratios(ratios: Mapping[str, Mapping[str, np.ndarray]], path: Path) -> Path | None:
    """Forest plot of the sd ratios VI / NUTS: median (dot) and range (line) per engine and quantity, log scale."""
    rows = [(e, q, np.asarray(r, dtype=float)) for e, per in ratios.items() for q, r in per.items()]
    rows = [(e, q, r[np.isfinite(r)]) for e, q, r in rows]
    rows = [row for row in rows if row[2].size]
    if not rows:
        return None
    fig, axes = _figure(1, (6.5, 0.32 * len(rows) + 1.2))
    ax = axes[0][0]
    engines = sorted({e for e, _, _ in rows}, key=list(ratios).index)
    colours = {e: f"C{i}" for i, e in enumerate(engines)}
    for y, (e, q, r) in enumerate(rows):
        ax.plot([r.min(), r.max()], [y, y], color=colours[e], lw=1.5)
        ax.plot([np.median(r)], [y], "o", color=colours[e])
    ax.axvline(1.0, color="k", lw=0.8, ls="--")
    ax.set_xscale("log")
    ax.set_yticks(range(len(rows)), [f"{e}: {q}" for e, q, _ in rows])
    ax.invert_yaxis()
    ax.set_xlabel("sd ratio VI / NUTS (1 = same spread; < 1 = VI too narrow)")
    ax.set_ylabel("engine: quantity")
    fig.savefig(path, dpi=90)
    return path


def plot_predictive(bands: Mapping[str, tuple[np.ndarray, np.ndarray]], phase: np.ndarray, demos, path: Path) -> Path:
    """Predictive mean +- 2 sd of a new demonstration per engine, over the demonstrations, per DoF.

    ``bands``: engine -> (mean (P, D), sd (P, D)) in data units; ``demos`` the
    raw :class:`~lmpromp_ppl.data.Demonstrations`.
    """
    num_dofs = demos.num_dofs
    fig, axes = _figure(num_dofs, (4.5 * num_dofs, 3.4))
    for k, ax in enumerate(axes[0]):
        for z, y in zip(demos.phases(), demos.positions):
            ax.plot(z, y[:, k], color="0.6", lw=0.7)
        for i, (engine, (mean, sd)) in enumerate(bands.items()):
            ax.plot(phase, mean[:, k], color=f"C{i}", lw=1.5, label=engine)
            ax.fill_between(phase, mean[:, k] - 2 * sd[:, k], mean[:, k] + 2 * sd[:, k], color=f"C{i}", alpha=0.15)
        ax.set_title(demos.dof_names[k])
        ax.set_xlabel("phase")
        ax.set_ylabel(_dof_label(demos, k))
    axes[0][0].legend(fontsize="small")
    fig.savefig(path, dpi=90)
    return path


def plot_latent(coords: Mapping[str, np.ndarray], labels: np.ndarray | None, path: Path, title: str,
                axis_labels: tuple[str, str] = ("latent dim 1", "latent dim 2")) -> Path:
    """Posterior-mean latent coordinates (L, 2) per engine, coloured by label where labels exist.

    ``axis_labels`` name the two coordinates (x, y).
    """
    fig, axes = _figure(len(coords), (3.6 * len(coords), 3.4))
    if labels is not None:
        classes = sorted(set(labels.tolist()))
        colour = np.array([classes.index(label) for label in labels])
    for ax, (engine, xy) in zip(axes[0], coords.items()):
        if labels is None:
            ax.scatter(xy[:, 0], xy[:, 1], s=14)
        else:
            for c, name in enumerate(classes):
                ax.scatter(xy[colour == c, 0], xy[colour == c, 1], s=14, color=f"C{c}", label=name)
        ax.set_title(engine)
        ax.set_xlabel(axis_labels[0])
        ax.set_ylabel(axis_labels[1])
    if labels is not None:
        axes[0][0].legend(fontsize="small")
    fig.suptitle(title, fontsize="medium")
    fig.savefig(path, dpi=90)
    return path

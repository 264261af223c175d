r"""Do the default settings give movement distributions that match real demonstrations?

``lmpromp real-data`` fits every dataset of a list with the default settings
of an engine and measures, in units of the data's standard deviation (per DoF,
then the root mean square over DoF):

* ``pop_rmse``: RMSE between the population predictive mean (the movement
  distribution of a new demonstration, conditioned on nothing) and the
  pointwise mean of the demonstrations (each interpolated onto a common phase
  grid);
* ``coverage90``: leave-one-demonstration-out coverage of the held-out
  demonstration's points by the central 90 % predictive band *including
  observation noise* (``sd_obs``), averaged over folds;
* ``halfwidth``: the mean half-width of that band;
* ``cond_rmse_observed``: conditioning on the first third of the held-out
  demonstration with the default ``predict`` (exact, Bayesian), the RMSE on
  the observed third; it passes below 0.5, or below 1.2 times the fitted noise
  s.d. (``noise_sd``) where the recording is noisier than that;
* ``cond_rmse_rest`` and ``uncond_rmse_rest``: the RMSE on the remaining two
  thirds with and without that conditioning; it passes when conditioning helps;
* ``max_abs_w``: the largest posterior-mean weight in standardised units.

Every figure is averaged over the folds; the per-fold values are kept in
``real-data.json``.  Mixtures are judged separately (:func:`mixture_rows`): on
pooled LASA shapes the mixture with K = 6 should keep as many active
components as there are shapes, with an adjusted Rand index (ARI) of at least
0.9 against the shapes.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "CRITERIA",
    "POOLED_LASA",
    "default_datasets",
    "dataset_row",
    "mixture_rows",
    "passes",
    "coverage_se",
    "markdown_table",
    "mixture_table",
    "write_report",
]

#: Half-width of the central 90 % band of a standard normal.
_Z90 = 1.6448536269514722

#: Pooled LASA shape sets for the mixture check.
POOLED_LASA = (
    "lasa:GShape+Angle+Sshape?every=20",
    "lasa:CShape+Worm+Zshape+Leaf_1?every=20",
    "lasa:Trapezoid+Snake+BendedLine?every=20",
    "lasa:Khamesh+Spoon+NShape+Sine?every=20",
)


def default_datasets() -> list[str]:
    """All 30 LASA shapes, GunPoint and two synthetic datasets."""
    from lmpromp_ppl.data.lasa import lasa_shapes

    return (
        [f"lasa:{shape}?every=10" for shape in lasa_shapes()]
        + ["gunpoint:train", "synthetic:latent?L=20&D=2&J=10&V=3&seed=0", "synthetic:reaching"]
    )


def passes(row: dict) -> dict[str, bool]:
    """Which criteria of :data:`CRITERIA` a dataset row meets."""
    noise = row.get("noise_sd") or 0.0
    return {
        "pop_rmse": row["pop_rmse"] < 0.25,
        "coverage90": 0.80 <= row["coverage90"] <= 0.98,
        "cond_rmse_observed": row["cond_rmse_observed"] < max(0.5, 1.2 * noise),
        "cond_rmse_rest": row["cond_rmse_rest"] < row["uncond_rmse_rest"],
    }


#: The pass rules of the issue, by column.
CRITERIA = {
    "pop_rmse": "< 0.25",
    "coverage90": "in [0.80, 0.98]",
    "cond_rmse_observed": "< max(0.5, 1.2 noise_sd)",
    "cond_rmse_rest": "< uncond_rmse_rest",
}


def _rms_over_dofs(err: np.ndarray, scale: np.ndarray) -> float:
    """RMSE per DoF divided by that DoF's s.d., then the root mean square over DoF; ``err`` (..., D)."""
    per_dof = np.sqrt(np.nanmean((err.reshape(-1, err.shape[-1])) ** 2, axis=0)) / scale
    return float(np.sqrt(np.mean(per_dof**2)))


def _demo_mean_on(demos, phase: np.ndarray) -> np.ndarray:
    stacked = []
    for z, y in zip(demos.phases(), demos.positions):
        stacked.append(np.stack([np.interp(phase, z, y[:, k]) for k in range(y.shape[1])], axis=-1))
    return np.mean(stacked, axis=0)


@dataclass
class FoldResult:
    coverage90: float
    halfwidth: float
    cond_rmse_observed: float
    cond_rmse_rest: float
    uncond_rmse_rest: float
    noise_sd: float
    seconds: float


@dataclass
class Fitter:
    """How to fit one engine with its default settings (``options`` go to :func:`lmpromp_ppl.fit`)."""

    engine: str
    model: str = "lmpromp"
    options: dict = field(default_factory=dict)

    def __call__(self, demos, seed: int):
        from lmpromp_ppl.api import fit

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return fit(demos, model=self.model, engine=self.engine, seed=seed, **self.options)


def _fold(fitter: Fitter, demos, held: int, seed: int) -> FoldResult:
    from lmpromp_ppl.predict.from_fit import population_prediction, predict_from_fit

    start = time.perf_counter()
    train = demos.subset([j for j in range(demos.num_demos) if j != held])
    result = fitter(train, seed)
    scale = np.asarray(result.scaling.scale, dtype=float)
    z, y = demos.phases()[held], demos.positions[held]
    pop = population_prediction(result, query=z, num_samples=1)
    inside = np.abs(y - pop.mean) <= _Z90 * pop.sd_obs
    third = max(1, z.shape[0] // 3)
    cond = predict_from_fit(result, z[:third], y[:third], query=z, num_samples=1)
    noise = float(np.sqrt(np.mean((pop.noise_sd / scale) ** 2)))
    return FoldResult(
        coverage90=float(np.mean(inside)),
        halfwidth=float(np.sqrt(np.mean(np.mean(_Z90 * pop.sd_obs, axis=0) ** 2 / scale**2))),
        cond_rmse_observed=_rms_over_dofs(cond.mean[:third] - y[:third], scale),
        cond_rmse_rest=_rms_over_dofs(cond.mean[third:] - y[third:], scale),
        uncond_rmse_rest=_rms_over_dofs(pop.mean[third:] - y[third:], scale),
        noise_sd=noise,
        seconds=time.perf_counter() - start,
    )


def dataset_row(
    dataset: str,
    engine: str = "cavi",
    *,
    max_folds: int = 8,
    seed: int = 0,
    options: dict | None = None,
    demos=None,
) -> dict:
    """Every figure of the module docstring for one dataset and engine.

    ``max_folds`` held-out demonstrations are spread evenly over the dataset
    (all of them when it has fewer).
    """
    from lmpromp_ppl.data import load_dataset
    from lmpromp_ppl.predict.from_fit import population_prediction

    demos = load_dataset(dataset) if demos is None else demos
    fitter = Fitter(engine, options=dict(options or {}))
    start = time.perf_counter()
    full = fitter(demos, seed)
    scale = np.asarray(full.scaling.scale, dtype=float)
    pop = population_prediction(full, num_samples=1)
    pop_rmse = _rms_over_dofs(pop.mean - _demo_mean_on(demos, pop.phase), scale)
    point_w = full.point.get("w")
    if point_w is None and full.draws is not None:
        point_w = np.mean(full.draws["w"], axis=(0, 1))
    max_abs_w = float(np.max(np.abs(point_w)))
    L = demos.num_demos
    held = np.unique(np.linspace(0, L - 1, min(L, max_folds)).round().astype(int))
    folds = [_fold(fitter, demos, int(i), seed) for i in held]
    row = {
        "dataset": dataset,
        "engine": engine,
        "num_demos": L,
        "num_dofs": demos.num_dofs,
        "pop_rmse": pop_rmse,
        "max_abs_w": max_abs_w,
        "warnings": list(full.summary.get("warnings", [])),
        "folds": [int(i) for i in held],
    }
    for name in ("coverage90", "halfwidth", "cond_rmse_observed", "cond_rmse_rest", "uncond_rmse_rest", "noise_sd"):
        row[name] = float(np.mean([getattr(f, name) for f in folds]))
    row["per_fold"] = [vars(f) for f in folds]
    row["seconds"] = time.perf_counter() - start
    row["passes"] = passes(row)
    return row


def mixture_rows(
    datasets: Sequence[str],
    *,
    seeds: Sequence[int] = tuple(range(10)),
    num_components: int = 6,
    latent_dim: int = 2,
    num_basis: int | str = "auto",
    on_row: Callable[[dict], None] | None = None,
) -> list[dict]:
    """The mixture with K components on labelled data, per seed: active components and ARI.

    V = 2 by default: on every pooled LASA set the bound of the types' partition is
    higher with V = 2 than with the single-type default V = 3 (docs/defaults.md).
    The basis is chosen by the bound (``num_basis="auto"``, once per dataset: the
    selection does not depend on the seed): each
    extra component pays an Occam factor that grows with the number of weights,
    and a basis finer than the data need hides the types (docs/defaults.md,
    *Choosing J by the bound*).
    """
    from lmpromp_ppl.api import fit, select_num_basis
    from lmpromp_ppl.data import load_dataset
    from lmpromp_ppl.models.hyper import preset

    rows = []
    hyper = preset("default", num_components=num_components, latent_dim=latent_dim)
    for dataset in datasets:
        demos = load_dataset(dataset)
        num_types = len(set(np.asarray(demos.labels).tolist())) if demos.labels is not None else None
        J = num_basis
        if J == "auto":
            # what fit(..., num_basis="auto") does for every seed: the selection's
            # single-type CAVI fits start deterministically (no restarts)
            J = select_num_basis(demos, hyper=hyper)["num_basis"]
        for seed in seeds:
            start = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                result = fit(demos, model="mixture", engine="cavi", hyper=hyper, num_basis=J, seed=seed)
            active = result.summary.get("active_components") or []
            row = {
                "dataset": dataset,
                "seed": int(seed),
                "num_types": num_types,
                "num_basis": int(result.num_basis),
                "active_components": len(active),
                "ari": result.summary.get("ari"),
                "elbo": result.summary.get("elbo"),
                "seconds": time.perf_counter() - start,
            }
            rows.append(row)
            if on_row is not None:
                on_row(row)
    return rows


def _fmt(x, digits=3) -> str:
    if x is None:
        return "–"
    if isinstance(x, float):
        return f"{x:.{digits}g}" if abs(x) < 1000 else f"{x:.0f}"
    return str(x)


def coverage_se(row: dict) -> float | None:
    """Standard error of a row's LOO coverage over its folds (None with one fold).

    A held-out demonstration's points are strongly correlated (one smooth
    curve), so the folds, not the points, are the independent replicates.
    """
    values = [f["coverage90"] for f in row.get("per_fold", [])]
    if len(values) < 2:
        return None
    return float(np.std(values, ddof=1) / np.sqrt(len(values)))


def markdown_table(rows: Sequence[dict]) -> str:
    """One line per dataset and engine; a failed criterion is marked ✗."""
    head = (
        "| dataset | engine | L | pop RMSE | LOO cov. 90 % | half-width | cond. RMSE observed | "
        "cond. RMSE rest | uncond. RMSE rest | noise s.d. | max abs(w) | all pass |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in rows:
        ok = r["passes"]

        def cell(name):
            mark = "" if ok.get(name, True) else " ✗"
            se = coverage_se(r) if name == "coverage90" else None
            return _fmt(r[name]) + ("" if se is None else f" ± {se:.2f}") + mark

        lines.append(
            f"| `{r['dataset']}` | {r['engine']} | {r['num_demos']} | {cell('pop_rmse')} | {cell('coverage90')} | "
            f"{_fmt(r['halfwidth'])} | {cell('cond_rmse_observed')} | {cell('cond_rmse_rest')} | "
            f"{_fmt(r['uncond_rmse_rest'])} | {_fmt(r['noise_sd'])} | {_fmt(r['max_abs_w'])} | "
            f"{'yes' if all(ok.values()) else 'no'} |"
        )
    return head + "\n".join(lines) + "\n"


def mixture_table(rows: Sequence[dict]) -> str:
    """Per dataset: seeds with the right number of active components and ARI >= 0.9."""
    out = [
        "| dataset | types | J | seeds | active = types | ARI >= 0.9 | both | median ARI | min ARI |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for dataset in dict.fromkeys(r["dataset"] for r in rows):
        sub = [r for r in rows if r["dataset"] == dataset]
        aris = [r["ari"] for r in sub if r["ari"] is not None]
        right = [r["active_components"] == r["num_types"] for r in sub]
        good = [r["ari"] is not None and r["ari"] >= 0.9 for r in sub]
        both = sum(a and b for a, b in zip(right, good))
        sizes = sorted({r["num_basis"] for r in sub if r.get("num_basis") is not None})
        J = ", ".join(str(j) for j in sizes) or "?"
        out.append(
            f"| `{dataset}` | {sub[0]['num_types']} | {J} | {len(sub)} | {sum(right)} | {sum(good)} | {both} | "
            f"{_fmt(float(np.median(aris)) if aris else None)} | {_fmt(float(np.min(aris)) if aris else None)} |"
        )
    return "\n".join(out) + "\n"


def overview_figure(datasets: Sequence[str], path, *, seed: int = 0) -> None:
    """Demonstrations and the default CAVI fit's population band (90 %, with noise) for a few datasets."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from lmpromp_ppl.data import load_dataset
    from lmpromp_ppl.predict.from_fit import population_prediction

    n = len(datasets)
    cols = min(4, n)
    rows = -(-n // cols)
    fig = Figure(figsize=(3.6 * cols, 3.2 * rows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax, dataset in zip(axes, datasets):
        demos = load_dataset(dataset)
        result = Fitter("cavi")(demos, seed)
        pop = population_prediction(result, num_samples=1)
        names = list(demos.dof_names) if demos.dof_names else [f"DoF {k}" for k in range(demos.num_dofs)]
        if demos.num_dofs == 2:
            for y in demos.positions:
                ax.plot(y[:, 0], y[:, 1], color="0.6", lw=0.8)
            ax.plot(pop.mean[:, 0], pop.mean[:, 1], color="tab:blue", lw=2, label="predictive mean")
            ax.set_xlabel(f"{names[0]} (data units)")
            ax.set_ylabel(f"{names[1]} (data units)")
            ax.set_aspect("equal", adjustable="datalim")
        else:
            for z, y in zip(demos.phases(), demos.positions):
                ax.plot(z, y[:, 0], color="0.6", lw=0.6)
            half = _Z90 * pop.sd_obs[:, 0]
            ax.fill_between(pop.phase, pop.mean[:, 0] - half, pop.mean[:, 0] + half, color="tab:blue", alpha=0.2,
                            label="90 % band (with noise)")
            ax.plot(pop.phase, pop.mean[:, 0], color="tab:blue", lw=2, label="predictive mean")
            ax.set_xlabel("phase")
            ax.set_ylabel(f"{names[0]} (data units)")
        ax.set_title(dataset.split("?")[0], fontsize=9)
    for ax in axes[n:]:
        ax.set_visible(False)
    axes[0].legend(fontsize=7)
    fig.savefig(path, dpi=100)


def write_report(out, rows: Sequence[dict], mixture: Sequence[dict], *, command: str, figure: Sequence[str] = ()) -> None:
    """``real-data.md`` and ``real-data.json`` (and ``predictive.png``) in ``out``."""
    import json
    from pathlib import Path

    from lmpromp_ppl.results import package_versions, to_json_value

    out = Path(out)
    summary = []
    for engine in dict.fromkeys(r["engine"] for r in rows):
        sub = [r for r in rows if r["engine"] == engine]
        for name in CRITERIA:
            ok = sum(r["passes"][name] for r in sub)
            summary.append(f"| {engine} | `{name}` {CRITERIA[name]} | {ok} / {len(sub)} |")
        summary.append(f"| {engine} | mean LOO coverage over datasets (nominal 0.90) | "
                       f"{np.mean([r['coverage90'] for r in sub]):.3f} |")
    text = [
        "# Default settings on real demonstrations",
        "",
        f"Generated by `{command}`.",
        "",
        "Every figure is in units of the data's standard deviation (per DoF, then the root mean square over",
        "DoF), from the default settings of each engine (`lmpromp_ppl.fit` without options).  `pop RMSE`:",
        "population predictive mean against the pointwise mean of the demonstrations.  `LOO cov. 90 %`:",
        "leave-one-demonstration-out coverage of the held-out points by the central 90 % band including",
        "observation noise, ± its standard error over the folds; `half-width` is that band's half-width.  `cond. RMSE`: default `predict` on the",
        "first third of the held-out demonstration, RMSE on the observed third and on the remaining two thirds",
        "(`uncond.`: the population mean instead).  `noise s.d.`: the fitted observation noise.  `max abs(w)`:",
        "the largest posterior-mean weight (standardised units).  ✗ marks a failed criterion.",
        "",
        *[f"{engine} ran with the options {options}." for engine, options in
          {r["engine"]: r["engine_options"] for r in rows if r.get("engine_options")}.items()],
        "",
        "## Criteria met",
        "",
        "| engine | criterion | datasets |",
        "|---|---|---|",
        *summary,
        "",
        "## Per dataset",
        "",
        markdown_table(rows),
    ]
    warned = [r for r in rows if r["warnings"]]
    if warned:
        text += ["## Degeneracy warnings of the full fits", ""]
        text += [f"* `{r['dataset']}` ({r['engine']}): {'; '.join(r['warnings'])}" for r in warned]
        text.append("")
    if mixture:
        text += [
            "## Mixtures",
            "",
            "The mixture LMProMP (CAVI, K = 6, V = 2, default settings) on labelled data, one fit per seed,",
            "with the basis size J chosen by the bound (`num_basis=\"auto\"`; `J` lists the sizes chosen):",
            "how often the number of active components equals the number of movement types, and the",
            "adjusted Rand index (ARI) of the most responsible component against the labels.",
            "",
            mixture_table(mixture),
        ]
    if figure:
        text += ["## Population predictive (CAVI)", "", "![predictive](predictive.png)", ""]
    (out / "real-data.md").write_text("\n".join(text))
    document = {"command": command, "rows": rows, "mixture": list(mixture), "criteria": CRITERIA,
                "package_versions": package_versions()}
    (out / "real-data.json").write_text(json.dumps(to_json_value(document), indent=1) + "\n")
    if figure:
        overview_figure(figure, out / "predictive.png")

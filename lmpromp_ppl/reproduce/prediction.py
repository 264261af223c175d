r"""Leave-one-out prediction of the rest of a movement from its initial segment (thesis Sec. 5.2).

The thesis predicts the ball's impact from the first part of a table-tennis
stroke under observation noise and sparse observations (Fig. 5.5).  Here:
for each held-out demonstration of a dataset, the models are trained on the
others, conditioned on the held-out movement's first ``observed_fraction`` of
phase, and scored on the rest of it:

* RMSE of the predicted mean against the clean held-out trajectory, in units
  of the training set's per-DoF standard deviation;
* log predictive density per row of the clean remainder (nats), with target
  noise s.d. :data:`TARGET_SD` (standardised units) for every model.

Noise of s.d. ``noise`` times each DoF's standard deviation is added to every
demonstration (training and observed segment); sparser observations keep
every ``interval``-th time sample (masked entries, so the compiled fits are
shared).  Conditioning uses the exact :math:`p(\mathbf w | \mathbf o)` of the
held-out movement (``exact=True`` of :func:`lmpromp_ppl.predict.condition`)
with observation variance :math:`\beta^{-1} + \sigma_{noise}^2`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from lmpromp_ppl.data.core import Demonstrations
from lmpromp_ppl.models.hyper import Hyperparameters
from lmpromp_ppl.models.registry import MODEL_NAMES
from lmpromp_ppl.predict import condition, observe, score_heldout
from lmpromp_ppl.reproduce._common import (
    SETTINGS,
    FitOutcome,
    Settings,
    fit_lmpromp,
    fit_mixture,
    fit_promp,
    mean_se,
    standardised_model_data,
)

__all__ = [
    "TARGET_SD",
    "MODEL_NAMES",
    "Setting",
    "Task",
    "FoldResult",
    "noisy_copy",
    "fit_models",
    "predict_remainder",
    "run_fold",
    "loo_sweep",
    "summarise",
    "effective_rank",
    "LASA_SHAPES",
    "prediction_tasks",
    "gain_counts",
    "verdict_from_counts",
    "sweep_table",
    "sweep_figure",
]

#: Target-noise standard deviation (standardised units) of the held-out log density: beta = 100.
TARGET_SD = 0.1
#: Models compared, in plotting order.


@dataclass(frozen=True)
class Setting:
    """One point of a sweep.

    Attributes
    ----------
    noise : noise s.d. as a fraction of each DoF's standard deviation
    interval : keep every ``interval``-th time sample (training and observed segment)
    train_size : number of training demonstrations (None: all but the held-out one)
    observed_fraction : phase up to which the held-out movement is observed
    """

    noise: float = 0.0
    interval: int = 1
    train_size: int | None = None
    observed_fraction: float = 0.3


@dataclass(frozen=True)
class Task:
    """A dataset for the prediction experiments.

    Attributes
    ----------
    label : name in tables and figures
    demos : demonstrations of equal length
    num_basis : J
    latent_dim : V
    folds : held-out demonstrations (indices)
    width : basis width
    """

    label: str
    demos: Demonstrations
    num_basis: int
    latent_dim: int
    folds: tuple[int, ...]
    width: float


@dataclass
class FoldResult:
    """Scores of every model on one held-out demonstration (None when a fit or score is not finite)."""

    rmse: dict
    lpd: dict
    converged: dict
    finite: dict
    fits: dict


def noisy_copy(demos: Demonstrations, noise: float, rng: np.random.Generator) -> Demonstrations:
    """``demos`` plus Gaussian noise of s.d. ``noise`` times each DoF's standard deviation."""
    if noise == 0:
        return demos
    sd = np.concatenate(demos.positions).std(axis=0)
    return demos.with_positions([y + noise * sd * rng.standard_normal(y.shape) for y in demos.positions])


def fit_models(data, hyper: Hyperparameters, models: Sequence[str], seed: int) -> dict[str, FitOutcome]:
    """Fit each of ``models`` (``promp``, ``lmpromp``, ``mixture``) to ``data``."""
    fits = {}
    for name in models:
        if name == "promp":
            fits[name] = fit_promp(data)
        elif name == "lmpromp":
            fits[name] = fit_lmpromp(data, hyper, seed)
        else:
            fits[name] = fit_mixture(data, hyper.replace(num_components=max(hyper.num_components, 2)), seed, 1)
    return fits


_SITES = {"promp": ("mu_w", "Sigma_w"), "lmpromp": ("b", "M", "alpha"), "mixture": ("pi", "b", "M", "alpha")}


def predict_remainder(
    model: str,
    fit: FitOutcome,
    phases: np.ndarray,
    noisy: np.ndarray,
    clean: np.ndarray,
    keep: np.ndarray,
    setting: Setting,
    observation_var: np.ndarray,
    num_basis: int,
    gamma: float,
    width: float,
) -> tuple[float | None, float | None]:
    """(RMSE, log density per row) of the clean remainder given the observed initial segment.

    ``noisy`` and ``clean`` are (T, D) in the standardised units of the fit;
    ``observation_var`` (D,) is the conditioning noise variance per DoF.
    """
    if not fit.finite:
        return None, None
    num_dofs = noisy.shape[1]
    seen = (phases <= setting.observed_fraction) & keep
    rest = phases > setting.observed_fraction
    obs = observe(phases[seen], noisy[seen], noise_sd=np.sqrt(observation_var), num_dofs=num_dofs,
                  num_basis=num_basis, width=width)
    target = observe(phases[rest], clean[rest], noise_sd=TARGET_SD, num_dofs=num_dofs, num_basis=num_basis,
                     width=width)
    params = {k: fit.params[k] for k in _SITES[model]}
    conditioned = condition(model, params, obs, gamma, exact=True)
    score = score_heldout(conditioned.weights, target)
    rmse, lpd = float(score.rmse), float(score.log_density_per_row)
    return (rmse if math.isfinite(rmse) else None), (lpd if math.isfinite(lpd) else None)


def run_fold(
    task: Task,
    noisy: Demonstrations,
    held_out: int,
    setting: Setting,
    hyper: Hyperparameters,
    models: Sequence[str],
    rng: np.random.Generator,
    seed: int,
    train_eval: int = 0,
) -> tuple[FoldResult, FoldResult | None]:
    """Train on all demonstrations but ``held_out`` (or a random ``train_size`` of them), score the held-out one.

    With ``train_eval`` > 0 the same prediction is also scored on that many
    training demonstrations (the training error of Fig. 5.6A).

    Returns
    -------
    (test, train) fold results; train is None without ``train_eval``.
    """
    demos = task.demos
    others = np.array([i for i in range(demos.num_demos) if i != held_out])
    if setting.train_size is not None:
        others = np.sort(rng.choice(others, size=setting.train_size, replace=False))
    hyper = hyper.replace(latent_dim=min(task.latent_dim, len(others) - 1))
    keep = np.arange(demos.lengths[0]) % setting.interval == 0
    data, scaling, _ = standardised_model_data(noisy.subset(others), task.num_basis, keep, width=task.width)
    fits = fit_models(data, hyper, models, seed)
    noise_sd = setting.noise * np.concatenate(demos.positions).std(axis=0)

    def score(index: int) -> FoldResult:
        phases = demos.phases()[index]
        noisy_i = scaling.apply(noisy.positions[index])
        clean_i = scaling.apply(demos.positions[index])
        result = FoldResult({}, {}, {}, {}, fits)
        for name, fit in fits.items():
            beta = float(fit.params.get("beta", hyper.beta)) if name != "promp" else hyper.beta
            variance = 1.0 / beta + (noise_sd / scaling.scale) ** 2
            rmse, lpd = predict_remainder(
                name, fit, phases, noisy_i, clean_i, keep, setting, variance, task.num_basis, hyper.gamma, task.width
            )
            result.rmse[name], result.lpd[name] = rmse, lpd
            result.converged[name], result.finite[name] = fit.converged, fit.finite
        return result

    test = score(held_out)
    if train_eval <= 0:
        return test, None
    train_scores = [score(int(i)) for i in others[:train_eval]]
    train = FoldResult(
        {m: _mean_or_none([r.rmse[m] for r in train_scores]) for m in fits},
        {m: _mean_or_none([r.lpd[m] for r in train_scores]) for m in fits},
        test.converged,
        test.finite,
        fits,
    )
    return test, train


def _mean_or_none(values: list) -> float | None:
    finite = [v for v in values if v is not None]
    return float(np.mean(finite)) if len(finite) == len(values) and finite else None


def summarise(results: Sequence[FoldResult], models: Sequence[str]) -> dict:
    """Per model: mean and standard error over folds of RMSE and log density, counts of failures.

    Each model other than ``promp`` also gets ``rmse_gain`` (ProMP's RMSE minus
    the model's) and ``lpd_gain`` (the model's log density minus ProMP's), paired
    over folds: mean and standard error (positive: better than the ProMP).
    """
    out = {}
    for name in models:
        rmse = [r.rmse[name] for r in results]
        lpd = [r.lpd[name] for r in results]
        rmse_mean, rmse_se = mean_se(rmse)
        lpd_mean, lpd_se = mean_se(lpd)
        out[name] = {
            "rmse_mean": rmse_mean,
            "rmse_se": rmse_se,
            "lpd_mean": lpd_mean,
            "lpd_se": lpd_se,
            "folds": len(results),
            "nonfinite": sum(r.rmse[name] is None or r.lpd[name] is None for r in results),
            "not_converged": sum(not r.converged[name] for r in results),
        }
        if name != "promp" and "promp" in models:
            for metric, sign in (("rmse", -1.0), ("lpd", 1.0)):
                pairs = [
                    sign * (getattr(r, metric)[name] - getattr(r, metric)["promp"])
                    for r in results
                    if getattr(r, metric)[name] is not None and getattr(r, metric)["promp"] is not None
                ]
                gain, gain_se = mean_se(pairs)
                out[name][f"{metric}_gain_mean"], out[name][f"{metric}_gain_se"] = gain, gain_se
    return out


def loo_sweep(
    task: Task,
    settings: Sequence[Setting],
    hyper: Hyperparameters,
    models: Sequence[str],
    seed: int,
    bar=None,
) -> list[dict]:
    """Leave-one-out over ``task.folds`` for each setting; one summary dict per setting."""
    rows = []
    for index, setting in enumerate(settings):
        rng = np.random.default_rng([seed, index])
        noisy = noisy_copy(task.demos, setting.noise, rng)
        results = []
        for fold in task.folds:
            test, _ = run_fold(task, noisy, fold, setting, hyper, models, rng, seed)
            results.append(test)
            if bar is not None:
                bar.update()
        rows.append({"setting": setting.__dict__.copy(), "models": summarise(results, models)})
    return rows


def effective_rank(M: np.ndarray, h: np.ndarray) -> dict:
    r"""Complexity of the learned model from the singular values of :math:`M H^T` (Sec. 5.3).

    Returns ``numerical`` (singular values above 1e-3 of the largest) and
    ``entropy`` (Roy and Vetterli's :math:`\exp(-\sum_k p_k \log p_k)`,
    :math:`p_k = s_k / \sum_j s_j`).
    """
    s = np.linalg.svd(np.asarray(M) @ np.asarray(h).T, compute_uv=False)
    if s.size == 0 or s[0] <= 0:
        return {"numerical": 0, "entropy": 0.0}
    p = s / s.sum()
    p = p[p > 0]
    return {"numerical": int(np.sum(s > 1e-3 * s[0])), "entropy": float(np.exp(-np.sum(p * np.log(p))))}



# --------------------------------------------------------------------------- datasets, tables, figures
#: LASA shapes of the full prediction experiments.
LASA_SHAPES = ("GShape", "Angle", "WShape")


def prediction_tasks(quick: bool, seed: int, settings: Settings = SETTINGS["thesis"]) -> list[Task]:
    """The datasets of the prediction experiments.

    Full: GunPoint (train split, 8 demonstrations of each class, J = 10, V = 5,
    leave-one-out over all 16) and the LASA shapes :data:`LASA_SHAPES` (every
    20th sample, 7 demonstrations, J = 10, V = 5, leave-one-out over all 7).
    Quick: LASA GShape (every 50th sample, J = 8, V = 3), three folds.  J and
    the width are the thesis's, scaled by ``settings`` (:data:`SETTINGS`).
    """
    from lmpromp_ppl.data import load_dataset

    J, width = settings.num_basis, settings.width
    if quick:
        demos = load_dataset("lasa:GShape?every=50")
        return [Task("LASA GShape", demos, J(8), 3, (0, 1, 2), width)]
    gunpoint = load_dataset("gunpoint:train")
    rng = np.random.default_rng([seed, 16])
    labels = np.asarray(gunpoint.labels)
    chosen = np.sort(np.concatenate([rng.choice(np.flatnonzero(labels == c), 8, replace=False)
                                     for c in sorted(set(labels))]))
    tasks = [Task("GunPoint", gunpoint.subset(chosen), J(10), 5, tuple(range(16)), width)]
    for shape in LASA_SHAPES:
        demos = load_dataset(f"lasa:{shape}?every=20")
        tasks.append(Task(f"LASA {shape}", demos, J(10), 5, tuple(range(demos.num_demos)), width))
    return tasks


def gain_counts(rows_by_task: dict[str, list[dict]], model: str, metric: str) -> tuple[int, int, int]:
    """(significant wins, significant losses, settings) of ``model`` over the ProMP: gain beyond 2 standard errors."""
    wins = losses = total = 0
    for rows in rows_by_task.values():
        for row in rows:
            entry = row["models"][model]
            gain, se = entry.get(f"{metric}_gain_mean"), entry.get(f"{metric}_gain_se")
            if gain is None or not math.isfinite(gain):
                continue
            total += 1
            wins += gain > 2 * se
            losses += gain < -2 * se
    return wins, losses, total


def verdict_from_counts(wins: int, losses: int, total: int) -> str:
    """``holds``: significant wins in at least 3/4 of the settings and no significant loss;
    ``holds partly``: more wins than losses; else ``does not hold``."""
    if total and wins >= 0.75 * total and losses == 0:
        return "holds"
    if wins > losses:
        return "holds partly"
    return "does not hold"


def sweep_table(rows_by_task: dict[str, list[dict]], key: str, models: Sequence[str]) -> str:
    """Markdown table: one line per (dataset, setting), RMSE and log density (mean ± se) per model."""
    head = "| dataset | " + key + " | " + " | ".join(f"RMSE {m}" for m in models) + " | " + \
        " | ".join(f"log dens. {m}" for m in models) + " |"
    lines = [head, "|" + "---|" * (2 + 2 * len(models))]
    for label, rows in rows_by_task.items():
        for row in rows:
            value = row["setting"][key]
            cells = [f"{row['models'][m]['rmse_mean']:.3f} ± {row['models'][m]['rmse_se']:.3f}" for m in models]
            cells += [f"{row['models'][m]['lpd_mean']:.3f} ± {row['models'][m]['lpd_se']:.3f}" for m in models]
            lines.append(f"| {label} | {'all' if value is None else value} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def sweep_figure(rows_by_task: dict[str, list[dict]], key: str, models: Sequence[str], path, xlabel: str) -> None:
    """RMSE (top) and log density (bottom) over the setting ``key``, one column per dataset (Fig. 5.5)."""
    from lmpromp_ppl.reproduce._common import matplotlib_figure, save_figure

    fig, axes = matplotlib_figure(2, len(rows_by_task), (3.2 * len(rows_by_task), 5.5))
    for col, (label, rows) in enumerate(rows_by_task.items()):
        values = [row["setting"][key] for row in rows]
        x = np.arange(len(values))
        for offset, model in enumerate(models):
            for r, metric in enumerate(("rmse", "lpd")):
                mean = [row["models"][model][f"{metric}_mean"] for row in rows]
                se = [row["models"][model][f"{metric}_se"] for row in rows]
                axes[r, col].errorbar(x + 0.08 * (offset - 1), mean, yerr=se, marker="o", capsize=3, label=model)
        for r, ylabel in enumerate(("RMSE (std. units)", "log pred. density / row")):
            axes[r, col].set_xticks(x, ["all" if v is None else str(v) for v in values])
            axes[r, col].set_xlabel(xlabel)
            axes[r, col].set_ylabel(ylabel)
        axes[0, col].set_title(label)
    axes[0, 0].legend(fontsize=8)
    save_figure(fig, path)

r"""``beta``: training and test error and the model complexity over beta (thesis Sec. 5.3, Fig. 5.6A).

The thesis's one free parameter is the data precision :math:`\beta`.  For
:math:`\beta \in \{1, 10, 50, 100, 200, 500, 1000, 5000\}` (standardised units)
the LMProMP is trained with leave-one-out folds on noisy, sparsely sampled
GunPoint demonstrations (as the thesis uses noise and 50 ms sampling); the test
error is the prediction of a held-out movement's rest from its first 30 %, the
training error the same prediction for training movements, and the complexity
the effective rank of :math:`M H^T` (:func:`~lmpromp_ppl.reproduce.prediction.effective_rank`).
The learned-beta option (``Hyperparameters.learn_beta``, a Gamma prior on beta)
is run beside the fixed values.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np
from scipy.stats import spearmanr

from lmpromp_ppl.models.hyper import Hyperparameters
from lmpromp_ppl.reproduce._common import SETTINGS, Claim, Context, ExperimentOutput, Settings, mean_se, progress_bar
from lmpromp_ppl.reproduce.prediction import Setting, Task, effective_rank, noisy_copy, prediction_tasks, run_fold

__all__ = ["BETAS", "sweep_task", "hyper_sweep", "run"]

#: The beta values of Fig. 5.6A.
BETAS = (1.0, 10.0, 50.0, 100.0, 200.0, 500.0, 1000.0, 5000.0)


def sweep_task(quick: bool, seed: int, settings: Settings = SETTINGS["thesis"]) -> tuple[Task, Setting]:
    """GunPoint (16 demonstrations, V = 10, every other demonstration held out) with noise 0.1 and
    every 4th sample; quick: the quick prediction task with noise 0.1 and every 2nd sample."""
    task = prediction_tasks(quick, seed, settings)[0]
    if quick:
        return task, Setting(noise=0.1, interval=2)
    return dataclasses.replace(task, latent_dim=10, folds=task.folds[::2]), Setting(noise=0.1, interval=4)


def hyper_sweep(
    task: Task, setting: Setting, hypers: Sequence[Hyperparameters], seed: int, train_eval: int, bar
) -> list[dict]:
    """LMProMP leave-one-out over ``task.folds`` for each hyperparameter set.

    Returns one dict per set: per-fold ``test_rmse``, ``test_lpd``, ``train_rmse``,
    ``train_lpd`` (None where not finite), ``rank`` and ``entropy_rank`` of
    :math:`MH^T`, ``active`` latent dims, ``beta`` (learned or fixed),
    ``converged`` and ``finite`` flags.
    """
    rng = np.random.default_rng([seed, 7])
    noisy = noisy_copy(task.demos, setting.noise, rng)
    out = []
    for hyper in hypers:
        record = {k: [] for k in ("test_rmse", "test_lpd", "train_rmse", "train_lpd", "rank", "entropy_rank",
                                  "active", "beta", "converged", "finite")}
        for fold in task.folds:
            test, train = run_fold(task, noisy, fold, setting, hyper, ("lmpromp",), rng, seed, train_eval)
            fit = test.fits["lmpromp"]
            record["test_rmse"].append(test.rmse["lmpromp"])
            record["test_lpd"].append(test.lpd["lmpromp"])
            record["train_rmse"].append(train.rmse["lmpromp"] if train else None)
            record["train_lpd"].append(train.lpd["lmpromp"] if train else None)
            record["converged"].append(fit.converged)
            record["finite"].append(fit.finite and test.rmse["lmpromp"] is not None and test.lpd["lmpromp"] is not None)
            if fit.finite:
                rank = effective_rank(fit.params["M"], fit.params["h"])
                inverse = 1.0 / np.asarray(fit.params["lam"])
                record["rank"].append(rank["numerical"])
                record["entropy_rank"].append(rank["entropy"])
                record["active"].append(int(np.sum(inverse > 1e-3 * inverse.max())))
                record["beta"].append(float(fit.params.get("beta", hyper.beta)))
            if bar is not None:
                bar.update()
        out.append(record)
    return out


def _summary(record: dict) -> dict:
    summary = {}
    for key in ("test_rmse", "test_lpd", "train_rmse", "train_lpd", "rank", "entropy_rank", "active", "beta"):
        values = [float(v) for v in record[key] if v is not None]
        if not values and key.startswith("train"):
            continue  # no training error requested (train_eval = 0)
        mean, se = mean_se(values)
        summary[f"{key}_mean"], summary[f"{key}_se"] = mean, se
    summary["nonfinite"] = int(sum(not f for f in record["finite"]))
    summary["not_converged"] = int(sum(not c for c in record["converged"]))
    summary["folds"] = len(record["finite"])
    return summary


def run(context: Context) -> ExperimentOutput:
    """Run the beta sweep and the learned-beta fit; figure ``beta.png``."""
    task, setting = sweep_task(context.quick, context.seed, context.settings)
    base = context.settings.hyper
    betas = (1.0, 100.0, 5000.0) if context.quick else BETAS
    train_eval = 2 if context.quick else 4
    hypers = [base.replace(beta=b, learn_beta=False) for b in betas] + [base.replace(learn_beta=True)]
    with progress_bar(len(hypers) * len(task.folds), "beta", context.progress) as bar:
        records = hyper_sweep(task, setting, hypers, context.seed, train_eval, bar)
    rows = [{"beta": b, **_summary(r)} for b, r in zip(betas, records)]
    learned = _summary(records[-1])
    _figure(rows, learned, context.out / "beta.png")
    test = np.array([r["test_rmse_mean"] for r in rows])
    train = np.array([r["train_rmse_mean"] for r in rows])
    rank = np.array([r["entropy_rank_mean"] for r in rows])
    rank_rho = float(spearmanr(betas, rank).statistic)
    train_rho = float(spearmanr(betas, train).statistic)
    best = int(np.nanargmin(test))
    claims = [
        Claim(
            claim="beta sets the model complexity: the effective rank of M h grows with beta",
            thesis="Sec. 5.3, Fig. 5.6A",
            measured=(f"entropy effective rank {rank[0]:.2f} ± {rows[0]['entropy_rank_se']:.2f} at beta={betas[0]:g} to "
                      f"{rank[-1]:.2f} ± {rows[-1]['entropy_rank_se']:.2f} at beta={betas[-1]:g}; Spearman rho {rank_rho:.2f}"),
            verdict="holds" if rank_rho > 0.8 else ("holds partly" if rank_rho > 0 else "does not hold"),
        ),
        Claim(
            claim="The training error decreases with beta",
            thesis="Sec. 5.3, Fig. 5.6A",
            measured=(f"training RMSE {train[0]:.3f} ± {rows[0]['train_rmse_se']:.3f} at beta={betas[0]:g}, "
                      f"{train[-1]:.3f} ± {rows[-1]['train_rmse_se']:.3f} at beta={betas[-1]:g}; Spearman rho {train_rho:.2f}"),
            verdict="holds" if train_rho < -0.8 else ("holds partly" if train_rho < 0 else "does not hold"),
        ),
        Claim(
            claim="The test error is lowest at a small beta (beta = 10 in the thesis) and the model overfits at large beta",
            thesis="Sec. 5.3, Fig. 5.6A",
            measured=(f"lowest test RMSE {test[best]:.3f} ± {rows[best]['test_rmse_se']:.3f} at beta={betas[best]:g}; "
                      f"{test[-1]:.3f} ± {rows[-1]['test_rmse_se']:.3f} at beta={betas[-1]:g}"),
            verdict=_overfit_verdict(rows, best),
        ),
    ]
    table = ["| beta | train RMSE | test RMSE | test log dens. | rank(M h) | entropy rank | active dims | non-finite |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows + [{"beta": "learned", **learned}]:
        table.append(
            f"| {r['beta'] if isinstance(r['beta'], str) else f'{r['beta']:g}'} | {r['train_rmse_mean']:.3f} ± {r['train_rmse_se']:.3f} | "
            f"{r['test_rmse_mean']:.3f} ± {r['test_rmse_se']:.3f} | {r['test_lpd_mean']:.3f} ± {r['test_lpd_se']:.3f} | "
            f"{r['rank_mean']:.2f} | {r['entropy_rank_mean']:.2f} | {r['active_mean']:.2f} | {r['nonfinite']} |"
        )
    section = "\n\n".join([
        f"{task.label}: {len(task.folds)} leave-one-out folds, noise s.d. {setting.noise} of each DoF's s.d., every "
        f"{setting.interval}-th sample, V = {task.latent_dim}. Test: prediction of a held-out movement's rest "
        f"from its first 30 %; training: the same for {train_eval} training movements per fold. RMSE in std. units.",
        "\n".join(table),
        f"Learned beta (Gamma({base.beta_a0:g}, {base.beta_b0:g}) prior): E[beta] = {learned['beta_mean']:.1f} ± "
        f"{learned['beta_se']:.1f} (standardised units), test RMSE {learned['test_rmse_mean']:.3f} ± "
        f"{learned['test_rmse_se']:.3f}.",
    ])
    return ExperimentOutput(
        numbers={"rows": rows, "learned_beta": learned, "spearman_rank": rank_rho, "spearman_train": train_rho},
        section=section,
        claims=claims,
        sizes={task.label: {"demonstrations": task.demos.num_demos, "folds": len(task.folds), "noise": setting.noise,
                            "interval": setting.interval, "latent_dim": task.latent_dim}},
        figures=["beta.png"],
    )


def _overfit_verdict(rows: list[dict], best: int) -> str:
    last = rows[-1]
    overfits = last["test_rmse_mean"] - rows[best]["test_rmse_mean"] > 2 * max(last["test_rmse_se"], rows[best]["test_rmse_se"])
    small = rows[best]["beta"] <= 50
    if overfits and small:
        return "holds"
    if overfits or small:
        return "holds partly"
    return "does not hold"


def _figure(rows: list[dict], learned: dict, path) -> None:
    from lmpromp_ppl.reproduce._common import matplotlib_figure, save_figure

    betas = [r["beta"] for r in rows]
    fig, axes = matplotlib_figure(1, 3, (12, 3.6))
    for key, label in (("train_rmse", "training"), ("test_rmse", "test")):
        axes[0, 0].errorbar(betas, [r[f"{key}_mean"] for r in rows], yerr=[r[f"{key}_se"] for r in rows],
                            marker="o", capsize=3, label=label)
    axes[0, 0].axhline(learned["test_rmse_mean"], color="k", ls="--", label="test, learned beta")
    axes[0, 0].set_ylabel("RMSE (std. units)")
    axes[0, 1].errorbar(betas, [r["test_lpd_mean"] for r in rows], yerr=[r["test_lpd_se"] for r in rows],
                        marker="o", capsize=3)
    axes[0, 1].set_ylabel("test log pred. density / row")
    axes[0, 2].errorbar(betas, [r["entropy_rank_mean"] for r in rows], yerr=[r["entropy_rank_se"] for r in rows],
                        marker="o", capsize=3, label="entropy rank of M h")
    axes[0, 2].plot(betas, [r["rank_mean"] for r in rows], marker="s", label="numerical rank of M h")
    axes[0, 2].plot(betas, [r["active_mean"] for r in rows], marker="^", label="active latent dims")
    axes[0, 2].legend(fontsize=8)
    for ax in axes[0]:
        ax.set_xscale("log")
        ax.set_xlabel("beta")
    axes[0, 0].legend(fontsize=8)
    save_figure(fig, path)

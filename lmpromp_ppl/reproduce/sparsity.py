"""``sparsity``: prediction from sparser observations (thesis Sec. 5.2, Fig. 5.5B).

Leave-one-out prediction of the rest of a movement from its first 30 % (see
:mod:`lmpromp_ppl.reproduce.prediction`), ProMP vs LMProMP vs mixture (K = 2),
keeping only every ``interval``-th time sample of the training demonstrations
and of the observed segment (the thesis's 50-300 ms sampling intervals).
"""

from __future__ import annotations

from lmpromp_ppl.reproduce._common import Claim, Context, ExperimentOutput, progress_bar
from lmpromp_ppl.reproduce.prediction import (
    MODEL_NAMES,
    Setting,
    gain_counts,
    loo_sweep,
    prediction_tasks,
    sweep_figure,
    sweep_table,
    verdict_from_counts,
)

__all__ = ["intervals", "run"]


def intervals(task, quick: bool) -> tuple[int, ...]:
    """Sampling intervals of a task: up to about one sample per basis function per demonstration."""
    if quick:
        return (1, 3)
    return (1, 4, 8, 16) if task.demos.lengths[0] > 100 else (1, 2, 4, 8)


def run(context: Context) -> ExperimentOutput:
    """Run the sampling-interval sweep; figure ``sparsity.png``."""
    tasks = prediction_tasks(context.quick, context.seed, context.settings)
    total = sum(len(t.folds) * len(intervals(t, context.quick)) for t in tasks)
    rows = {}
    with progress_bar(total, "sparsity", context.progress) as bar:
        for task in tasks:
            settings = [Setting(interval=k) for k in intervals(task, context.quick)]
            rows[task.label] = loo_sweep(task, settings, context.settings.hyper, MODEL_NAMES, context.seed, bar)
    sweep_figure(rows, "interval", MODEL_NAMES, context.out / "sparsity.png", "sampling interval (samples)")
    sparse = {k: [r for r in v if r["setting"]["interval"] > 1] for k, v in rows.items()}
    claims = []
    for metric, what in (("rmse", "RMSE"), ("lpd", "held-out log predictive density")):
        wins, losses, n = gain_counts(sparse, "lmpromp", metric)
        mix_wins, mix_losses, _ = gain_counts(sparse, "mixture", metric)
        claims.append(Claim(
            claim=f"The LMProMP is more robust to sparse observations than the ProMP ({what})",
            thesis="Sec. 5.2, Fig. 5.5B",
            measured=(f"LMProMP better than ProMP beyond 2 s.e. in {wins}/{n} (dataset, interval > 1) settings, "
                      f"worse in {losses}; mixture better in {mix_wins}/{n}, worse in {mix_losses}"),
            verdict=verdict_from_counts(wins, losses, n),
        ))
    section = "\n\n".join([
        "Leave-one-out prediction of the rest of each movement (phase > 0.3) from its first 30 %, keeping "
        "every k-th time sample of the training demonstrations and of the observed segment. Metrics as in "
        "the noise experiment; mean ± standard error over folds.",
        sweep_table(rows, "interval", MODEL_NAMES),
    ])
    sizes = {t.label: {"demonstrations": t.demos.num_demos, "folds": len(t.folds), "T": int(t.demos.lengths[0]),
                       "intervals": list(intervals(t, context.quick))} for t in tasks}
    return ExperimentOutput(numbers={"interval": rows}, section=section, claims=claims, sizes=sizes,
                            figures=["sparsity.png"])

r"""Prediction with unknown timing on real and synthetic demonstrations (``lmpromp timing``, reports/timing/).

For each dataset and each held-out demonstration i (leave one out, up to
``max_folds``): fit the LMProMP with the default settings (CAVI) to the other
demonstrations, observe the first third of demonstration i *in time*
(``t - t_0 <= T_i / 3``, seconds from its start), and predict the remaining
two thirds at their true times with three timings:

* ``true``: the true duration :math:`T_i` (``--duration T_i``);
* ``estimated``: ``--duration estimate`` (:mod:`lmpromp_ppl.predict.timing`),
  the prediction averaged over the duration's posterior;
* ``mean``: the training demonstrations' mean duration.

The table gives the RMSE on the remaining two thirds in data units (root mean
square over samples and DoF, averaged over folds), the ratios of the
estimated and mean-timing RMSEs to the true-timing one, the median relative
error of the estimated duration and the coverage of its central 90 % interval.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

__all__ = ["DEFAULT_DATASETS", "timing_rows", "fold_row", "render_markdown", "write_report"]

#: The committed table: synthetic demonstrations of known durations, eight LASA shapes, GunPoint.
DEFAULT_DATASETS = (
    "synthetic:latent?L=40&D=2&J=10&V=3&T=100&duration=2&spread=0.2&seed=0",
    "lasa:GShape", "lasa:Angle", "lasa:Sshape", "lasa:Worm", "lasa:CShape", "lasa:NShape", "lasa:Trapezoid",
    "lasa:Spoon",
    "gunpoint:train",
)


def fold_row(demos, index: int, *, seed: int = 0) -> dict:
    """One held-out demonstration: RMSEs of the three timings and the duration's estimate."""
    from lmpromp_ppl.api import fit
    from lmpromp_ppl.predict.from_fit import predict_from_fit

    keep = np.arange(demos.num_demos) != index
    train = demos.subset(keep)
    result = fit(train, "lmpromp", "cavi", seed=seed)
    t = demos.times[index] - demos.times[index][0]
    y = demos.positions[index]
    duration = float(t[-1])
    seen = t <= duration / 3.0
    rest = ~seen
    mean_duration = float(np.mean([tt[-1] - tt[0] for tt in train.times]))
    row = {"fold": int(index), "duration": duration, "mean_duration": mean_duration}
    started = time.perf_counter()
    for label, timing in (("true", duration), ("estimated", "estimate"), ("mean", mean_duration)):
        pred = predict_from_fit(result, t[seen], y[seen], duration=timing, time_query=t[rest], num_samples=1)
        row[f"rmse_{label}"] = float(np.sqrt(np.mean((pred.time_mean - y[rest]) ** 2)))
        if label == "estimated":
            row["estimate"] = float(pred.duration)
            row["interval"] = [float(v) for v in pred.duration_interval]
            row["seconds_estimated"] = time.perf_counter() - started
        started = time.perf_counter()
    row["relative_error"] = row["estimate"] / duration - 1.0
    row["covered"] = bool(row["interval"][0] <= duration <= row["interval"][1])
    return row


def _summary(name: str, folds: list[dict]) -> dict:
    rmse = {k: float(np.mean([f[f"rmse_{k}"] for f in folds])) for k in ("true", "estimated", "mean")}
    durations = np.array([f["duration"] for f in folds])
    return {
        "dataset": name,
        "folds": len(folds),
        "duration_spread": float(np.std(durations) / np.mean(durations)),
        "rmse_true": rmse["true"],
        "rmse_estimated": rmse["estimated"],
        "rmse_mean": rmse["mean"],
        "ratio_estimated": rmse["estimated"] / rmse["true"],
        "ratio_mean": rmse["mean"] / rmse["true"],
        "median_abs_relative_error": float(np.median(np.abs([f["relative_error"] for f in folds]))),
        "coverage90": float(np.mean([f["covered"] for f in folds])),
        "seconds_estimated": float(np.mean([f["seconds_estimated"] for f in folds])),
        "per_fold": folds,
    }


def timing_rows(datasets: Sequence[str], *, max_folds: int = 7, seed: int = 0,
                echo: Callable[[str], None] | None = None) -> list[dict]:
    """The table's rows (module docstring); ``echo`` reports progress per dataset."""
    from lmpromp_ppl.data import load_dataset

    rows = []
    for name in datasets:
        demos = load_dataset(name, seed=seed)
        count = min(demos.num_demos, max_folds)
        folds = [fold_row(demos, i, seed=seed) for i in np.linspace(0, demos.num_demos - 1, count).astype(int)]
        rows.append(_summary(name, folds))
        if echo is not None:
            r = rows[-1]
            echo(f"{name}: RMSE true {r['rmse_true']:.3g}, estimated {r['rmse_estimated']:.3g}, "
                 f"mean {r['rmse_mean']:.3g}; duration error {100 * r['median_abs_relative_error']:.1f} %")
    return rows


def render_markdown(rows: list[dict]) -> str:
    """The table of reports/timing/timing.md."""
    lines = [
        "# Prediction with unknown timing",
        "",
        "Leave-one-out: the LMProMP (CAVI, default settings) fitted to the other demonstrations, the first third "
        "of the held-out one observed in time, the remaining two thirds predicted at their true times. RMSE in "
        "data units; `x true` is the ratio to the RMSE with the true duration. Duration error: median of "
        "|estimate / truth - 1|; coverage: of the central 90 % interval. Regenerate with `make timing-report`.",
        "",
        "| dataset | folds | spread of durations | RMSE true | RMSE estimated | x true | RMSE mean timing | x true "
        "| duration error | 90 % coverage | s per estimate |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['dataset']} | {r['folds']} | {100 * r['duration_spread']:.1f} % | {r['rmse_true']:.3g} | "
            f"{r['rmse_estimated']:.3g} | {r['ratio_estimated']:.2f} | {r['rmse_mean']:.3g} | {r['ratio_mean']:.2f} | "
            f"{100 * r['median_abs_relative_error']:.1f} % | {r['coverage90']:.2f} | {r['seconds_estimated']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def write_report(out: Path, rows: list[dict], settings: dict) -> None:
    """``timing.md`` and ``timing.json`` into ``out``."""
    out = Path(out)
    (out / "timing.md").write_text(render_markdown(rows))
    (out / "timing.json").write_text(json.dumps({"settings": settings, "rows": rows}, indent=2) + "\n")

r"""Prediction with unknown timing on real and synthetic demonstrations (``lmpromp timing``, reports/timing/).

For each dataset and each held-out demonstration i (leave one out, up to
``max_folds`` evenly spread ones of a recorded dataset, every one of a
synthetic set, whose duration errors vary from 0.2 % to 61 % between
demonstrations so that a median over a few is noise): fit the LMProMP with the default settings (CAVI) to the other
demonstrations, observe the first third of demonstration i *in time*
(``t - t_0 <= T_i / 3``, seconds from its start), and predict the remaining
two thirds at their true times with three timings:

* ``true``: the true duration :math:`T_i` (``--duration T_i``);
* ``estimated``: ``--duration estimate`` (:mod:`lmpromp_ppl.predict.timing`),
  the prediction averaged over the duration's posterior;
* ``mean``: the training demonstrations' mean duration;

and, to measure what aligning the training demonstrations' phases changes
(:func:`lmpromp_ppl.data.align.align_phases`), the same fit with
``align="dtw"`` predicting with the true and with the estimated timing.  The
population column is the mean s.d. of the unconditioned movement distribution
(data units), of the linear-phase and the aligned fit.

A synthetic set is fitted twice: with the default basis and with the basis
that generated it (its ``num_basis`` and the generator's width), so that the
table separates what the timing estimate loses to the basis from what it
loses to the fit.  On synthetic data the generating parameters are known, so each fold also
gives the duration's error under them (all samples, the training durations'
prior): the information the first third holds, which no fit can beat.  The
first synthetic set holds the duration to 4.7 % (median) under its generating
parameters, so a 5 % goal would ask any fit to be as good as the truth; the
second has the same draws with less noise (observation s.d. 0.01 instead of
0.05, weight-noise s.d. 0.032 instead of 0.1), chosen before any fit by that
error alone (1.5 %), so that it measures what the fit loses where the first
third does determine the duration.

The table gives the RMSE on the remaining two thirds in data units (root mean
square over samples and DoF, averaged over folds), the ratios of the
estimated and mean-timing RMSEs to the true-timing one, the median relative
error of the estimated duration and the coverage of its central 90 % interval.
"""

from __future__ import annotations

import json
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

__all__ = ["DEFAULT_DATASETS", "timing_rows", "fold_row", "render_markdown", "write_report"]

#: The committed table: two synthetic sets of known durations, eight LASA shapes, GunPoint.
DEFAULT_DATASETS = (
    "synthetic:latent?L=40&D=2&J=10&V=3&T=100&duration=2&spread=0.2&seed=0",
    # the same draws with less noise, chosen by the generating parameters' duration error alone (1.5 %)
    "synthetic:latent?L=40&D=2&J=10&V=3&T=100&duration=2&spread=0.2&alpha=1000&beta=10000&seed=0",
    "lasa:GShape", "lasa:Angle", "lasa:Sshape", "lasa:Worm", "lasa:CShape", "lasa:NShape", "lasa:Trapezoid",
    "lasa:Spoon",
    "gunpoint:train",
)


def fold_row(demos, index: int, *, seed: int = 0, fit_options: dict | None = None) -> dict:
    """One held-out demonstration: RMSEs of the three timings and the duration's estimate
    (``fit_options``: e.g. ``num_basis`` and ``width`` of every fit; default the library's).

    CAVI fits that stop at their iteration limit (the fold's fits and the calibration's refits)
    are counted in ``fits_at_iteration_limit`` instead of warning once each; other warnings pass."""
    from lmpromp_ppl.errors import ConvergenceWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ConvergenceWarning)
        row = _fold_row(demos, index, seed=seed, fit_options=fit_options)
    for w in caught:
        if not issubclass(w.category, ConvergenceWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    row["fits_at_iteration_limit"] = sum(issubclass(w.category, ConvergenceWarning) for w in caught)
    return row


def _fold_row(demos, index: int, *, seed: int, fit_options: dict | None) -> dict:
    from lmpromp_ppl.api import fit
    from lmpromp_ppl.predict.from_fit import population_prediction

    keep = np.arange(demos.num_demos) != index
    train = demos.subset(keep)
    options = dict(fit_options or {})
    result = fit(train, "lmpromp", "cavi", seed=seed, **options)
    aligned = fit(train, "lmpromp", "cavi", seed=seed, align="dtw", **options)
    t = demos.times[index] - demos.times[index][0]
    y = demos.positions[index]
    duration = float(t[-1])
    seen = t <= duration / 3.0
    mean_duration = float(np.mean([tt[-1] - tt[0] for tt in train.times]))
    row = {"fold": int(index), "duration": duration, "mean_duration": mean_duration}
    variants = (("true", result, duration, (1.0, None)), ("estimated", result, "estimate", (1.0, None)),
                ("mean", result, mean_duration, (1.0, None)), ("aligned_true", aligned, duration, (1.0, None)),
                ("aligned_estimated", aligned, "estimate", (1.0, None)))
    row |= _prediction_columns(variants, t, y, seen)
    row |= calibrated_columns(result, t, y, seen)
    for label, fitted in (("linear", result), ("aligned", aligned)):
        row[f"population_sd_{label}"] = float(np.mean(population_prediction(fitted, num_samples=1).sd))
    if {"b", "M", "alpha", "beta", "num_basis"} <= set(demos.metadata):
        row["oracle_relative_error"] = _oracle_estimate(demos.metadata, t[seen], y[seen],
                                                        [tt[-1] - tt[0] for tt in train.times]) / duration - 1.0
    return row


def calibrated_columns(result, t: np.ndarray, y: np.ndarray, seen: np.ndarray) -> dict:
    """A fold's columns of the calibrated timing (:func:`lmpromp_ppl.api.calibrate_timing`): the candidate
    powers averaged (``calibrated_*``, what ``lmpromp predict`` does) and the best-scoring one (``best_*``)."""
    from lmpromp_ppl.api import calibrate_timing

    started = time.perf_counter()
    calibration = calibrate_timing(result, float(t[seen][-1]))
    row = {"calibration_power": calibration.mean_power,
           "calibration_best_power": calibration.power, "seconds_calibration": time.perf_counter() - started}
    variants = (("calibrated_estimated", result, "estimate", (calibration.powers, calibration.weights)),
                ("best_estimated", result, "estimate", (calibration.power, None)))
    return row | _prediction_columns(variants, t, y, seen)


def _prediction_columns(variants, t: np.ndarray, y: np.ndarray, seen: np.ndarray) -> dict:
    """RMSE on the unseen rest (and, for an estimated timing, the duration's estimate) of each
    ``(label, fit, duration, (power, power_weights))``."""
    from lmpromp_ppl.predict.from_fit import predict_from_fit

    row, rest, duration = {}, ~seen, float(t[-1])
    started = time.perf_counter()
    for label, fitted, timing, (power, power_weights) in variants:
        pred = predict_from_fit(fitted, t[seen], y[seen], duration=timing, time_query=t[rest], num_samples=1,
                                timing_power=power, timing_weights=power_weights)
        row[f"rmse_{label}"] = float(np.sqrt(np.mean((pred.time_mean - y[rest]) ** 2)))
        if label.endswith("estimated"):
            prefix = label[: -len("estimated")]
            row[f"{prefix}estimate"] = float(pred.duration)
            row[f"{prefix}interval"] = [float(v) for v in pred.duration_interval]
            row[f"{prefix}relative_error"] = row[f"{prefix}estimate"] / duration - 1.0
            row[f"{prefix}covered"] = bool(row[f"{prefix}interval"][0] <= duration <= row[f"{prefix}interval"][1])
            if not prefix:
                row["seconds_estimated"] = time.perf_counter() - started
        started = time.perf_counter()
    return row


def _oracle_estimate(metadata: dict, t: np.ndarray, y: np.ndarray, durations) -> float:
    """The duration's posterior median under the generating parameters of a synthetic set."""
    import jax.numpy as jnp

    from lmpromp_ppl.data.core import Scaling
    from lmpromp_ppl.data.synthetic import GENERATOR_WIDTH
    from lmpromp_ppl.predict.timing import duration_prior, timed_rows, timing_posterior

    draws = {"b": jnp.asarray(metadata["b"])[None], "M": jnp.asarray(metadata["M"])[None],
             "alpha": jnp.asarray(metadata["alpha"]).reshape(1)}
    rows = timed_rows(t, y, noise_sd=float(metadata["beta"]) ** -0.5, scaling=Scaling.identity(y.shape[1]))
    post = timing_posterior("lmpromp", draws, rows, duration_prior(np.asarray(durations)), 1.0,
                            num_dofs=y.shape[1], num_basis=int(metadata["num_basis"]), width=GENERATOR_WIDTH)
    return float(post.estimate)


def _summary(name: str, folds: list[dict]) -> dict:
    def mean(key):
        return float(np.mean([f[key] for f in folds]))

    durations = np.array([f["duration"] for f in folds])
    row = {"dataset": name, "folds": len(folds), "duration_spread": float(np.std(durations) / np.mean(durations))}
    for label in ("true", "estimated", "mean", "aligned_true", "aligned_estimated", "calibrated_estimated",
                  "best_estimated"):
        row[f"rmse_{label}"] = mean(f"rmse_{label}")
        if label != "true":
            row[f"ratio_{label}"] = row[f"rmse_{label}"] / mean("rmse_true")
    for prefix in ("", "aligned_", "calibrated_", "best_"):
        row[f"{prefix}median_abs_relative_error"] = float(np.median(np.abs([f[f"{prefix}relative_error"] for f in folds])))
        row[f"{prefix}coverage90"] = mean(f"{prefix}covered")
    for label in ("linear", "aligned"):
        row[f"population_sd_{label}"] = mean(f"population_sd_{label}")
    oracle = [f.get("oracle_relative_error") for f in folds]
    row["oracle_median_abs_relative_error"] = None if None in oracle else float(np.median(np.abs(oracle)))
    row["fits_at_iteration_limit"] = int(sum(f.get("fits_at_iteration_limit", 0) for f in folds))
    for key in ("calibration_power", "calibration_best_power"):  # the weighted mean power, the best one
        powers = [f[key] for f in folds]
        row[f"{key}_median"] = float(np.median(powers))
        row[f"{key}_range"] = [float(np.min(powers)), float(np.max(powers))]
    return row | {
        "seconds_estimated": float(np.mean([f["seconds_estimated"] for f in folds])),
        "seconds_calibration": float(np.mean([f["seconds_calibration"] for f in folds])),
        "per_fold": folds,
    }


def timing_rows(datasets: Sequence[str], *, max_folds: int = 7, seed: int = 0,
                echo: Callable[[str], None] | None = None) -> list[dict]:
    """The table's rows (module docstring); ``echo`` reports progress per dataset."""
    from lmpromp_ppl.data import load_dataset

    rows = []
    from lmpromp_ppl.data.synthetic import GENERATOR_WIDTH

    for name in datasets:
        demos = load_dataset(name, seed=seed)
        synthetic = name.startswith("synthetic:")
        count = demos.num_demos if synthetic else min(demos.num_demos, max_folds)
        variants = [(name, {})]
        if synthetic and "num_basis" in demos.metadata:  # also fit with the basis that generated the data
            generator = {"num_basis": int(demos.metadata["num_basis"]), "width": GENERATOR_WIDTH}
            variants.append((f"{name} (generator's basis, J = {generator['num_basis']}, width {GENERATOR_WIDTH:g})",
                             generator))
        for label, options in variants:
            folds = [fold_row(demos, i, seed=seed, fit_options=options)
                     for i in np.linspace(0, demos.num_demos - 1, count).astype(int)]
            rows.append(_summary(label, folds))
            if echo is not None:
                r = rows[-1]
                echo(f"{label}: RMSE true {r['rmse_true']:.3g}, estimated {r['rmse_estimated']:.3g}, "
                     f"mean {r['rmse_mean']:.3g}; duration error {100 * r['median_abs_relative_error']:.1f} %"
                     + (f"; {r['fits_at_iteration_limit']} CAVI fits stopped at their iteration limit"
                        if r["fits_at_iteration_limit"] else ""))
    return rows


def render_markdown(rows: list[dict]) -> str:
    """The table of reports/timing/timing.md."""
    lines = [
        "# Prediction with unknown timing",
        "",
        "Leave-one-out: the LMProMP (CAVI, default settings; a synthetic set also with the basis that generated it) "
        "fitted to the other demonstrations, the first third "
        "of the held-out one observed in time, the remaining two thirds predicted at their true times. RMSE in "
        "data units; `x true` is the ratio to the RMSE with the true duration. Duration error: median of "
        "|estimate / truth - 1|; coverage: of the central 90 % interval; the last column (synthetic data) is the "
        "duration error under the generating parameters, the information the first third holds. The second "
        "synthetic set has the first one's draws with less noise (observation s.d. 0.01 instead of 0.05, "
        "weight-noise s.d. 0.032 instead of 0.1), chosen by that last column alone (1.5 % against 4.7 %), so that "
        "the first third determines the duration. A recorded "
        "dataset holds out up to seven demonstrations, a synthetic one every demonstration. Regenerate with "
        "`make timing-report`.",
        "",
        "| dataset | folds | spread of durations | RMSE true | RMSE estimated | x true | RMSE mean timing | x true "
        "| duration error | 90 % coverage | s per estimate | duration error, generating parameters |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['dataset']} | {r['folds']} | {100 * r['duration_spread']:.1f} % | {r['rmse_true']:.3g} | "
            f"{r['rmse_estimated']:.3g} | {r['ratio_estimated']:.2f} | {r['rmse_mean']:.3g} | {r['ratio_mean']:.2f} | "
            f"{100 * r['median_abs_relative_error']:.1f} % | {r['coverage90']:.2f} | {r['seconds_estimated']:.1f} | "
            f"{'—' if r.get('oracle_median_abs_relative_error') is None else f'{100 * r['oracle_median_abs_relative_error']:.1f} %'} |"
        )
    lines += [
        "",
        "## Aligned training phases",
        "",
        "The same folds with the training demonstrations' phases aligned by dynamic time warping before fitting "
        "(`lmpromp fit --align dtw`); `x true` is the ratio to the linear-phase fit's true-timing RMSE above. "
        "Population s.d.: the mean s.d. of the unconditioned movement distribution, data units.",
        "",
        "| dataset | RMSE true, aligned | x true | RMSE estimated, aligned | x true | duration error | 90 % coverage "
        "| population s.d. linear | population s.d. aligned |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['dataset']} | {r['rmse_aligned_true']:.3g} | {r['ratio_aligned_true']:.2f} | "
            f"{r['rmse_aligned_estimated']:.3g} | {r['ratio_aligned_estimated']:.2f} | "
            f"{100 * r['aligned_median_abs_relative_error']:.1f} % | {r['aligned_coverage90']:.2f} | "
            f"{r['population_sd_linear']:.3g} | {r['population_sd_aligned']:.3g} |"
        )
    lines += [
        "",
        "## Calibrated timing likelihood",
        "",
        "The same folds and linear-phase fits, the timing's likelihood tempered as "
        "`lmpromp_ppl.calibrate_timing` weighs it (the default of `lmpromp predict --duration estimate`): refits "
        "without each of up to eight folds of the training demonstrations, each held-out training demonstration "
        "observed for as long as the test observation; each candidate power in [0, 1] is weighed by the exponential "
        "of the summed log density it gives their true durations (pseudo-BMA), and the prediction is averaged "
        "over the mixture of the tempered posteriors. The power column is the weighted mean power of each fold "
        "(median and range over folds). `x true` and `x mean` are ratios to the true-timing and mean-timing RMSEs "
        "of the first table. The last columns use the best-scoring power alone instead of the average.",
        "",
        "| dataset | mean power: median (range) | RMSE estimated, calibrated | x true | x mean | duration error "
        "| 90 % coverage | s per calibration | best power: RMSE | x true | duration error | 90 % coverage |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lo, hi = r["calibration_power_range"]
        lines.append(
            f"| {r['dataset']} | {r['calibration_power_median']:.3g} ({lo:.3g}-{hi:.3g}) | "
            f"{r['rmse_calibrated_estimated']:.3g} | {r['ratio_calibrated_estimated']:.2f} | "
            f"{r['rmse_calibrated_estimated'] / r['rmse_mean']:.2f} | "
            f"{100 * r['calibrated_median_abs_relative_error']:.1f} % | {r['calibrated_coverage90']:.2f} "
            f"| {r['seconds_calibration']:.1f} | {r['rmse_best_estimated']:.3g} | "
            f"{r['ratio_best_estimated']:.2f} | {100 * r['best_median_abs_relative_error']:.1f} % | "
            f"{r['best_coverage90']:.2f} |"
        )
    return "\n".join(lines) + "\n"


def write_report(out: Path, rows: list[dict], settings: dict) -> None:
    """``timing.md`` and ``timing.json`` into ``out``."""
    out = Path(out)
    (out / "timing.md").write_text(render_markdown(rows))
    (out / "timing.json").write_text(json.dumps({"settings": settings, "rows": rows}, indent=2) + "\n")

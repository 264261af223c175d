"""Does a movement's shape tell its duration?  Leave-one-out prediction of LASA durations from the latent shape.

Issue 20's picture is that the control variables h and the timing explain a partial observation
together.  If a demonstration's duration depended on its shape, a regression of log T on h would
predict a new movement's duration better than the training durations' mean, and the timing
likelihood could borrow that.  This measures the best case: the LMProMP (CAVI, default settings)
fitted to *all* demonstrations of a shape, each demonstration's posterior mean of h taken from
its whole movement (more than a first third can tell, and the held-out one is in the fit, both in
the regression's favour), then leave-one-out over the demonstrations: log T_i predicted from the
others by the training mean, by Bayesian ridge regression on E[h_i] (scikit-learn's
``BayesianRidge``, its precisions chosen by the evidence), by the same regression on the
start position, and by the same regression on the early speed, a feature of the first third alone
that needs no model: the log of the time each demonstration takes to cover the path length that
every demonstration covers within its first third.  The table gives the median over the
demonstrations of |T_pred / T_i - 1|.
Run from the repository root (about 15 s on 2 cores)::

    python benchmarks/duration_predictability.py --out benchmarks/duration_predictability.json
"""

from __future__ import annotations

import argparse
import json
import warnings

import numpy as np
from sklearn.linear_model import BayesianRidge

from lmpromp_ppl.api import fit
from lmpromp_ppl.data import load_dataset
from lmpromp_ppl.errors import ConvergenceWarning

DATASETS = tuple(f"lasa:{s}" for s in ("GShape", "Angle", "Sshape", "Worm", "CShape", "NShape", "Trapezoid", "Spoon"))
PREDICTORS = ("training mean", "latent shape E[h]", "start position", "early speed")


def loo_errors(log_duration: np.ndarray, features: np.ndarray | None) -> np.ndarray:
    """|T_pred / T_i - 1| for each demonstration, log T_i predicted from the others."""
    errors = []
    for i in range(log_duration.size):
        keep = np.arange(log_duration.size) != i
        if features is None:
            predicted = log_duration[keep].mean()
        else:
            model = BayesianRidge().fit(features[keep], log_duration[keep])
            predicted = float(model.predict(features[i : i + 1])[0])
        errors.append(abs(np.exp(predicted - log_duration[i]) - 1.0))
    return np.asarray(errors)


def early_speed(demos) -> np.ndarray:
    """(L, 1) log of the time each demonstration takes to cover the path length that every one
    of them covers within its first third (seconds)."""
    paths = []
    for t, y in zip(demos.times, demos.positions):
        t = t - t[0]
        length = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(y, axis=0), axis=1))]
        paths.append((t, length, length[t <= t[-1] / 3.0][-1]))
    common = min(first_third for _, _, first_third in paths)
    return np.log([np.interp(common, length, t) for t, length, _ in paths])[:, None]


def dataset_row(name: str, seed: int = 0) -> dict:
    demos = load_dataset(name)
    log_duration = np.log([t[-1] - t[0] for t in demos.times])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        result = fit(demos, "lmpromp", "cavi", seed=seed)
    h = np.asarray(result.posterior_draws(200)["h"])
    h = h.reshape((-1,) + h.shape[-2:]).mean(axis=0)  # (L, V)
    start = np.array([y[0] for y in demos.positions])
    features = (None, h, start, early_speed(demos))
    errors = {label: loo_errors(log_duration, x) for label, x in zip(PREDICTORS, features)}
    return {"dataset": name, "demonstrations": int(log_duration.size),
            "duration_spread": float(np.std(np.exp(log_duration)) / np.mean(np.exp(log_duration))),
            "median_abs_relative_error": {k: float(np.median(v)) for k, v in errors.items()},
            "per_demonstration": {k: [float(e) for e in v] for k, v in errors.items()}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/duration_predictability.json")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rows = [dataset_row(name, args.seed) for name in DATASETS]
    print(f"{'dataset':<16} {'spread':>7} " + " ".join(f"{p:>18}" for p in PREDICTORS))
    for row in rows:
        errs = row["median_abs_relative_error"]
        print(f"{row['dataset']:<16} {row['duration_spread']:7.1%} " + " ".join(f"{errs[p]:18.1%}" for p in PREDICTORS))
    with open(args.out, "w") as f:
        json.dump({"seed": args.seed, "predictors": list(PREDICTORS), "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()

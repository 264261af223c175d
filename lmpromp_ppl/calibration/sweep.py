r"""Hyperparameter sweeps: a grid of CAVI fits scored on held-out demonstrations.

A sweep fits the single-type LMProMP by CAVI (thesis Sec. 4.1.1) at every
point of a grid over hyperparameters (any field of
:class:`~lmpromp_ppl.models.hyper.Hyperparameters`, e.g. ``beta``, ``c0``,
``latent_dim``) and the number of basis functions ``num_basis`` (J), on the
training part of a dataset, and scores it on the held-out part.  Each grid
point is one task of :func:`lmpromp_ppl.calibration.runner.run_tasks`.

The split is a seeded random permutation of the demonstrations; each DoF is
standardised on the training demonstrations only, and the test
demonstrations use that scaling.  Both held-out metrics score *the same*
prediction, the one a user of ``lmpromp predict`` makes: each held-out
demonstration's first third (:data:`OBSERVED_FRACTION` of its time steps) is
observed and the rest is predicted, with the plug-in posterior means
:math:`\bar b, \bar M, \bar\alpha` of q and the fit's noise precision
(:math:`E_q[\beta]` when ``beta`` is learned, the fixed value otherwise).  The
weights' marginal :math:`\mathcal N(\bar b,\ \bar\alpha^{-1}I + \gamma^{-1}\bar M\bar M^T)`
(w and h integrated out) is conditioned exactly on the observed rows; then

* ``lpd``: log density of the remaining rows under that conditional
  predictive *including observation noise*, :math:`\mathcal N(\Psi_r\mu_{w|o},\
  \beta^{-1}I + \Psi_r\Sigma_{w|o}\Psi_r^T)`, per predicted value (higher is better);
* ``rmse``: root mean squared error of its mean :math:`\Psi_r\mu_{w|o}` on
  the same rows (standardised units, lower is better).

An earlier version scored the *unconditioned* density against the
*population mean's* RMSE with the preset's ``beta`` even when it was learned:
the density rewarded a covariance that explains a held-out demonstration's
offset while the RMSE only saw the mean, so the two ranked a ``beta`` grid in
opposite orders.  A grid over ``beta`` fixes ``beta`` (``learn_beta`` off) at
each value.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from lmpromp_ppl.basis import DEFAULT_NUM_BASIS
from lmpromp_ppl.errors import LmprompError

__all__ = ["METRICS", "OBSERVED_FRACTION", "parse_grid", "split_demos", "heldout_scores", "sweep_task", "sweep_tasks", "sweep_table"]

METRICS = {"lpd": "max", "rmse": "min"}
_GRID_INTS = {"latent_dim", "num_basis"}


def parse_grid(items: Sequence[str]) -> dict[str, list]:
    """Parse ``["beta=50,100", "latent_dim=1,2"]`` into ``{"beta": [50.0, 100.0], "latent_dim": [1, 2]}``.

    Names are hyperparameter fields (numbers) or ``num_basis``; ``latent_dim``
    and ``num_basis`` are integers.
    """
    from lmpromp_ppl.models.hyper import Hyperparameters

    allowed = {f for f, v in Hyperparameters().to_dict().items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    allowed = (allowed - {"num_components"}) | {"num_basis"}
    grid: dict[str, list] = {}
    for item in items:
        name, sep, values = item.partition("=")
        name = name.strip()
        if not sep or not values.strip():
            raise LmprompError(f"grid entry {item!r} must look like NAME=V1,V2")
        if name not in allowed:
            raise LmprompError(f"unknown grid parameter {name!r}; choose from {sorted(allowed)}")
        if name in grid:
            raise LmprompError(f"grid parameter {name!r} given twice")
        parsed = []
        for text in values.split(","):
            try:
                value = float(text)
            except ValueError:
                raise LmprompError(f"grid value {text!r} of {name} is not a number") from None
            if name in _GRID_INTS:
                if value != int(value):
                    raise LmprompError(f"grid values of {name} must be integers, got {text!r}")
                value = int(value)
            parsed.append(value)
        grid[name] = parsed
    if not grid:
        raise LmprompError("the grid is empty; give at least one --grid NAME=V1,V2")
    return grid


def split_demos(num_demos: int, test_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Seeded random split of demonstration indices into (train, test), both sorted and non-empty."""
    if not 0.0 < test_fraction < 1.0:
        raise LmprompError(f"test_fraction must lie in (0, 1), got {test_fraction!r}")
    num_test = int(round(test_fraction * num_demos))
    if num_test < 1 or num_test > num_demos - 2:
        raise LmprompError(
            f"cannot hold out {test_fraction:g} of {num_demos} demonstrations (need >= 1 test and >= 2 train)"
        )
    order = np.random.default_rng(seed).permutation(num_demos)
    return np.sort(order[num_test:]), np.sort(order[:num_test])


#: Fraction of each held-out demonstration's time steps that is observed before the rest is predicted.
OBSERVED_FRACTION = 1.0 / 3.0


def heldout_scores(point: Mapping[str, Any], data, hyper, num_dofs: int) -> dict[str, float]:
    """``lpd`` (per predicted value) and ``rmse`` of the rest of each held-out demonstration given its first third.

    ``data`` holds the model inputs (:class:`~lmpromp_ppl.data.core.PhaseData` or
    :class:`~lmpromp_ppl.data.core.ModelData`) of the held-out demonstrations (rows time-major, ``num_dofs`` per time step); module
    docstring for the prediction both metrics score.  The conditioning and the
    scores are :func:`lmpromp_ppl.predict.condition_gaussian` and
    :func:`lmpromp_ppl.predict.score_heldout`.
    """
    from lmpromp_ppl.predict import GaussianMixture, Observation, condition_gaussian, score_heldout

    b = np.asarray(point["b"])
    M = np.asarray(point["M"])
    weight_cov = np.eye(b.shape[0]) / float(point["alpha"]) + M @ M.T / hyper.gamma
    noise_var = 1.0 / (float(point["beta"]) if "beta" in point else float(hyper.beta))

    def rows(psi, y, keep):
        n = int(keep.sum())
        index = np.flatnonzero(keep)
        return Observation(psi[keep], y[keep], np.full(n, noise_var), np.zeros(n), index % num_dofs,
                           np.zeros(n, dtype=int))

    total_lpd, total_sq, total_n = 0.0, 0.0, 0
    for psi, y, mask in zip(*(np.asarray(a) for a in data.dense())):
        keep = mask > 0
        steps = np.arange(psi.shape[0]) // num_dofs
        seen = keep & (steps < max(1, math.ceil(OBSERVED_FRACTION * (steps[keep].max() + 1))))
        rest = keep & ~seen
        if not rest.any():
            continue
        mean_w, cov_w, _ = condition_gaussian(b, weight_cov, rows(psi, y, seen))
        score = score_heldout(GaussianMixture(np.zeros(1), mean_w[None], cov_w[None]), rows(psi, y, rest))
        n = int(rest.sum())
        total_lpd += float(score.log_density)
        total_sq += float(score.rmse) ** 2 * n
        total_n += n
    if total_n == 0:
        raise LmprompError("no held-out values to predict: every held-out demonstration is too short")
    return {"lpd": total_lpd / total_n, "rmse": math.sqrt(total_sq / total_n)}


def sweep_task(spec: Mapping[str, Any]) -> dict[str, Any]:
    """Fit one grid point and score it: the unit of work of the sweep.

    Parameters
    ----------
    spec : ``{"dataset": str, "params": {name: value}, "preset": str,
        "num_basis": int, "test_fraction": float, "seed": int, "options": {...}}``
        (``params`` may override ``num_basis``; ``options`` go to
        :func:`~lmpromp_ppl.inference.cavi.fit`)

    Returns
    -------
    ``{"params", "heldout": {"lpd", "rmse"}, "elbo", "converged", "iterations", "seconds"}``
    """
    import jax

    from lmpromp_ppl.data import load_dataset, prepare_dataset
    from lmpromp_ppl.inference import cavi
    from lmpromp_ppl.models.hyper import preset

    params = dict(spec["params"])
    num_basis = int(params.pop("num_basis", spec.get("num_basis", DEFAULT_NUM_BASIS)))
    if "beta" in params:  # a grid over beta compares fixed noise levels
        params["learn_beta"] = False
    hyper = preset(spec.get("preset", "default"), **params)
    demos = load_dataset(spec["dataset"])
    train_idx, test_idx = split_demos(demos.num_demos, float(spec.get("test_fraction", 0.25)), int(spec.get("seed", 0)))
    train = prepare_dataset(demos.subset(train_idx), num_basis)
    test = prepare_dataset(demos.subset(test_idx), num_basis, scaling=train.scaling)
    fit = cavi.fit(train.model_data, hyper, jax.random.key(int(spec.get("seed", 0))),
                   **dict(spec.get("options") or {}))
    scores = heldout_scores(cavi.point_estimate(fit.state), test.model_data, hyper, demos.num_dofs)
    return {"params": dict(spec["params"]), "heldout": scores, "elbo": fit.elbo, "converged": fit.converged,
            "iterations": fit.iterations, "seconds": fit.seconds, "num_train": int(train_idx.size),
            "num_test": int(test_idx.size)}


def sweep_tasks(
    dataset: str,
    grid: Mapping[str, Sequence],
    *,
    preset_name: str = "default",
    num_basis: int = DEFAULT_NUM_BASIS,
    test_fraction: float = 0.25,
    seed: int = 0,
    options: Mapping[str, Any] | None = None,
) -> dict[str, dict[str, Any]]:
    """Task specifications (task id -> spec) for every point of the grid's Cartesian product."""
    from lmpromp_ppl.models.hyper import preset

    preset(preset_name)  # validates the name
    names = list(grid)
    tasks = {}
    for values in itertools.product(*(grid[n] for n in names)):
        params = dict(zip(names, values))
        task_id = "sweep-" + "-".join(f"{n}={v:g}" for n, v in params.items())
        tasks[task_id] = {"kind": "sweep", "dataset": dataset, "params": params, "preset": preset_name,
                          "num_basis": int(num_basis), "test_fraction": float(test_fraction), "seed": int(seed),
                          "options": dict(options or {})}
    return tasks


def sweep_table(records: Mapping[str, Mapping[str, Any]], metric: str = "lpd") -> list[dict[str, Any]]:
    """Rows of the finished grid points, best ``metric`` first (failed points are left out)."""
    if metric not in METRICS:
        raise LmprompError(f"unknown metric {metric!r}; choose from {sorted(METRICS)}")
    rows = [{"task_id": task_id, **r["result"]["params"], **r["result"]["heldout"],
             "elbo": r["result"]["elbo"], "converged": r["result"]["converged"]}
            for task_id, r in records.items() if r.get("status") == "ok"]
    sign = -1.0 if METRICS[metric] == "max" else 1.0
    return sorted(rows, key=lambda row: sign * row[metric])

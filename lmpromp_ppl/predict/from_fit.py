r"""Prediction from a saved or fresh fit (:class:`~lmpromp_ppl.results.FitResult`).

:func:`predict_from_fit` ties observations in data units to the fit's basis
and scaling, conditions the plug-in or Bayesian predictive, and returns the
trajectory distribution and samples in data units.  ``lmpromp predict`` calls it.

Defaults: the exact conditional :math:`p(\mathbf w | \mathbf o)` (the thesis's
eqs. 4.6-4.7 only with ``exact=False``, docs/derivation.md), averaged over
posterior draws (``bayesian=True``; the plug-in posterior mean of ``M`` is
meaningless for a sampler, whose draws of ``M`` differ by rotations), with the
observation noise of the fit (its learned ``beta`` when ``beta`` was inferred).
Two bands are returned: ``sd`` of the movement :math:`\Psi\mathbf w` and
``sd_obs`` of a new observation of it (``sd`` with the noise variance added).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from lmpromp_ppl._keys import PREDICTION, seed_key
from lmpromp_ppl.errors import DataError
from lmpromp_ppl.predict.conditioning import condition, condition_draws
from lmpromp_ppl.predict.observations import empty_observation, observe
from lmpromp_ppl.predict.trajectories import sample_trajectories, trajectory_distribution

__all__ = ["Prediction", "predict_from_fit", "population_prediction", "noise_sd_of"]


class Prediction(NamedTuple):
    """A predicted trajectory distribution in data units."""

    phase: np.ndarray  # (P,)
    mean: np.ndarray  # (P, D)
    sd: np.ndarray  # (P, D) movement (noise-free trajectory)
    sd_obs: np.ndarray  # (P, D) a new observation: movement plus observation noise
    samples: np.ndarray  # (N, P, D)
    component_weights: np.ndarray  # (K,) responsibilities (1 for single-type models)
    noise_sd: np.ndarray  # (D,) observation noise s.d. in data units


def noise_sd_of(result) -> np.ndarray:
    """Observation-noise s.d. per DoF in data units: :math:`E[\beta]^{-1/2}` when
    ``beta`` was learned (posterior mean), else the fixed ``hyper.beta``."""
    beta = result.point.get("beta") if result.point else None
    if beta is None and result.draws is not None and "beta" in result.draws:
        beta = np.mean(result.draws["beta"])
    beta = result.hyper.beta if beta is None else float(np.mean(beta))
    return np.asarray(result.scaling.scale, dtype=float) / np.sqrt(beta)


def predict_from_fit(
    result,
    phase: np.ndarray,
    values: np.ndarray,
    *,
    noise_sd: float | np.ndarray | None = None,
    bayesian: bool = True,
    exact: bool = True,
    num_phases: int = 100,
    query: np.ndarray | None = None,
    num_samples: int = 20,
    max_draws: int = 200,
    key=None,
) -> Prediction:
    """Condition ``result`` on observed positions and predict the whole movement.

    Parameters
    ----------
    result : a FitResult (fresh or from :func:`lmpromp_ppl.load`)
    phase : (T,) phases in [0, 1] of the observations
    values : (T, D) positions in data units; NaN marks an unobserved entry
        (partial observation of some DoF); T = 0 gives the population
        (unconditioned) movement distribution
    noise_sd : observation noise s.d. in data units (scalar or per DoF);
        default :func:`noise_sd_of` the fit
    bayesian : average over posterior draws (default) instead of plugging in
        the posterior mean
    exact : the exact conditional p(w | o) (default); ``False`` gives the
        thesis's approximation, eqs. 4.6-4.7
    num_phases : predict at this many equally spaced phases in [0, 1] ...
    query : ... or at these phases
    key : PRNG key of the sampled trajectories; default: derived from the fit's seed
    """
    values = np.asarray(values, dtype=float)
    phase = np.asarray(phase, dtype=float)
    D = result.num_dofs
    if values.ndim != 2 or values.shape[1] != D:
        raise DataError(f"observed positions must have shape (T, {D}) for this fit, got {values.shape}")
    if phase.shape != (values.shape[0],):
        raise DataError(f"{phase.shape[0]} phases for {values.shape[0]} observed samples")
    if np.any(np.isinf(values)):
        raise DataError("observed positions contain inf")
    mask = np.isfinite(values)
    if noise_sd is None:
        noise_sd = noise_sd_of(result)
    noise = np.broadcast_to(np.asarray(noise_sd, dtype=float), (D,))
    if phase.size == 0:
        obs = empty_observation(D * result.num_basis)
    else:
        obs = observe(
            phase, np.where(mask, values, 0.0), noise_sd=noise_sd, num_dofs=D, num_basis=result.num_basis,
            width=result.width, mask=mask, scaling=result.scaling,
        )
    gamma = result.hyper.gamma
    if bayesian:
        draws = result.posterior_draws()
        flat = {k: np.asarray(v).reshape((-1,) + np.asarray(v).shape[2:]) for k, v in draws.items()}
        n = next(iter(flat.values())).shape[0]
        keep = np.linspace(0, n - 1, min(n, max_draws)).astype(int)
        post = condition_draws(result.model, {k: v[keep] for k, v in flat.items()}, obs, gamma, exact=exact)
    else:
        post = condition(result.model, result.point, obs, gamma, exact=exact)
    query = np.linspace(0.0, 1.0, num_phases) if query is None else np.asarray(query, dtype=float)
    traj = trajectory_distribution(post.weights, query, num_dofs=D, num_basis=result.num_basis, width=result.width)
    key = seed_key(result.seed, PREDICTION) if key is None else key
    paths = np.asarray(
        sample_trajectories(key, post.weights, query, num_samples, num_dofs=D, num_basis=result.num_basis, width=result.width)
    )
    scale, shift = np.asarray(result.scaling.scale), np.asarray(result.scaling.mean)
    weights = np.exp(np.asarray(post.weights.log_weights))
    sd = np.asarray(traj.sd) * scale
    return Prediction(
        phase=query,
        mean=np.asarray(traj.mean) * scale + shift,
        sd=sd,
        sd_obs=np.sqrt(sd**2 + noise**2),
        samples=paths * scale + shift,
        component_weights=weights / weights.sum(),
        noise_sd=noise,
    )


def population_prediction(result, **options) -> Prediction:
    """The movement distribution of a new demonstration, conditioned on nothing (options as :func:`predict_from_fit`)."""
    return predict_from_fit(result, np.zeros(0), np.zeros((0, result.num_dofs)), **options)

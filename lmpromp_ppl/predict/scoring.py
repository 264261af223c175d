r"""Held-out scoring: log predictive density and RMSE of a predicted demonstration.

The predictive of an observed set of rows :math:`\mathbf{y}_*` (a whole
held-out demonstration under the prior, or its unobserved remainder under the
distribution conditioned on its observed part) is Gaussian in observation
space for each weight component:

.. math::

    \log p(\mathbf{y}_*) = \log \sum_k z_k\,
    \mathcal{N}(\mathbf{y}_* | \Psi_* \boldsymbol\mu_k, \Sigma_* + \Psi_* \Sigma_k \Psi_*^T),

a log-sum-exp over mixture components and, for the Bayesian predictive of
:func:`~lmpromp_ppl.predict.conditioning.condition_draws`, a log-mean-exp over
draws (the draws are components with weight 1/S).  :math:`\Sigma_*` is the
target's observation noise, normally :math:`\beta^{-1} I`: build the target
with ``observe(..., noise_sd=beta ** -0.5)``.

The work is jit-compiled; the :class:`Scaling` argument (NumPy arrays) is
converted to per-row scales outside the compiled part.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.scipy.special import logsumexp

from lmpromp_ppl.data.core import Scaling
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.predict.gaussian import GaussianMixture, log_marginal_density
from lmpromp_ppl.predict.observations import Observation

__all__ = ["HeldoutScore", "log_predictive_density", "rmse", "score_heldout"]


class HeldoutScore(NamedTuple):
    """Scores of a prediction on held-out rows.

    Attributes
    ----------
    log_density : () array
        :func:`log_predictive_density` (nats, total over rows).
    log_density_per_row : () array
        ``log_density`` divided by the number of rows.
    rmse : () array
        :func:`rmse` of the predicted mean.
    """

    log_density: Array
    log_density_per_row: Array
    rmse: Array


def _check(weights: GaussianMixture, target: Observation) -> None:
    if target.psi.ndim != 2 or target.psi.shape[1] != weights.means.shape[1]:
        raise LmprompError(
            f"target has weight dimension {target.psi.shape[-1]}, the prediction has {weights.means.shape[1]}"
        )


def _row_scale(target: Observation, scaling: Scaling | None) -> Array:
    if scaling is None:
        return jnp.ones_like(target.values)
    return jnp.asarray(scaling.scale, dtype=jnp.float64)[target.dof]


@jax.jit
def _log_density(weights: GaussianMixture, target: Observation, row_scale: Array) -> Array:
    per_component = jax.vmap(lambda mean, cov: log_marginal_density(mean, cov, target))(
        weights.means, weights.covs
    )
    return logsumexp(weights.log_weights + per_component) - jnp.sum(jnp.log(row_scale))


@jax.jit
def _rmse(weights: GaussianMixture, target: Observation, row_scale: Array) -> Array:
    mean = jnp.einsum("k,ki->i", weights.weights, weights.means)
    residual = (target.values - target.psi @ mean) * row_scale
    return jnp.sqrt(jnp.mean(residual**2))


def log_predictive_density(
    weights: GaussianMixture, target: Observation, scaling: Scaling | None = None
) -> Array:
    r"""Log predictive density of the target rows under a weight distribution.

    .. math::

        \log \sum_k z_k\, \mathcal{N}(\mathbf{y}_* | \Psi_*\boldsymbol\mu_k, \Sigma_* + \Psi_*\Sigma_k\Psi_*^T)

    Parameters
    ----------
    weights : GaussianMixture
        A prior, conditioned or Bayesian predictive (``Conditioned.weights``).
    target : Observation
        Held-out rows :math:`\Psi_*, \mathbf{y}_*, \Sigma_*`.
    scaling : Scaling, optional
        When given, the density is of the original units: the Jacobian
        :math:`-\sum_n \log s_{k(n)}` of the standardisation is added.

    Returns
    -------
    () array
    """
    _check(weights, target)
    return _log_density(weights, target, _row_scale(target, scaling))


def rmse(weights: GaussianMixture, target: Observation, scaling: Scaling | None = None) -> Array:
    r"""Root-mean-square error of the predicted mean :math:`\Psi_* \sum_k z_k \boldsymbol\mu_k` on the target rows.

    Parameters
    ----------
    weights : GaussianMixture
    target : Observation
    scaling : Scaling, optional
        When given, the error is in original units (residuals times the scale of each row's DoF).
    """
    _check(weights, target)
    return _rmse(weights, target, _row_scale(target, scaling))


def score_heldout(
    weights: GaussianMixture, target: Observation, scaling: Scaling | None = None
) -> HeldoutScore:
    """:func:`log_predictive_density` and :func:`rmse` of ``target`` together."""
    log_density = log_predictive_density(weights, target, scaling)
    return HeldoutScore(log_density, log_density / target.values.shape[0], rmse(weights, target, scaling))

r"""Trajectory distributions and samples from a weight distribution (thesis Sec. 3.1, eq. 3.1).

A weight distribution :math:`p(\mathbf{w})` (a prior, a conditioned
predictive, or a Bayesian predictive, all :class:`GaussianMixture`) induces a
distribution over the position of DoF k at phase z,
:math:`y_k(z) = \psi(z)^T \mathbf{w}_k + \epsilon`, with
:math:`\epsilon \sim \mathcal{N}(0, \beta^{-1})` when observation noise is
included.  Only the diagonal blocks of the weight covariances are needed for
the per-(phase, DoF) standard deviation:

.. math::

    m_{k t d} = \psi(z_t)^T \boldsymbol\mu_{k,d}, \qquad
    v_{k t d} = \psi(z_t)^T \Sigma_{k,dd}\, \psi(z_t) + \beta^{-1},

and the mixture's moments are :math:`\bar m = \sum_k z_k m_k`,
:math:`\bar v = \sum_k z_k (v_k + (m_k - \bar m)^2)` (mean = average of
means; variance = average of (variance + mean^2) - mean^2).

Results are in the standardised space of the fit; :func:`unstandardise` and
:func:`unstandardise_samples` map them back with a :class:`Scaling`.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from lmpromp_ppl.basis import DEFAULT_WIDTH, rbf_basis
from lmpromp_ppl.data.core import Scaling
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.predict.gaussian import GaussianMixture

__all__ = [
    "TrajectoryDistribution",
    "trajectory_distribution",
    "sample_weights",
    "sample_trajectories",
    "unstandardise",
    "unstandardise_samples",
]


class TrajectoryDistribution(NamedTuple):
    """Per-(phase, DoF) moments of a trajectory distribution.

    Attributes
    ----------
    phase : (T,) array
    mean : (T, D) array
        Mixture mean.
    sd : (T, D) array
        Mixture standard deviation (marginal, per phase and DoF).
    component_means : (K, T, D) array
    component_sds : (K, T, D) array
    component_weights : (K,) array
        Responsibilities / mixture weights of the components.
    """

    phase: Array
    mean: Array
    sd: Array
    component_means: Array
    component_sds: Array
    component_weights: Array


def _split_weights(
    weights: GaussianMixture, num_dofs: int, num_basis: int
) -> tuple[Array, Array]:
    num_components, num_weights = weights.means.shape
    if num_weights != num_dofs * num_basis:
        raise LmprompError(
            f"weight dimension {num_weights} is not num_dofs x num_basis = {num_dofs} x {num_basis}"
        )
    means = weights.means.reshape(num_components, num_dofs, num_basis)
    full = weights.covs.reshape(num_components, num_dofs, num_basis, num_dofs, num_basis)
    blocks = jnp.stack([full[:, k, :, k, :] for k in range(num_dofs)], axis=1)  # (K, D, J, J)
    return means, blocks


def _noise_variance(beta: ArrayLike | None) -> Array:
    if beta is None:
        return jnp.zeros(())
    return 1.0 / jnp.asarray(beta, dtype=jnp.float64)


@partial(jax.jit, static_argnames=("num_dofs", "num_basis", "width"))
def trajectory_distribution(
    weights: GaussianMixture,
    phase: ArrayLike,
    *,
    num_dofs: int,
    num_basis: int,
    width: float = DEFAULT_WIDTH,
    beta: ArrayLike | None = None,
) -> TrajectoryDistribution:
    r"""Mean and standard deviation of the trajectory at each (phase, DoF).

    Parameters
    ----------
    weights : GaussianMixture
        Weight distribution, e.g. ``condition(...).weights``.
    phase : (T,) array
        Query phases.
    num_dofs, num_basis, width
        The basis of the fit.
    beta : float, optional
        Observation-noise precision; when given, :math:`\beta^{-1}` is added
        to each variance (predicting observed positions rather than the
        noise-free trajectory :math:`\Psi\mathbf{w}`).

    Returns
    -------
    TrajectoryDistribution
    """
    means, blocks = _split_weights(weights, num_dofs, num_basis)
    phi = rbf_basis(phase, num_basis, width)  # (T, J)
    component_means = jnp.einsum("tj,kdj->ktd", phi, means)
    component_vars = jnp.einsum("tj,kdji,ti->ktd", phi, blocks, phi) + _noise_variance(beta)
    component_vars = jnp.maximum(component_vars, 0.0)
    z = weights.weights
    mean = jnp.einsum("k,ktd->td", z, component_means)
    var = jnp.einsum("k,ktd->td", z, component_vars + (component_means - mean) ** 2)
    return TrajectoryDistribution(
        phase=jnp.asarray(phase, dtype=jnp.float64),
        mean=mean,
        sd=jnp.sqrt(var),
        component_means=component_means,
        component_sds=jnp.sqrt(component_vars),
        component_weights=z,
    )


@partial(jax.jit, static_argnames=("num_samples",))
def sample_weights(key: Array, weights: GaussianMixture, num_samples: int) -> Array:
    r"""Draw weight vectors from a Gaussian mixture.

    A component is drawn from the mixture weights, then
    :math:`\mathbf{w} = \boldsymbol\mu_k + U_k \Lambda_k^{1/2} \boldsymbol\epsilon`
    with the eigendecomposition :math:`\Sigma_k = U_k \Lambda_k U_k^T`
    (negative round-off eigenvalues clipped to 0), which also handles the
    singular covariances of noiseless conditioning.

    Parameters
    ----------
    key : PRNG key
    weights : GaussianMixture
    num_samples : int
        Static.

    Returns
    -------
    (num_samples, d) array
    """
    key_component, key_noise = jax.random.split(key)
    component = jax.random.categorical(key_component, weights.log_weights, shape=(num_samples,))
    eigenvalues, eigenvectors = jnp.linalg.eigh(weights.covs)
    roots = eigenvectors * jnp.sqrt(jnp.maximum(eigenvalues, 0.0))[:, None, :]
    noise = jax.random.normal(key_noise, (num_samples, weights.means.shape[1]))
    return jax.vmap(lambda k, e: weights.means[k] + roots[k] @ e)(component, noise)


@partial(jax.jit, static_argnames=("num_samples", "num_dofs", "num_basis", "width"))
def sample_trajectories(
    key: Array,
    weights: GaussianMixture,
    phase: ArrayLike,
    num_samples: int,
    *,
    num_dofs: int,
    num_basis: int,
    width: float = DEFAULT_WIDTH,
    beta: ArrayLike | None = None,
) -> Array:
    r"""Draw trajectories :math:`\Psi \mathbf{w}` (plus :math:`\mathcal{N}(0, \beta^{-1})` noise when ``beta`` is given).

    Parameters
    ----------
    key : PRNG key
    weights : GaussianMixture
        Prior or conditioned weight distribution.
    phase : (T,) array
    num_samples : int
        Static.
    num_dofs, num_basis, width
        The basis of the fit.
    beta : float, optional
        Observation-noise precision.

    Returns
    -------
    (num_samples, T, D) array
    """
    key_weights, key_noise = jax.random.split(key)
    drawn = sample_weights(key_weights, weights, num_samples)
    phi = rbf_basis(phase, num_basis, width)
    if drawn.shape[1] != num_dofs * num_basis:
        raise LmprompError(
            f"weight dimension {drawn.shape[1]} is not num_dofs x num_basis = {num_dofs} x {num_basis}"
        )
    paths = jnp.einsum("tj,ndj->ntd", phi, drawn.reshape(num_samples, num_dofs, num_basis))
    if beta is None:
        return paths
    return paths + jnp.sqrt(_noise_variance(beta)) * jax.random.normal(key_noise, paths.shape)


def unstandardise(distribution: TrajectoryDistribution, scaling: Scaling) -> TrajectoryDistribution:
    """Map moments back to the original units: mean -> mean + scale * x, sd -> sd * scale."""
    shift = jnp.asarray(scaling.mean, dtype=jnp.float64)
    scale = jnp.asarray(scaling.scale, dtype=jnp.float64)
    return distribution._replace(
        mean=shift + scale * distribution.mean,
        sd=scale * distribution.sd,
        component_means=shift + scale * distribution.component_means,
        component_sds=scale * distribution.component_sds,
    )


def unstandardise_samples(samples: ArrayLike, scaling: Scaling) -> Array:
    """Map trajectory samples (..., D) back to the original units."""
    shift = jnp.asarray(scaling.mean, dtype=jnp.float64)
    scale = jnp.asarray(scaling.scale, dtype=jnp.float64)
    return shift + scale * jnp.asarray(samples)

r"""Gaussian mixtures in weight space and the Gaussian conditioning of eqs. (3.2), (3.3).

Every predictive of lmpromp-ppl is a :class:`GaussianMixture` over the weight
vector :math:`\mathbf{w}`: one component for the ProMP and the LMProMP, K for
the mixture model, and S x K for a Bayesian predictive averaged over S
posterior draws.  Trajectory moments, samples and held-out scores are then
computed the same way for every model (:mod:`.trajectories`, :mod:`.scoring`).

Linear algebra uses Cholesky factors and triangular solves only, never an
explicit inverse: for an observation
:math:`\mathbf{o} = \Psi_o \mathbf{w} + \epsilon` with
:math:`\mathbf{w} \sim \mathcal{N}(\boldsymbol\mu, \Sigma)` and
:math:`A = \Sigma_o + \Psi_o \Sigma \Psi_o^T`, eqs. (3.2) and (3.3) read

.. math::

    \boldsymbol\mu_{w|o} = \boldsymbol\mu + G^T A^{-1} \mathbf{r}, \qquad
    \Sigma_{w|o} = \Sigma - G^T A^{-1} G, \qquad
    G = \Psi_o \Sigma, \quad \mathbf{r} = \mathbf{o} - \Psi_o \boldsymbol\mu,

with the quadratic forms :math:`X^T A^{-1} Y` computed by
:func:`observation_marginal` (a Cholesky factor of A when there are fewer
observed rows than weights, the Woodbury form in weight space otherwise).  If
:math:`A` is not positive definite (noiseless observations that are linearly
dependent under the prior) the factor, and hence the result, is NaN.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax.numpy as jnp
from jax import Array
from jax.scipy.linalg import solve_triangular

from lmpromp_ppl.predict.observations import Observation

__all__ = ["GaussianMixture", "Marginal", "observation_marginal", "condition_gaussian", "log_marginal_density"]

_LOG_2PI = jnp.log(2.0 * jnp.pi)


class GaussianMixture(NamedTuple):
    r"""A mixture :math:`\sum_k \exp(\ell_k)\, \mathcal{N}(\boldsymbol\mu_k, \Sigma_k)`.

    Attributes
    ----------
    log_weights : (K,) array
        Normalised log mixture weights :math:`\ell_k` (``-inf`` allowed).
    means : (K, n) array
        Component means.
    covs : (K, n, n) array
        Component covariances.
    """

    log_weights: Array
    means: Array
    covs: Array

    @property
    def num_components(self) -> int:
        """K, the number of components."""
        return self.means.shape[0]

    @property
    def weights(self) -> Array:
        """Mixture weights :math:`\\exp(\\ell_k)`, shape (K,)."""
        return jnp.exp(self.log_weights)

    def moments(self) -> tuple[Array, Array]:
        r"""Moment-matched mean and covariance of the mixture.

        .. math::

            \boldsymbol\mu = \sum_k z_k \boldsymbol\mu_k, \qquad
            \Sigma = \sum_k z_k \left(\Sigma_k + (\boldsymbol\mu_k - \boldsymbol\mu)
            (\boldsymbol\mu_k - \boldsymbol\mu)^T\right).

        The between-component term is what Sec. 4.2.2 leaves out (erratum).
        The mean of a multimodal mixture can lie between its modes, where the
        mixture has little mass: look at the components too.
        """
        z = self.weights
        mean = jnp.einsum("k,ki->i", z, self.means)
        centred = self.means - mean
        cov = jnp.einsum("k,kij->ij", z, self.covs) + jnp.einsum("k,ki,kj->ij", z, centred, centred)
        return mean, cov


class Marginal(NamedTuple):
    r"""Solves with the observation-space covariance :math:`A = \Sigma_o + \Psi_o \Sigma \Psi_o^T`.

    Attributes
    ----------
    quad : callable
        ``quad(X, Y)`` returns :math:`X^T A^{-1} Y` for X, Y of shape (N,) or (N, a).
    log_det : () array
        :math:`\log |A|`.
    """

    quad: Callable[[Array, Array], Array]
    log_det: Array


def _row_scaled(x: Array, scale: Array) -> Array:
    return x / scale.reshape(scale.shape + (1,) * (x.ndim - 1))


def observation_marginal(cov: Array, observation: Observation) -> Marginal:
    r"""Factor :math:`A = \Sigma_o + \Psi_o \Sigma \Psi_o^T` for solves and its log-determinant.

    With N rows and d weights, N <= d uses the Cholesky factor of the N x N
    matrix A (noiseless rows allowed).  N > d uses the weight-space (Woodbury)
    form, O(N d^2) instead of O(N^3): with :math:`\Sigma = R R^T`
    (eigendecomposition, so singular :math:`\Sigma` is fine),
    :math:`U = \Sigma_o^{-1/2}\Psi_o R` and :math:`K = I + U^T U = L_K L_K^T`,

    .. math::

        A^{-1} = \Sigma_o^{-1/2}(I - U K^{-1} U^T)\Sigma_o^{-1/2}, \qquad
        \log|A| = \log|\Sigma_o| + \log|K|,

    which needs every noise variance to be positive; with N > d and a zero
    noise variance A is singular anyway.

    Parameters
    ----------
    cov : (d, d) array
        Prior covariance of the weights.
    observation : Observation
    """
    psi = observation.psi
    num_rows, num_weights = psi.shape
    if num_rows <= num_weights:
        gram = psi @ cov @ psi.T + jnp.diag(observation.noise_var)
        chol = jnp.linalg.cholesky(0.5 * (gram + gram.T))

        def quad_chol(x: Array, y: Array) -> Array:
            return jnp.tensordot(
                solve_triangular(chol, x, lower=True), solve_triangular(chol, y, lower=True), axes=(0, 0)
            )

        return Marginal(quad_chol, 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol))))
    eigenvalues, eigenvectors = jnp.linalg.eigh(0.5 * (cov + cov.T))
    root = eigenvectors * jnp.sqrt(jnp.maximum(eigenvalues, 0.0))
    noise_sd = jnp.sqrt(observation.noise_var)
    factor = _row_scaled(psi @ root, noise_sd)  # U, (N, d)
    chol_k = jnp.linalg.cholesky(jnp.eye(num_weights) + factor.T @ factor)

    def quad_woodbury(x: Array, y: Array) -> Array:
        x_white = _row_scaled(x, noise_sd)
        y_white = _row_scaled(y, noise_sd)
        x_low = solve_triangular(chol_k, jnp.tensordot(factor, x_white, axes=(0, 0)), lower=True)
        y_low = solve_triangular(chol_k, jnp.tensordot(factor, y_white, axes=(0, 0)), lower=True)
        return jnp.tensordot(x_white, y_white, axes=(0, 0)) - jnp.tensordot(x_low, y_low, axes=(0, 0))

    log_det = jnp.sum(jnp.log(observation.noise_var)) + 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol_k)))
    return Marginal(quad_woodbury, log_det)


def _log_density(residual: Array, marginal: Marginal) -> Array:
    num_rows = residual.shape[0]
    return -0.5 * marginal.quad(residual, residual) - 0.5 * marginal.log_det - 0.5 * num_rows * _LOG_2PI


def log_marginal_density(mean: Array, cov: Array, observation: Observation) -> Array:
    r""":math:`\log \mathcal{N}(\mathbf{o} | \Psi_o \boldsymbol\mu, \Sigma_o + \Psi_o \Sigma \Psi_o^T)`.

    Parameters
    ----------
    mean : (d,) array
        Mean of the weights.
    cov : (d, d) array
        Covariance of the weights.
    observation : Observation
    """
    marginal = observation_marginal(cov, observation)
    return _log_density(observation.values - observation.psi @ mean, marginal)


def condition_gaussian(
    mean: Array, cov: Array, observation: Observation, marginal: Marginal | None = None
) -> tuple[Array, Array, Array]:
    r"""Condition :math:`\mathcal{N}(\mathbf{w} | \boldsymbol\mu, \Sigma)` on a linear-Gaussian observation (eqs. 3.2, 3.3).

    Parameters
    ----------
    mean : (d,) array
    cov : (d, d) array
    observation : Observation
    marginal : Marginal, optional
        :func:`observation_marginal` of ``cov`` and ``observation``, when already computed.

    Returns
    -------
    mean : (d,) array
        :math:`\boldsymbol\mu_{w|o}` (eq. 3.2).
    cov : (d, d) array
        :math:`\Sigma_{w|o}` (eq. 3.3), symmetrised.
    log_marginal : () array
        :math:`\log p(\mathbf{o}) = \log \mathcal{N}(\mathbf{o} | \Psi_o\boldsymbol\mu, A)`.
    """
    if marginal is None:
        marginal = observation_marginal(cov, observation)
    residual = observation.values - observation.psi @ mean
    gain = observation.psi @ cov  # Psi_o Sigma, (N, d)
    post_mean = mean + marginal.quad(gain, residual)
    post_cov = cov - marginal.quad(gain, gain)
    return post_mean, 0.5 * (post_cov + post_cov.T), _log_density(residual, marginal)

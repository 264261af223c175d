r"""Closed-form optimal factors given weighted sufficient statistics (one kernel per factor).

The updates of :mod:`.updates` call these with per-demonstration weights
``weights`` (L,): the responsibilities :math:`r_{ik}` of one component k (all
ones for the single type).  The weight kernel takes a per-demonstration prior
precision (:math:`\sum_k r_{ik}\bar\alpha_k`), which keeps the shared-:math:`\Psi`
fast path valid.  Derivations: ``docs/derivation.md`` (App. B.1 and B.2 corrected).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array
from jax.scipy.linalg import cho_solve
from jax.scipy.special import digamma, gammaln

from lmpromp_ppl.inference.cavi.data import (
    CaviData,
    Covariance,
    DiagonalCovariance,
    DiagonalGram,
    EigenCovariance,
    FullCovariance,
    SharedGram,
)

__all__ = [
    "w_posterior",
    "h_posterior",
    "joint_posterior",
    "b_posterior",
    "M_columns_posterior",
    "M_rows_posterior",
    "gamma_entropy",
    "gamma_log_prior",
    "xlogx",
]


def w_posterior(
    data: CaviData, beta: Array, prior_precision: Array, prior_linear: Array
) -> tuple[Array, Covariance]:
    """q*(w_i) for a Gaussian prior with precision ``prior_precision[i] * I``.

    Precision :math:`\\beta\\Psi_i^T\\Psi_i + \\bar\\alpha_i I`; mean
    :math:`\\Sigma_{w_i}(\\beta\\Psi_i^T y_i + \\ell_i)`, where ``prior_linear``
    :math:`\\ell_i` is the prior's precision times its mean.  On the fast path the
    precision is diagonal in the shared eigenbasis for any per-demonstration
    ``prior_precision`` (mixture: :math:`\\sum_k r_{ik}\\bar\\alpha_k`); in the rotated
    coordinates of :class:`~.data.DiagonalGram` it is diagonal, O(L d).
    """
    linear = beta * data.psi_t_y + prior_linear
    gram = data.gram
    if isinstance(gram, DiagonalGram):
        variances = 1.0 / (beta * gram.eigvals[None, :] + prior_precision[:, None])
        return linear * variances, DiagonalCovariance(variances)
    if isinstance(gram, SharedGram):
        variances = 1.0 / (beta * gram.eigvals[None, :] + prior_precision[:, None])
        mean = ((linear @ gram.basis) * variances) @ gram.basis.T
        return mean, EigenCovariance(gram.basis, variances)
    d = linear.shape[-1]
    precision = beta * gram.matrices + prior_precision[:, None, None] * jnp.eye(d)
    chol = jnp.linalg.cholesky(precision)
    solve = jax.vmap(lambda c, rhs: cho_solve((c, True), rhs))
    cov = solve(chol, jnp.broadcast_to(jnp.eye(d), precision.shape))
    cov = 0.5 * (cov + jnp.swapaxes(cov, -1, -2))
    mean = solve(chol, linear)
    return mean, FullCovariance(cov)


def h_posterior(
    weights: Array, alpha_mean: Array, MtM: Array, M_mean: Array, offset: Array, gamma: Array
) -> tuple[Array, Array]:
    """q*(h_i): precision :math:`r_i\\bar\\alpha E[M^TM] + \\gamma I`, mean :math:`\\Sigma_{h_i} r_i\\bar\\alpha\\bar M^T(\\mu_{w_i}-\\mu_b)`."""
    V = MtM.shape[0]
    precision = (weights * alpha_mean)[:, None, None] * MtM + gamma * jnp.eye(V)
    chol = jnp.linalg.cholesky(precision)
    solve = jax.vmap(lambda c, rhs: cho_solve((c, True), rhs))
    cov = solve(chol, jnp.broadcast_to(jnp.eye(V), precision.shape))
    cov = 0.5 * (cov + jnp.swapaxes(cov, -1, -2))
    mean = solve(chol, (weights * alpha_mean)[:, None] * (offset @ M_mean))
    return mean, cov


def joint_posterior(
    alpha_mean: Array, MtM: Array, M_mean: Array, offset: Array, a: Array, WM: Array, gamma: Array
) -> tuple[Array, Array, Array, Array]:
    """q*(w_i, h_i) of the joint local family from q*(w_i) with h_i integrated out of its prior mean.

    ``a`` (L, d) and ``W`` are that q*(w_i)'s mean and covariance, ``offset`` is
    :math:`a_i - \\mu_b` and ``WM`` is :math:`W_i\\bar M` (L, d, V).  Returns
    :math:`\\mu_{w_i}`, :math:`\\mu_{h_i}`, :math:`S_i` and :math:`C_i` of
    :func:`~lmpromp_ppl.inference.cavi.updates.update_wh`.
    """
    V = MtM.shape[0]
    B = alpha_mean * WM
    precision = alpha_mean * MtM[None] - alpha_mean * jnp.einsum("dv,idu->ivu", M_mean, B) + gamma * jnp.eye(V)
    chol = jnp.linalg.cholesky(precision)
    solve = jax.vmap(lambda c, rhs: cho_solve((c, True), rhs))
    S = solve(chol, jnp.broadcast_to(jnp.eye(V), precision.shape))
    S = 0.5 * (S + jnp.swapaxes(S, -1, -2))
    h = solve(chol, alpha_mean * offset @ M_mean)
    w = a + jnp.einsum("idv,iv->id", B, h)
    return w, h, S, jnp.einsum("idu,iuv->idv", B, S)


def b_posterior(
    weights: Array, alpha_mean: Array, w_mean: Array, h_mean: Array, M_mean: Array, lambda0: Array
) -> tuple[Array, Array]:
    """q*(b): :math:`\\sigma_b = (\\bar\\alpha\\sum_i r_i + \\lambda_0)^{-1}`, :math:`\\mu_b = \\sigma_b\\bar\\alpha\\sum_i r_i(\\mu_{w_i} - \\bar M\\mu_{h_i})`."""
    var = 1.0 / (alpha_mean * jnp.sum(weights) + lambda0)
    mean = var * alpha_mean * (weights @ (w_mean - h_mean @ M_mean.T))
    return mean, var


def M_columns_posterior(
    weights: Array, alpha_mean: Array, hhT: Array, offset: Array, h_mean: Array, lam_mean: Array,
    cross: Array | None = None,
) -> tuple[Array, Array]:
    """Joint column-wise q*(m_1..m_V) from S = sum r_i E[h_i h_i^T], R = sum r_i (mu_wi - mu_b) mu_hi^T.

    :math:`\\bar M(\\bar\\alpha S + \\operatorname{diag}\\bar\\lambda) = \\bar\\alpha R`,
    :math:`\\sigma_{m_v} = (\\bar\\alpha S_{vv} + \\bar\\lambda_v)^{-1}`.
    """
    S = jnp.einsum("i,iuv->uv", weights, hhT)
    R = jnp.einsum("i,id,iv->dv", weights, offset, h_mean) + (0.0 if cross is None else cross)
    A = alpha_mean * S + jnp.diag(lam_mean)
    mean = jnp.linalg.solve(A, alpha_mean * R.T).T
    var = 1.0 / (alpha_mean * jnp.diagonal(S) + lam_mean)
    return mean, var


def M_rows_posterior(
    weights: Array, alpha_mean: Array, hhT: Array, offset: Array, h_mean: Array, lam_mean: Array,
    cross: Array | None = None,
) -> tuple[Array, Array]:
    """Row-wise q*(M): rows :math:`\\mathcal N(\\mu_{j\\cdot}, A^{-1})`, :math:`A = \\bar\\alpha S + \\operatorname{diag}\\bar\\lambda`, :math:`\\bar M = \\bar\\alpha R A^{-1}`."""
    S = jnp.einsum("i,iuv->uv", weights, hhT)
    R = jnp.einsum("i,id,iv->dv", weights, offset, h_mean) + (0.0 if cross is None else cross)
    V = S.shape[0]
    A = alpha_mean * S + jnp.diag(lam_mean)
    chol = jnp.linalg.cholesky(A)
    cov = cho_solve((chol, True), jnp.eye(V))
    cov = 0.5 * (cov + cov.T)
    mean = cho_solve((chol, True), alpha_mean * R.T).T
    return mean, cov


def gamma_entropy(
    shape: Array, rate: Array, log_mean: Array | None = None, gammaln_shape: Array | None = None
) -> Array:
    """Entropy of :math:`\\Gamma(\\text{shape}, \\text{rate})`: :math:`a - \\log b + \\log\\Gamma(a) + (1 - a)\\psi(a)`.

    ``log_mean`` (:math:`E[\\log x] = \\psi(a) - \\log b`) and ``gammaln_shape``
    (:math:`\\log\\Gamma(a)`), when given, are used instead of evaluating the special
    functions again (the bound evaluates each once, for every factor together).
    """
    psi = digamma(shape) if log_mean is None else log_mean + jnp.log(rate)
    lgamma = gammaln(shape) if gammaln_shape is None else gammaln_shape
    return shape - jnp.log(rate) + lgamma + (1.0 - shape) * psi


def gamma_log_prior(shape0: Array, rate0: Array, log_mean: Array, mean: Array,
                    gammaln_shape0: Array | None = None) -> Array:
    """:math:`E_q[\\log\\Gamma(x\\mid a_0, b_0)]` from :math:`E[\\log x]` and :math:`E[x]`."""
    lgamma = gammaln(shape0) if gammaln_shape0 is None else gammaln_shape0
    return shape0 * jnp.log(rate0) - lgamma + (shape0 - 1.0) * log_mean - rate0 * mean


def xlogx(x: Array) -> Array:
    """:math:`x\\log x` with :math:`0\\log 0 = 0`."""
    safe = jnp.where(x > 0, x, 1.0)
    return jnp.where(x > 0, x * jnp.log(safe), 0.0)

r"""Hand-derived mean-field variational inference (CAVI) for the single-type LMProMP.

Model (thesis Sec. 4.1; precisions everywhere, Gamma is shape/rate):

.. math::

    b &\sim \mathcal N(0, \lambda_0^{-1} I_d), \quad
    \lambda_v \sim \Gamma(c_0, d_0), \quad
    m_v \sim \mathcal N(0, \lambda_v^{-1} I_d), \quad
    \alpha \sim \Gamma(a_0, b_0), \\
    h_i &\sim \mathcal N(0, \gamma^{-1} I_V), \quad
    w_i \sim \mathcal N(b + M h_i, \alpha^{-1} I_d), \quad
    y_i \sim \mathcal N(\Psi_i w_i, \beta^{-1} I)\ \text{(observed entries)}.

Mean-field family (thesis eq. 4.3): :math:`q(w_i) = \mathcal N(\mu_{w_i}, \Sigma_{w_i})`,
:math:`q(h_i) = \mathcal N(\mu_{h_i}, \Sigma_{h_i})`,
:math:`q(b) = \mathcal N(\mu_b, \sigma_b I)`,
:math:`q(m_v) = \mathcal N(\mu_{m_v}, \sigma_{m_v} I)`,
:math:`q(\alpha) = \Gamma(\bar a, \bar b)`, :math:`q(\lambda_v) = \Gamma(\bar c_v, \bar d_v)`.

Every update is derived in ``docs/derivation.md`` and checked in
``tests/test_cavi.py`` by autodiff stationarity of :func:`elbo` (the gradient
of the bound with respect to the updated factor's own parameters vanishes).
Four corrections to the thesis are implemented (see each docstring):
the coupling between the columns of M in the update of :math:`\mu_{m_v}`
(App. B.1), the inverse in :math:`\sigma_b` (App. B.1), the factor d in
:math:`E[M^T M]` and the :math:`\frac d2 E[\log\lambda_v]` term of the bound
(App. C.1).

Layout for the extensions (mixture, structured q(M), learned beta)
-------------------------------------------------------------------
The public updates call private kernels written in terms of per-demonstration
weights ``weights`` (L,) (all ones here; the responsibilities :math:`r_{ik}`
of component k in the mixture) and weighted sufficient statistics, and the
weight update :func:`_w_posterior` takes a per-demonstration prior precision
(:math:`\bar\alpha` here, :math:`\sum_k r_{ik}\bar\alpha_k` in the mixture),
which keeps the shared-:math:`\Psi` fast path valid.  The noise precision
enters only as the scalar ``beta`` argument of the kernels (replace it by
:math:`E[\beta]` and add :math:`\frac{n}{2}E[\log\beta]` for a learned beta).

Shared design matrix
--------------------
When every demonstration has the same :math:`\Psi` (:meth:`ModelData.shares_psi`),
:func:`prepare_cavi_data` computes one eigendecomposition
:math:`\Psi^T\Psi = U \operatorname{diag}(s) U^T` per fit and the weight
covariances are kept in that basis (:class:`EigenCovariance`):
:math:`\Sigma_{w_i} = U \operatorname{diag}(1/(\beta s + \bar\alpha_i)) U^T`,
so that a sweep costs :math:`O(L d^2)` instead of :math:`O(L d^3)`.
"""

from __future__ import annotations

import math
import time
import warnings
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.scipy.linalg import cho_solve
from jax.scipy.special import digamma, gammaln

from lmpromp_ppl._progress import show_progress_bars
from lmpromp_ppl.data.core import ModelData
from lmpromp_ppl.errors import ConvergenceWarning, DataError, LmprompError
from lmpromp_ppl.models.hyper import Hyperparameters

__all__ = [
    "HyperArrays",
    "hyper_arrays",
    "DemoGrams",
    "SharedGram",
    "CaviData",
    "prepare_cavi_data",
    "FullCovariance",
    "EigenCovariance",
    "CaviState",
    "CaviInfo",
    "ExpectedStats",
    "RunResult",
    "CaviFit",
    "expected_stats",
    "w_covariance",
    "update_w",
    "update_h",
    "update_b",
    "update_M",
    "update_alpha",
    "update_lam",
    "UPDATES",
    "elbo",
    "step",
    "run",
    "fit_cavi",
    "sample_q",
    "point_estimate",
    "active_latent_dims",
    "FAMILIES",
    "MixtureState",
    "fit_cavi_mixture",
    "active_components",
]

_LOG_2PI = math.log(2.0 * math.pi)


# --------------------------------------------------------------------------- inputs
class HyperArrays(NamedTuple):
    """Hyperparameters as float64 scalars, so compiled code is shared across values.

    Attributes
    ----------
    beta : noise precision :math:`\\beta`
    lambda0 : prior precision :math:`\\lambda^{[0]}` of ``b``
    gamma : prior precision :math:`\\gamma` of ``h``
    a0, b0 : Gamma shape/rate of :math:`\\alpha`
    c0, d0 : Gamma shape/rate of :math:`\\lambda_v`
    """

    beta: Array
    lambda0: Array
    gamma: Array
    a0: Array
    b0: Array
    c0: Array
    d0: Array


def hyper_arrays(hyper: Hyperparameters) -> HyperArrays:
    """Build :class:`HyperArrays` from a :class:`Hyperparameters`."""
    return HyperArrays(*(jnp.asarray(getattr(hyper, name), jnp.float64) for name in HyperArrays._fields))


class DemoGrams(NamedTuple):
    """Per-demonstration masked Gram matrices :math:`\\Psi_i^T \\Psi_i`, (L, d, d)."""

    matrices: Array


class SharedGram(NamedTuple):
    """One Gram matrix :math:`\\Psi^T\\Psi = U \\operatorname{diag}(s) U^T` shared by all demonstrations.

    Attributes
    ----------
    basis : (d, d) orthogonal eigenvectors U (columns)
    eigvals : (d,) eigenvalues s (clipped at 0)
    """

    basis: Array
    eigvals: Array


class CaviData(NamedTuple):
    """Sufficient statistics of the data used by every update.

    Attributes
    ----------
    psi_t_y : (L, d) :math:`\\Psi_i^T y_i` over observed entries
    y_sq : (L,) :math:`y_i^T y_i` over observed entries
    num_obs : (L,) number of observed entries :math:`n_i`
    gram : :class:`DemoGrams` (general path) or :class:`SharedGram` (fast path)
    """

    psi_t_y: Array
    y_sq: Array
    num_obs: Array
    gram: DemoGrams | SharedGram


def prepare_cavi_data(data: ModelData, shared_psi: bool | None = None) -> CaviData:
    """Precompute the data statistics for CAVI.

    Parameters
    ----------
    data : padded model inputs (psi (L, S, d), y (L, S), mask (L, S))
    shared_psi : use the fast path with one eigendecomposition of :math:`\\Psi^T\\Psi`.
        ``None`` chooses it when :meth:`ModelData.shares_psi`; ``True`` demands it
        (error when the demonstrations do not share one design matrix).

    Returns
    -------
    CaviData
    """
    _check_model_data(data)
    shares = data.shares_psi()
    if shared_psi is None:
        shared_psi = shares
    elif shared_psi and not shares:
        raise DataError("shared_psi=True but the demonstrations do not share one design matrix")
    mask = jnp.asarray(data.mask, jnp.float64)
    # masked entries (padding, or NaN for a missing value) are neutralised
    psi = jnp.where(mask[..., None] > 0, jnp.asarray(data.psi, jnp.float64), 0.0)
    y = jnp.where(mask > 0, jnp.asarray(data.y, jnp.float64), 0.0)
    psi_t_y = jnp.einsum("isd,is->id", psi, y)
    y_sq = jnp.sum(y**2, axis=1)
    num_obs = jnp.sum(mask, axis=1)
    if shared_psi:
        eigvals, basis = jnp.linalg.eigh(psi[0].T @ psi[0])
        gram: DemoGrams | SharedGram = SharedGram(basis, jnp.maximum(eigvals, 0.0))
    else:
        gram = DemoGrams(jnp.einsum("isd,is,ise->ide", psi, mask, psi))
    return CaviData(psi_t_y, y_sq, num_obs, gram)


def _check_model_data(data: ModelData) -> None:
    if not isinstance(data, ModelData):
        raise DataError(f"expected ModelData, got {type(data).__name__}")
    psi, y, mask = (np.asarray(a) for a in data)
    if psi.ndim != 3 or y.shape != psi.shape[:2] or mask.shape != psi.shape[:2]:
        raise DataError(
            f"inconsistent ModelData shapes: psi {psi.shape}, y {y.shape}, mask {mask.shape}"
        )
    if not np.all((mask == 0.0) | (mask == 1.0)):
        raise DataError("ModelData.mask must contain only 0 and 1")
    observed = mask == 1.0
    if not np.all(np.isfinite(y[observed])):
        raise DataError("observed entries of ModelData.y contain NaN or inf")
    if not np.all(np.isfinite(psi[observed])):
        raise DataError("design-matrix rows of observed entries contain NaN or inf")


# --------------------------------------------------------------------------- state
class FullCovariance(NamedTuple):
    """Weight covariances stored as (L, d, d) matrices (general path)."""

    matrices: Array


class EigenCovariance(NamedTuple):
    """Weight covariances :math:`\\Sigma_{w_i} = U \\operatorname{diag}(v_i) U^T` with a shared U.

    Attributes
    ----------
    basis : (d, d) the eigenvectors U of the shared Gram matrix
    variances : (L, d) the variances :math:`v_i` in that basis
    """

    basis: Array
    variances: Array


class CaviState(NamedTuple):
    """Parameters of every factor of the mean-field posterior (thesis eq. 4.3).

    Attributes
    ----------
    w_mean : (L, d) :math:`\\mu_{w_i}`
    w_cov : :class:`FullCovariance` or :class:`EigenCovariance`, :math:`\\Sigma_{w_i}`
    h_mean : (L, V) :math:`\\mu_{h_i}`
    h_cov : (L, V, V) :math:`\\Sigma_{h_i}`
    b_mean : (d,) :math:`\\mu_b`
    b_var : () :math:`\\sigma_b` (a variance)
    M_mean : (d, V) :math:`\\bar M = [\\mu_{m_1}, \\dots, \\mu_{m_V}]`
    M_var : (V,) :math:`\\sigma_{m_v}` (variances)
    alpha_shape, alpha_rate : () :math:`\\bar a, \\bar b`
    lam_shape, lam_rate : (V,) :math:`\\bar c_v, \\bar d_v`
    """

    w_mean: Array
    w_cov: FullCovariance | EigenCovariance
    h_mean: Array
    h_cov: Array
    b_mean: Array
    b_var: Array
    M_mean: Array
    M_var: Array
    alpha_shape: Array
    alpha_rate: Array
    lam_shape: Array
    lam_rate: Array


class CaviInfo(NamedTuple):
    """Per-sweep information: the ELBO after the sweep."""

    elbo: Array


class ExpectedStats(NamedTuple):
    """Moments of q shared by the updates and the bound.

    Attributes
    ----------
    alpha_mean, log_alpha_mean : :math:`\\bar\\alpha = \\bar a/\\bar b`, :math:`E[\\log\\alpha] = \\psi(\\bar a) - \\log\\bar b`
    lam_mean, log_lam_mean : (V,) the same for :math:`\\lambda_v`
    MtM : (V, V) :math:`E[M^T M] = \\bar M^T \\bar M + d\\,\\operatorname{diag}(\\sigma_{m})`
    hhT : (L, V, V) :math:`E[h_i h_i^T] = \\Sigma_{h_i} + \\mu_{h_i}\\mu_{h_i}^T`
    residual_sq : (L,) :math:`E\\|w_i - b - M h_i\\|^2`
    """

    alpha_mean: Array
    log_alpha_mean: Array
    lam_mean: Array
    log_lam_mean: Array
    MtM: Array
    hhT: Array
    residual_sq: Array


# --------------------------------------------------------------------------- covariance helpers
def _cov_trace(cov: FullCovariance | EigenCovariance) -> Array:
    if isinstance(cov, EigenCovariance):
        return jnp.sum(cov.variances, axis=-1)
    return jnp.trace(cov.matrices, axis1=-2, axis2=-1)


def _logdet_psd(matrices: Array) -> Array:
    chol = jnp.linalg.cholesky(matrices)
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)


def _cov_logdet(cov: FullCovariance | EigenCovariance) -> Array:
    if isinstance(cov, EigenCovariance):
        return jnp.sum(jnp.log(cov.variances), axis=-1)
    return _logdet_psd(cov.matrices)


def _gram_quadratic(gram: DemoGrams | SharedGram, x: Array) -> Array:
    """:math:`x_i^T \\Psi_i^T\\Psi_i x_i` for (L, d) x."""
    if isinstance(gram, SharedGram):
        return jnp.sum(gram.eigvals * (x @ gram.basis) ** 2, axis=-1)
    return jnp.einsum("id,ide,ie->i", x, gram.matrices, x)


def _gram_trace(gram: DemoGrams | SharedGram, cov: FullCovariance | EigenCovariance) -> Array:
    """:math:`\\operatorname{tr}(\\Psi_i^T\\Psi_i \\Sigma_{w_i})` (same basis on the fast path)."""
    if isinstance(gram, SharedGram) and isinstance(cov, EigenCovariance):
        return cov.variances @ gram.eigvals
    if isinstance(gram, DemoGrams) and isinstance(cov, FullCovariance):
        return jnp.einsum("ide,ied->i", gram.matrices, cov.matrices)
    raise TypeError(
        f"weight covariance {type(cov).__name__} does not match the data path {type(gram).__name__}"
    )


def w_covariance(state: CaviState) -> Array:
    """The weight covariances :math:`\\Sigma_{w_i}` as (L, d, d) matrices, whatever the storage."""
    cov = state.w_cov
    if isinstance(cov, EigenCovariance):
        return jnp.einsum("dj,ij,ej->ide", cov.basis, cov.variances, cov.basis)
    return cov.matrices


def _gamma_entropy(shape: Array, rate: Array) -> Array:
    return shape - jnp.log(rate) + gammaln(shape) + (1.0 - shape) * digamma(shape)


# --------------------------------------------------------------------------- expected statistics
def expected_stats(state: CaviState) -> ExpectedStats:
    """Shared moments of q (App. B.1 helper functions 3 and 4, with the factor d kept)."""
    d = state.M_mean.shape[0]
    alpha_mean = state.alpha_shape / state.alpha_rate
    log_alpha_mean = digamma(state.alpha_shape) - jnp.log(state.alpha_rate)
    lam_mean = state.lam_shape / state.lam_rate
    log_lam_mean = digamma(state.lam_shape) - jnp.log(state.lam_rate)
    MtM = state.M_mean.T @ state.M_mean + d * jnp.diag(state.M_var)
    hhT = state.h_cov + jnp.einsum("iu,iv->iuv", state.h_mean, state.h_mean)
    offset = state.w_mean - state.b_mean
    residual_sq = (
        jnp.sum(offset**2, axis=-1)
        + _cov_trace(state.w_cov)
        + d * state.b_var
        - 2.0 * jnp.einsum("id,dv,iv->i", offset, state.M_mean, state.h_mean)
        + jnp.einsum("uv,ivu->i", MtM, hhT)
    )
    return ExpectedStats(alpha_mean, log_alpha_mean, lam_mean, log_lam_mean, MtM, hhT, residual_sq)


# --------------------------------------------------------------------------- kernels (weighted)
def _w_posterior(
    data: CaviData, beta: Array, prior_precision: Array, prior_linear: Array
) -> tuple[Array, FullCovariance | EigenCovariance]:
    """q*(w_i) for a Gaussian prior with precision ``prior_precision[i] * I``.

    Precision :math:`\\beta\\Psi_i^T\\Psi_i + \\bar\\alpha_i I`; mean
    :math:`\\Sigma_{w_i}(\\beta\\Psi_i^T y_i + \\ell_i)`, where ``prior_linear``
    :math:`\\ell_i` is the prior's precision times its mean.  On the fast path the
    precision is diagonal in the shared eigenbasis for any per-demonstration
    ``prior_precision`` (mixture: :math:`\\sum_k r_{ik}\\bar\\alpha_k`).
    """
    linear = beta * data.psi_t_y + prior_linear
    gram = data.gram
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


def _h_posterior(
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


def _b_posterior(
    weights: Array, alpha_mean: Array, w_mean: Array, h_mean: Array, M_mean: Array, lambda0: Array
) -> tuple[Array, Array]:
    """q*(b): :math:`\\sigma_b = (\\bar\\alpha\\sum_i r_i + \\lambda_0)^{-1}`, :math:`\\mu_b = \\sigma_b\\bar\\alpha\\sum_i r_i(\\mu_{w_i} - \\bar M\\mu_{h_i})`."""
    var = 1.0 / (alpha_mean * jnp.sum(weights) + lambda0)
    mean = var * alpha_mean * (weights @ (w_mean - h_mean @ M_mean.T))
    return mean, var


def _M_posterior(
    weights: Array,
    alpha_mean: Array,
    hhT: Array,
    offset: Array,
    h_mean: Array,
    lam_mean: Array,
) -> tuple[Array, Array]:
    """Joint q*(m_1..m_V) from the weighted statistics S = sum r_i E[h_i h_i^T], R = sum r_i (mu_wi - mu_b) mu_hi^T.

    :math:`\\bar M(\\bar\\alpha S + \\operatorname{diag}\\bar\\lambda) = \\bar\\alpha R`,
    :math:`\\sigma_{m_v} = (\\bar\\alpha S_{vv} + \\bar\\lambda_v)^{-1}`.
    """
    S = jnp.einsum("i,iuv->uv", weights, hhT)
    R = jnp.einsum("i,id,iv->dv", weights, offset, h_mean)
    A = alpha_mean * S + jnp.diag(lam_mean)
    mean = jnp.linalg.solve(A, alpha_mean * R.T).T
    var = 1.0 / (alpha_mean * jnp.diagonal(S) + lam_mean)
    return mean, var


# --------------------------------------------------------------------------- public updates
@jax.jit
def update_w(state: CaviState, data: CaviData, hyper: HyperArrays) -> CaviState:
    """Update q(w_i) for all i (Sec. 4.1.1 / App. B.1; confirmed).

    .. math::

        \\Sigma_{w_i} = (\\beta\\Psi_i^T\\Psi_i + \\bar\\alpha I_d)^{-1}, \\qquad
        \\mu_{w_i} = \\Sigma_{w_i}(\\beta\\Psi_i^T y_i + \\bar\\alpha(\\mu_b + \\bar M\\mu_{h_i})).

    :math:`\\Psi_i` holds only the observed rows (mask).  On the fast path
    (:class:`SharedGram`) :math:`\\Sigma_{w_i} = U\\operatorname{diag}(1/(\\beta s + \\bar\\alpha))U^T`.
    """
    stats = expected_stats(state)
    L = state.w_mean.shape[0]
    prior_precision = jnp.full((L,), stats.alpha_mean)
    prior_linear = stats.alpha_mean * (state.b_mean + state.h_mean @ state.M_mean.T)
    mean, cov = _w_posterior(data, hyper.beta, prior_precision, prior_linear)
    return state._replace(w_mean=mean, w_cov=cov)


@jax.jit
def update_h(state: CaviState, data: CaviData, hyper: HyperArrays) -> CaviState:
    """Update q(h_i) for all i (Sec. 4.1.1 / App. B.1; confirmed, with the factor d).

    .. math::

        \\Sigma_{h_i} = (\\bar\\alpha(\\bar M^T\\bar M + d\\,\\Sigma_{M}) + \\gamma I_V)^{-1}, \\qquad
        \\mu_{h_i} = \\Sigma_{h_i}\\bar\\alpha\\bar M^T(\\mu_{w_i} - \\mu_b),

    with :math:`\\Sigma_M = \\operatorname{diag}(\\sigma_{m_1},\\dots,\\sigma_{m_V})`.
    The d comes from :math:`E[m_v^Tm_v] = \\|\\mu_{m_v}\\|^2 + d\\sigma_{m_v}`; App. C.1 drops it.
    """
    del data
    stats = expected_stats(state)
    weights = jnp.ones(state.h_mean.shape[0])
    mean, cov = _h_posterior(
        weights, stats.alpha_mean, stats.MtM, state.M_mean, state.w_mean - state.b_mean, hyper.gamma
    )
    return state._replace(h_mean=mean, h_cov=cov)


@jax.jit
def update_b(state: CaviState, data: CaviData, hyper: HyperArrays) -> CaviState:
    """Update q(b) (Sec. 4.1.1; App. B.1 corrected: sigma_b is an inverse).

    .. math::

        \\sigma_b = (L\\bar\\alpha + \\lambda^{[0]})^{-1}, \\qquad
        \\mu_b = \\sigma_b\\,\\bar\\alpha\\sum_i(\\mu_{w_i} - \\bar M\\mu_{h_i}).

    App. B.1 writes :math:`\\sigma_b = L\\bar\\alpha + \\lambda^{[0]}` (no inverse); Sec. 4.1.1 has it right.
    """
    del data
    stats = expected_stats(state)
    weights = jnp.ones(state.w_mean.shape[0])
    mean, var = _b_posterior(weights, stats.alpha_mean, state.w_mean, state.h_mean, state.M_mean, hyper.lambda0)
    return state._replace(b_mean=mean, b_var=var)


@jax.jit
def update_M(state: CaviState, data: CaviData, hyper: HyperArrays) -> CaviState:
    """Update q(m_1), ..., q(m_V) jointly (Sec. 4.1.1 / App. B.1 corrected).

    With :math:`S = \\sum_i E[h_i h_i^T]` and
    :math:`R = \\sum_i(\\mu_{w_i}-\\mu_b)\\mu_{h_i}^T`,

    .. math::

        \\sigma_{m_v} = \\Big(\\bar\\alpha\\sum_i E[h_{v,i}^2] + \\bar\\lambda_v\\Big)^{-1}, \\qquad
        \\bar M\\,(\\bar\\alpha S + \\operatorname{diag}(\\bar\\lambda)) = \\bar\\alpha R.

    Column v of the last equation reads
    :math:`\\mu_{m_v} = \\sigma_{m_v}\\bar\\alpha\\sum_i[\\mu_{h_{v,i}}(\\mu_{w_i}-\\mu_b) - \\sum_{u\\ne v}\\mu_{m_u}E[h_{u,i}h_{v,i}]]`:
    the thesis omits the coupling sum over :math:`u \\ne v`.  Solving the V columns
    jointly is the exact maximiser over all factors q(m_v) (the bound is a concave
    quadratic in :math:`\\bar M`, separable from the :math:`\\sigma_{m_v}`), i.e. the
    fixed point of the corrected column-wise updates.
    """
    del data, hyper
    stats = expected_stats(state)
    weights = jnp.ones(state.w_mean.shape[0])
    mean, var = _M_posterior(
        weights, stats.alpha_mean, stats.hhT, state.w_mean - state.b_mean, state.h_mean, stats.lam_mean
    )
    return state._replace(M_mean=mean, M_var=var)


@jax.jit
def update_lam(state: CaviState, data: CaviData, hyper: HyperArrays) -> CaviState:
    """Update q(lam_v) for all v (Sec. 4.1.1 / App. B.1; confirmed).

    .. math::

        \\bar c_v = c^{[0]} + \\frac d2, \\qquad
        \\bar d_v = d^{[0]} + \\frac12(\\mu_{m_v}^T\\mu_{m_v} + d\\,\\sigma_{m_v}).
    """
    del data
    d = state.M_mean.shape[0]
    shape = jnp.full_like(state.lam_shape, hyper.c0 + 0.5 * d)
    rate = hyper.d0 + 0.5 * (jnp.sum(state.M_mean**2, axis=0) + d * state.M_var)
    return state._replace(lam_shape=shape, lam_rate=rate)


@jax.jit
def update_alpha(state: CaviState, data: CaviData, hyper: HyperArrays) -> CaviState:
    """Update q(alpha) (Sec. 4.1.1 / App. B.1; confirmed).

    .. math::

        \\bar a = a^{[0]} + \\frac{dL}2, \\qquad
        \\bar b = b^{[0]} + \\frac12\\sum_i\\{C_i + \\operatorname{tr}\\Sigma_{w_i} + d\\sigma_b
        + \\mu_{h_i}^T d\\Sigma_M\\mu_{h_i} + \\operatorname{tr}[(\\bar M^T\\bar M + d\\Sigma_M)\\Sigma_{h_i}]\\},

    :math:`C_i = \\|\\mu_{w_i} - \\mu_b - \\bar M\\mu_{h_i}\\|^2`; the braces are
    :math:`E\\|w_i - b - Mh_i\\|^2` (``ExpectedStats.residual_sq``).
    """
    del data
    stats = expected_stats(state)
    d = state.w_mean.shape[1]
    weights = jnp.ones(state.w_mean.shape[0])
    shape = hyper.a0 + 0.5 * d * jnp.sum(weights)
    rate = hyper.b0 + 0.5 * (weights @ stats.residual_sq)
    return state._replace(alpha_shape=shape, alpha_rate=rate)


#: The sweep order of :func:`step` (the order of Sec. 4.1.1), name -> update.
UPDATES = {
    "w": update_w,
    "b": update_b,
    "M": update_M,
    "h": update_h,
    "lam": update_lam,
    "alpha": update_alpha,
}


# --------------------------------------------------------------------------- bound
@jax.jit
def elbo(state: CaviState, data: CaviData, hyper: HyperArrays) -> Array:
    """Closed-form evidence lower bound :math:`E_q[\\log p(y,\\theta) - \\log q(\\theta)]`, every constant kept.

    Corrects App. C.1, which drops the factor d of :math:`d\\Sigma_M` in
    :math:`E\\log p(w_i\\mid\\cdot)` and the term :math:`\\frac d2 E[\\log\\lambda_v]`
    of :math:`E\\log p(M)` (which changes during the updates), and the constants.
    """
    stats = expected_stats(state)
    L, d = state.w_mean.shape
    V = state.h_mean.shape[1]
    beta = hyper.beta
    # E log p(y_i | w_i): observed entries only
    quad = (
        data.y_sq
        - 2.0 * jnp.sum(state.w_mean * data.psi_t_y, axis=-1)
        + _gram_quadratic(data.gram, state.w_mean)
        + _gram_trace(data.gram, state.w_cov)
    )
    log_lik = jnp.sum(0.5 * data.num_obs * (jnp.log(beta) - _LOG_2PI) - 0.5 * beta * quad)
    # E log p(w_i | b, M, h_i, alpha)
    log_p_w = jnp.sum(
        0.5 * d * (stats.log_alpha_mean - _LOG_2PI) - 0.5 * stats.alpha_mean * stats.residual_sq
    )
    # E log p(h_i)
    h_sq = jnp.sum(state.h_mean**2, axis=-1) + jnp.trace(state.h_cov, axis1=-2, axis2=-1)
    log_p_h = jnp.sum(0.5 * V * (jnp.log(hyper.gamma) - _LOG_2PI) - 0.5 * hyper.gamma * h_sq)
    # E log p(b)
    log_p_b = 0.5 * d * (jnp.log(hyper.lambda0) - _LOG_2PI) - 0.5 * hyper.lambda0 * (
        jnp.sum(state.b_mean**2) + d * state.b_var
    )
    # E log p(M | lam)
    m_sq = jnp.sum(state.M_mean**2, axis=0) + d * state.M_var
    log_p_M = jnp.sum(0.5 * d * (stats.log_lam_mean - _LOG_2PI) - 0.5 * stats.lam_mean * m_sq)
    # E log p(alpha), E log p(lam)
    log_p_alpha = (
        hyper.a0 * jnp.log(hyper.b0) - gammaln(hyper.a0)
        + (hyper.a0 - 1.0) * stats.log_alpha_mean - hyper.b0 * stats.alpha_mean
    )
    log_p_lam = jnp.sum(
        hyper.c0 * jnp.log(hyper.d0) - gammaln(hyper.c0)
        + (hyper.c0 - 1.0) * stats.log_lam_mean - hyper.d0 * stats.lam_mean
    )
    # entropies
    entropy = (
        jnp.sum(0.5 * d * (1.0 + _LOG_2PI) + 0.5 * _cov_logdet(state.w_cov))
        + jnp.sum(0.5 * V * (1.0 + _LOG_2PI) + 0.5 * _logdet_psd(state.h_cov))
        + 0.5 * d * (1.0 + _LOG_2PI + jnp.log(state.b_var))
        + jnp.sum(0.5 * d * (1.0 + _LOG_2PI + jnp.log(state.M_var)))
        + _gamma_entropy(state.alpha_shape, state.alpha_rate)
        + jnp.sum(_gamma_entropy(state.lam_shape, state.lam_rate))
    )
    return log_lik + log_p_w + log_p_h + log_p_b + log_p_M + log_p_alpha + log_p_lam + entropy


# --------------------------------------------------------------------------- loop
@jax.jit
def step(state: CaviState, data: CaviData, hyper: HyperArrays) -> tuple[CaviState, CaviInfo]:
    """One sweep over all factors in the order of :data:`UPDATES`; returns the new state and its ELBO."""
    for update in UPDATES.values():
        state = update(state, data, hyper)
    return state, CaviInfo(elbo(state, data, hyper))


class RunResult(NamedTuple):
    """Output of :func:`run`.

    Attributes
    ----------
    state : final state
    elbo_trace : (max_iter,) ELBO after each sweep, NaN after the last one
    iterations : () int32 number of sweeps run
    converged : () bool, relative ELBO change fell below ``tol``
    """

    state: CaviState
    elbo_trace: Array
    iterations: Array
    converged: Array


def _iterate(
    state: CaviState,
    data: CaviData,
    hyper: HyperArrays,
    tol: Array,
    limit: Array,
    elbo_previous: Array,
    buffer: int,
    step_fn=None,
) -> RunResult:
    """Sweep until the relative ELBO change is below ``tol``, at most ``limit`` (<= ``buffer``) times.

    ``step_fn(state, data, hyper) -> (state, info)`` is the sweep (static; default :func:`step`);
    the extensions of :mod:`lmpromp_ppl.inference.cavi_mixture` pass theirs.
    """
    sweep = step if step_fn is None else step_fn

    def cond(carry):
        _, iteration, previous, _, converged = carry
        return (iteration < limit) & ~converged & ~jnp.isnan(previous)

    def body(carry):
        state, iteration, previous, trace, _ = carry
        state, info = sweep(state, data, hyper)
        converged = jnp.abs(info.elbo - previous) <= tol * jnp.abs(info.elbo)
        return state, iteration + 1, info.elbo, trace.at[iteration].set(info.elbo), converged

    carry = (
        state,
        jnp.zeros((), jnp.int32),
        jnp.asarray(elbo_previous, jnp.float64),
        jnp.full((buffer,), jnp.nan),
        jnp.zeros((), jnp.bool_),
    )
    state, iteration, _, trace, converged = jax.lax.while_loop(cond, body, carry)
    return RunResult(state, trace, iteration, converged)


_iterate_jit = jax.jit(_iterate, static_argnames=("buffer", "step_fn"))


def run(
    state: CaviState, data: CaviData, hyper: HyperArrays, tol: float | Array, max_iter: int
) -> RunResult:
    """Iterate :func:`step` in a compiled ``lax.while_loop``.

    Stops when :math:`|\\Delta\\mathcal L| \\le` ``tol`` :math:`|\\mathcal L|`, when the ELBO
    is NaN, or after ``max_iter`` sweeps (``max_iter`` is static: it sizes the trace).
    The loop is compiled ahead of time once per argument shapes and ``max_iter``
    and shared with :func:`fit_cavi`; call ``run`` outside ``jax.jit``.
    """
    args = (
        state,
        data,
        hyper,
        jnp.asarray(tol, jnp.float64),
        jnp.asarray(max_iter, jnp.int32),
        jnp.asarray(-jnp.inf),
    )
    compiled, _ = _compiled_iterate(args, int(max_iter))
    return compiled(*args)


# --------------------------------------------------------------------------- fitting
class CaviFit(NamedTuple):
    """Result of :func:`fit_cavi`.

    Attributes
    ----------
    state : best state over the restarts
    elbo : its final ELBO
    elbo_trace : (iterations,) ELBO after each sweep of the best restart
    iterations : sweeps run by the best restart
    converged : whether the best restart met the tolerance
    seconds : wall time of all restarts, excluding compilation
    compile_seconds : ahead-of-time compilation time (0 when already compiled in this process)
    restart_elbos : final ELBO of every restart, in order
    """

    state: CaviState
    elbo: float
    elbo_trace: np.ndarray
    iterations: int
    converged: bool
    seconds: float
    compile_seconds: float
    restart_elbos: list[float]


_COMPILED: dict = {}


def _compiled_iterate(args: tuple, buffer: int, step_fn=None):
    """Ahead-of-time compiled :func:`_iterate` for these argument shapes; (function, compile seconds)."""
    leaves, treedef = jax.tree.flatten(args)
    key = (
        treedef,
        tuple((np.shape(x), jnp.asarray(x).dtype, getattr(x, "weak_type", False)) for x in leaves),
        buffer,
        step_fn,
    )
    if key in _COMPILED:
        return _COMPILED[key], 0.0
    start = time.perf_counter()
    compiled = _iterate_jit.lower(*args, buffer=buffer, step_fn=step_fn).compile()
    seconds = time.perf_counter() - start
    _COMPILED[key] = compiled
    return compiled, seconds


def _run_one(
    state: CaviState,
    data: CaviData,
    hyper: HyperArrays,
    tol: float,
    max_iter: int,
    progress: bool,
    description: str,
    step_fn=None,
) -> tuple[RunResult, np.ndarray, float, float]:
    """Run one restart, in chunks when showing progress; (result, trace, seconds, compile seconds).

    ``step_fn``: the sweep (default :func:`step`), see :func:`_iterate`.
    """
    progress = show_progress_bars(progress)
    chunk = min(max_iter, 50) if progress else max_iter
    tol_arr = jnp.asarray(tol, jnp.float64)
    previous = jnp.asarray(-jnp.inf)
    probe = (state, data, hyper, tol_arr, jnp.asarray(chunk, jnp.int32), previous)
    compiled, compile_seconds = _compiled_iterate(probe, chunk, step_fn)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=max_iter, desc=description, leave=False)
    traces, done, seconds = [], 0, 0.0
    try:
        while True:
            limit = jnp.asarray(min(chunk, max_iter - done), jnp.int32)
            start = time.perf_counter()
            result = compiled(state, data, hyper, tol_arr, limit, previous)
            jax.block_until_ready(result)
            seconds += time.perf_counter() - start
            n = int(result.iterations)
            traces.append(np.asarray(result.elbo_trace[:n]))
            done += n
            state = result.state
            if bar is not None:
                bar.update(n)
                if n:
                    bar.set_postfix(elbo=f"{float(traces[-1][-1]):.6g}")
            if bool(result.converged) or done >= max_iter or n == 0 or np.isnan(traces[-1][-1]):
                break
            previous = result.elbo_trace[n - 1]
    finally:
        if bar is not None:
            bar.close()
    trace = np.concatenate(traces)
    return result._replace(iterations=jnp.asarray(done, jnp.int32)), trace, seconds, compile_seconds


def fit_cavi(
    data: ModelData,
    hyper: Hyperparameters,
    key: Array,
    *,
    tol: float = 1e-8,
    max_iter: int = 2000,
    num_restarts: int = 1,
    progress: bool = False,
    shared_psi: bool | None = None,
    family: str = "columnwise",
) -> CaviFit:
    """Fit the single-type LMProMP by CAVI, keeping the best of ``num_restarts`` starts.

    The first start is the thesis's initialisation (ridge regression + PCA,
    :func:`lmpromp_ppl.inference.init.init_state`); further starts perturb it
    with keys split from ``key``.  With the thesis's family and a fixed beta the
    result holds a :class:`CaviState`; with ``family="rowwise"`` or
    ``hyper.learn_beta`` the fit runs in
    :func:`lmpromp_ppl.inference.cavi_mixture.fit_single_extended` and holds a
    K = 1 :class:`~lmpromp_ppl.inference.cavi_mixture.MixtureState` (the
    functions below accept both).

    Parameters
    ----------
    data : padded model inputs
    hyper : hyperparameters (``latent_dim`` is V; single component, fixed beta)
    key : jax PRNG key for the restarts
    tol : stop when the relative ELBO change is below ``tol``
    max_iter : maximum number of sweeps per start (warns with ConvergenceWarning when hit)
    num_restarts : number of starts
    progress : show a progress bar (tqdm) updated every 50 sweeps, when stderr is a terminal
    shared_psi : see :func:`prepare_cavi_data`
    family : ``"columnwise"`` (the thesis's isotropic q(m_v), default) or
        ``"rowwise"`` (rows of M share one V x V covariance), see
        :data:`lmpromp_ppl.inference.cavi_mixture.FAMILIES`

    Returns
    -------
    CaviFit
    """
    from lmpromp_ppl.inference.init import init_state  # init imports this module

    if not isinstance(hyper, Hyperparameters):
        raise LmprompError(f"hyper must be a Hyperparameters, got {type(hyper).__name__}")
    if hyper.num_components != 1:
        raise LmprompError(
            f"the single-type CAVI engine needs num_components=1, got {hyper.num_components}"
        )
    _check_family(family)
    if family != "columnwise" or hyper.learn_beta:
        from lmpromp_ppl.inference.cavi_mixture import fit_single_extended

        return fit_single_extended(
            data, hyper, key, tol=tol, max_iter=max_iter, num_restarts=num_restarts,
            progress=progress, shared_psi=shared_psi, family=family,
        )
    _check_options(tol, max_iter, num_restarts)
    _check_model_data(data)
    hyper.validate_for(data.num_weights, data.num_demos)
    cavi_data = prepare_cavi_data(data, shared_psi)
    hyper_arr = hyper_arrays(hyper)
    keys = jax.random.split(key, num_restarts)
    starts = (init_state(cavi_data, hyper, key=None if r == 0 else keys[r]) for r in range(num_restarts))
    return _best_of_restarts(starts, cavi_data, hyper_arr, tol, max_iter, progress, "CAVI")


def _check_options(tol, max_iter, num_restarts) -> None:
    """Validate the loop options shared by every CAVI engine."""
    if not (isinstance(tol, (int, float)) and not isinstance(tol, bool) and tol > 0 and math.isfinite(tol)):
        raise LmprompError(f"tol must be a positive number, got {tol!r}")
    for name, value in (("max_iter", max_iter), ("num_restarts", num_restarts)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise LmprompError(f"{name} must be an integer >= 1, got {value!r}")


def _best_of_restarts(starts, cavi_data, hyper_arr, tol, max_iter, progress, label, step_fn=None) -> CaviFit:
    """Run every start with the compiled loop and keep the best final ELBO (warns at ``max_iter``).

    ``step_fn`` is the sweep (default :func:`step`; the mixture engine passes its own).
    """
    step_fn = step if step_fn is None else step_fn
    best, restart_elbos, seconds, compile_seconds = None, [], 0.0, 0.0
    starts = list(starts) if not hasattr(starts, "__next__") else starts
    for r, start in enumerate(starts):
        result, trace, run_seconds, run_compile = _run_one(
            start, cavi_data, hyper_arr, float(tol), int(max_iter), progress,
            f"{label} restart {r + 1}", step_fn=step_fn,
        )
        seconds += run_seconds
        compile_seconds += run_compile
        final = check_restart_bound(float(trace[-1]), r)
        restart_elbos.append(final)
        if best is None or final > best[0]:
            best = (final, result, trace)
    final, result, trace = best
    return best_fit(result, final, trace, int(result.iterations), seconds, compile_seconds, restart_elbos,
                    tol=tol, max_iter=max_iter)


def check_restart_bound(final: float, restart: int) -> float:
    """The final bound of a restart; a non-finite one is a typed error."""
    if not math.isfinite(final):
        raise LmprompError(
            f"CAVI diverged (ELBO {final}) in restart {restart + 1}; check beta and the data scaling"
        )
    return final


def best_fit(result, final, trace, iterations, seconds, compile_seconds, restart_elbos, *, tol, max_iter) -> CaviFit:
    """The :class:`CaviFit` of the best restart; warns when it stopped at ``max_iter``."""
    if not bool(result.converged):
        warnings.warn(
            f"CAVI stopped at max_iter={max_iter} before the relative ELBO change fell below tol={tol}",
            ConvergenceWarning,
            stacklevel=5,
        )
    return CaviFit(
        state=result.state,
        elbo=final,
        elbo_trace=trace,
        iterations=iterations,
        converged=bool(result.converged),
        seconds=seconds,
        compile_seconds=compile_seconds,
        restart_elbos=restart_elbos,
    )


# --------------------------------------------------------------------------- posterior summaries
@partial(jax.jit, static_argnames="num_draws")
def _gamma_draws(key: Array, shapes: Array, num_draws: int) -> Array:
    """(num_draws, K) standard Gamma draws; one compiled sampler for alpha and lam (costly to compile)."""
    return jax.random.gamma(key, shapes, (num_draws,) + shapes.shape)


def _extension(state) -> bool:
    """True for a :class:`~lmpromp_ppl.inference.cavi_mixture.MixtureState` (mixture or extended single type)."""
    return not isinstance(state, CaviState)


def sample_q(key: Array, state: CaviState, num_draws: int) -> dict[str, Array]:
    """Independent draws from q with a leading draw axis.

    Returns a dict with ``b`` (n, d), ``M`` (n, d, V), ``h`` (n, L, V),
    ``w`` (n, L, d), ``alpha`` (n,), ``lam`` (n, V).  For a
    :class:`~lmpromp_ppl.inference.cavi_mixture.MixtureState` see
    :func:`lmpromp_ppl.inference.cavi_mixture.sample_q` (mixture sites, ``beta``).
    """
    if _extension(state):
        return _mixture.sample_q(key, state, num_draws)
    L, d = state.w_mean.shape
    V = state.h_mean.shape[1]
    k_w, k_h, k_b, k_M, k_g = jax.random.split(key, 5)
    cov = state.w_cov
    z_w = jax.random.normal(k_w, (num_draws, L, d))
    if isinstance(cov, EigenCovariance):
        w = state.w_mean + (z_w * jnp.sqrt(cov.variances)) @ cov.basis.T
    else:
        w = state.w_mean + jnp.einsum("ide,nie->nid", jnp.linalg.cholesky(cov.matrices), z_w)
    z_h = jax.random.normal(k_h, (num_draws, L, V))
    h = state.h_mean + jnp.einsum("iuv,niv->niu", jnp.linalg.cholesky(state.h_cov), z_h)
    b = state.b_mean + jnp.sqrt(state.b_var) * jax.random.normal(k_b, (num_draws, d))
    M = state.M_mean + jnp.sqrt(state.M_var) * jax.random.normal(k_M, (num_draws, d, V))
    shapes = jnp.concatenate([state.alpha_shape[None], state.lam_shape])
    rates = jnp.concatenate([state.alpha_rate[None], state.lam_rate])
    precisions = _gamma_draws(k_g, shapes, num_draws) / rates
    return {"b": b, "M": M, "h": h, "w": w, "alpha": precisions[:, 0], "lam": precisions[:, 1:]}


def point_estimate(state: CaviState) -> dict[str, Array]:
    """Posterior means of q: ``b``, ``M``, ``alpha``, ``lam``, ``h``, ``w`` (for plug-in prediction).

    For a :class:`~lmpromp_ppl.inference.cavi_mixture.MixtureState` see
    :func:`lmpromp_ppl.inference.cavi_mixture.point_estimate`.
    """
    if _extension(state):
        return _mixture.point_estimate(state)
    return {
        "b": state.b_mean,
        "M": state.M_mean,
        "alpha": state.alpha_shape / state.alpha_rate,
        "lam": state.lam_shape / state.lam_rate,
        "h": state.h_mean,
        "w": state.w_mean,
    }


def active_latent_dims(state: CaviState, threshold: float = 1e-3) -> list[int] | list[list[int]]:
    r"""Latent dimensions that ARD left switched on.

    Column v is active when it passes both

    * the relative rule :math:`1/E[\lambda_v] > \text{threshold}\cdot\max_u 1/E[\lambda_u]`, and
    * the absolute rule :math:`\lVert E[m_v] \rVert^2 > \operatorname{tr}\operatorname{Cov}_q(m_v)`:
      the column's mean stands out of its own posterior spread, i.e. q says the
      column is not zero.

    The relative rule alone cannot say "none": when the data switch every column
    off, all :math:`E[\lambda_v]` sit near the same large value (near
    :math:`c_0/d_0` under the thesis prior) and each passes.  A switched-off
    column has :math:`E[m_v] \approx 0` and a posterior spread of the order of
    its prior's, so the absolute rule fails for it whatever the units of the
    data; a column that explains data has a mean far outside its spread.

    A list of indices; for a mixture one list per component
    (:func:`lmpromp_ppl.inference.cavi_mixture.active_latent_dims`).
    """
    if _extension(state):
        return _mixture.active_latent_dims(state, threshold)
    inverse = np.asarray(state.lam_rate / state.lam_shape)
    mean_sq = np.sum(np.asarray(state.M_mean) ** 2, axis=0)
    spread = state.M_mean.shape[0] * np.asarray(state.M_var)
    return [int(v) for v in np.flatnonzero((inverse > threshold * inverse.max()) & (mean_sq > spread))]


def _check_family(family: str) -> None:
    if family not in _mixture.FAMILIES:
        raise LmprompError(f"unknown family {family!r} for q(M); choose from {list(_mixture.FAMILIES)}")


# The extensions (mixture, row-wise q(M), learned beta) build on the kernels above.
from lmpromp_ppl.inference import cavi_mixture as _mixture  # noqa: E402
from lmpromp_ppl.inference.cavi_mixture import (  # noqa: E402
    FAMILIES,
    MixtureState,
    active_components,
    fit_cavi_mixture,
)

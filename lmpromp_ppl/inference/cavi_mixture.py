r"""CAVI extensions: the mixture of LMProMPs, a row-wise structured q(M), and a learned beta.

Model (thesis Sec. 4.2, eq. 4.8, with the Dirichlet prior of
:func:`lmpromp_ppl.models.mixture.mixture_model`; precisions, Gamma shape/rate):

.. math::

    \pi &\sim \mathrm{Dir}(\kappa_0 1_K), \quad z_i \sim \mathrm{Cat}(\pi), \quad
    b_k \sim \mathcal N(0, \lambda_0^{-1} I_d), \quad
    \lambda_{kv} \sim \Gamma(c_0, d_0), \quad
    m_{kv} \sim \mathcal N(0, \lambda_{kv}^{-1} I_d), \quad
    \alpha_k \sim \Gamma(a_0, b_0), \\
    h_{ik} &\sim \mathcal N(0, \gamma^{-1} I_V), \quad
    w_i \mid z_i = k \sim \mathcal N(b_k + M_k h_{ik}, \alpha_k^{-1} I_d), \quad
    y_i \sim \mathcal N(\Psi_i w_i, \beta^{-1} I), \quad
    \beta \sim \Gamma(\beta_{a0}, \beta_{b0})\ \text{(when learned)}.

Variational family (Sec. 4.2.1): :math:`q(z_i) = \mathrm{Cat}(r_i)`,
:math:`q(\pi) = \mathrm{Dir}(\hat\kappa)`, per component :math:`q(b_k)`,
:math:`q(M_k)`, :math:`q(\alpha_k)`, :math:`q(\lambda_{kv})`, :math:`q(h_{ik})`
for every i and k, shared :math:`q(w_i)`, and :math:`q(\beta) = \Gamma(\hat a_\beta, \hat b_\beta)`
when beta is learned.  Two families for M (:data:`FAMILIES`):

* ``"columnwise"`` (thesis eq. 4.3, the default):
  :math:`q(m_{kv}) = \mathcal N(\mu_{kv}, \sigma_{kv} I_d)`; ``M_var`` is (K, V);
* ``"rowwise"`` (variational Bayesian PCA): the rows of :math:`M_k` share one full
  covariance, :math:`q(M_k) = \prod_j \mathcal N(m_{k,j\cdot} \mid \mu_{k,j\cdot}, \Sigma_{M_k})`;
  ``M_var`` is (K, V, V).  The column-wise family is the special case of a
  diagonal :math:`\Sigma_{M_k}`, and the row-wise family contains the
  unconstrained optimum of q(M) given the other factors.

The single-type model is the case K = 1 with ``resp`` and ``pi_conc`` set to
``None`` (its bound is the mixture's with K = 1: the terms in pi and z vanish).
:func:`lmpromp_ppl.inference.cavi.fit_cavi` uses this engine for the single type
when ``family="rowwise"`` or ``hyper.learn_beta``.

Removed components (Sec. 4.2.1) are kept in the arrays and switched off by the
boolean ``active`` mask: they get :math:`r_{ik} = 0`, their factors are frozen,
and their terms are left out of the bound.  This is the bound of the declared
K-component model for the family in which q(z_i = k) = 0 and the parameters of a
removed component are distributed as under their prior (their KL term is then 0);
``q(pi)`` keeps all K components.  Derivations and thesis errata: ``docs/derivation.md``.
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.scipy.linalg import cho_solve
from jax.scipy.special import digamma, gammaln

from lmpromp_ppl.data.core import ModelData
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference.cavi import (
    CaviData,
    CaviFit,
    CaviInfo,
    CaviState,
    EigenCovariance,
    FullCovariance,
    _b_posterior,
    _check_model_data,
    _cov_logdet,
    _cov_trace,
    _gamma_draws,
    _gamma_entropy,
    _gram_quadratic,
    _gram_trace,
    _h_posterior,
    _logdet_psd,
    _M_posterior,
    _best_of_restarts,
    _check_options,
    _w_posterior,
    prepare_cavi_data,
)
from lmpromp_ppl.models.hyper import Hyperparameters

__all__ = [
    "FAMILIES",
    "MixtureHyper",
    "mixture_hyper_arrays",
    "MixtureState",
    "MixtureStats",
    "mixture_stats",
    "family_of",
    "lift_state",
    "update_w",
    "update_b",
    "update_M",
    "update_h",
    "update_lam",
    "update_alpha",
    "update_beta",
    "update_z",
    "update_pi",
    "prune",
    "updates_for",
    "elbo",
    "step",
    "fit_cavi_mixture",
    "fit_single_extended",
    "responsibilities",
    "sample_q",
    "point_estimate",
    "active_components",
    "active_latent_dims",
]

_LOG_2PI = math.log(2.0 * math.pi)

#: Names of the families of q(M): the thesis's column-wise isotropic one (default) and the row-wise one.
FAMILIES = ("columnwise", "rowwise")


# --------------------------------------------------------------------------- inputs
class MixtureHyper(NamedTuple):
    """Hyperparameters (and the pruning threshold) as float64 scalars shared by compiled code.

    Attributes
    ----------
    beta : fixed noise precision (ignored when the state has ``q(beta)``)
    lambda0, gamma, a0, b0, c0, d0 : as :class:`lmpromp_ppl.inference.cavi.HyperArrays`
    kappa0 : Dirichlet concentration of :math:`\\pi`
    beta_a0, beta_b0 : Gamma shape/rate of :math:`\\beta` when learned
    prune_threshold : a component is removed when its expected number of
        demonstrations :math:`N_k = \\sum_i r_{ik}` falls below this (an algorithm
        setting, not part of the model; Sec. 4.2.1)
    """

    beta: Array
    lambda0: Array
    gamma: Array
    a0: Array
    b0: Array
    c0: Array
    d0: Array
    kappa0: Array
    beta_a0: Array
    beta_b0: Array
    prune_threshold: Array


def mixture_hyper_arrays(hyper: Hyperparameters, prune_threshold: float = 0.5) -> MixtureHyper:
    """Build :class:`MixtureHyper` from a :class:`Hyperparameters`."""
    values = [getattr(hyper, name) for name in MixtureHyper._fields[:-1]] + [prune_threshold]
    return MixtureHyper(*(jnp.asarray(v, jnp.float64) for v in values))


# --------------------------------------------------------------------------- state
class MixtureState(NamedTuple):
    """Parameters of every factor of q (Sec. 4.2.1, with the extensions of this module).

    Attributes
    ----------
    w_mean : (L, d) :math:`\\mu_{w_i}`
    w_cov : :class:`FullCovariance` or :class:`EigenCovariance`, :math:`\\Sigma_{w_i}`
    h_mean : (L, K, V) :math:`\\mu_{h_{ik}}`
    h_cov : (L, K, V, V) :math:`\\Sigma_{h_{ik}}`
    b_mean : (K, d) :math:`\\mu_{b_k}`
    b_var : (K,) :math:`\\sigma_{b_k}` (variances)
    M_mean : (K, d, V) :math:`\\bar M_k`
    M_var : (K, V) column variances :math:`\\sigma_{kv}` (``"columnwise"``) or
        (K, V, V) the shared row covariance :math:`\\Sigma_{M_k}` (``"rowwise"``)
    alpha_shape, alpha_rate : (K,) :math:`\\bar a_k, \\bar b_k`
    lam_shape, lam_rate : (K, V) :math:`\\bar c_{kv}, \\bar d_{kv}`
    resp : (L, K) responsibilities :math:`r_{ik} = q(z_i = k)`; ``None`` for the single type
    pi_conc : (K,) Dirichlet concentration :math:`\\hat\\kappa` of q(pi); ``None`` for the single type
    beta_shape, beta_rate : () Gamma q(beta), used when ``beta_learned``
    beta_learned : () bool, beta has the factor q(beta) (else the fixed ``hyper.beta``)
    active : (K,) bool, False for removed components

    Whether beta is learned is an array (not the pytree structure) so that
    fixed and learned beta share compiled code.
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
    resp: Array | None
    pi_conc: Array | None
    beta_shape: Array
    beta_rate: Array
    beta_learned: Array
    active: Array


def family_of(state: MixtureState) -> str:
    """``"rowwise"`` when ``M_var`` holds (V, V) covariances, else ``"columnwise"``."""
    return "rowwise" if state.M_var.ndim == 3 else "columnwise"


def lift_state(
    state: CaviState, family: str = "columnwise", beta: tuple[float, float] | None = None
) -> MixtureState:
    """The single-type :class:`CaviState` as a K = 1 :class:`MixtureState`.

    ``family="rowwise"`` turns the column variances into a diagonal row
    covariance (the same distribution); ``beta=(shape, rate)`` adds q(beta).
    """
    shape, rate = (1.0, 1.0) if beta is None else beta
    _check_family(family)
    M_var = state.M_var[None]
    if family == "rowwise":
        M_var = jax.vmap(jnp.diag)(M_var)
    f64 = lambda x: jnp.asarray(x, jnp.float64)  # noqa: E731
    return MixtureState(
        w_mean=state.w_mean,
        w_cov=state.w_cov,
        h_mean=state.h_mean[:, None],
        h_cov=state.h_cov[:, None],
        b_mean=state.b_mean[None],
        b_var=f64(state.b_var)[None],
        M_mean=state.M_mean[None],
        M_var=M_var,
        alpha_shape=f64(state.alpha_shape)[None],
        alpha_rate=f64(state.alpha_rate)[None],
        lam_shape=state.lam_shape[None],
        lam_rate=state.lam_rate[None],
        resp=None,
        pi_conc=None,
        beta_shape=f64(shape),
        beta_rate=f64(rate),
        beta_learned=jnp.asarray(beta is not None),
        active=jnp.ones((1,), jnp.bool_),
    )


def _check_family(family: str) -> None:
    if family not in FAMILIES:
        raise LmprompError(f"unknown family {family!r} for q(M); choose from {list(FAMILIES)}")


# --------------------------------------------------------------------------- expected statistics
class MixtureStats(NamedTuple):
    """Moments of q shared by the updates and the bound.

    Attributes
    ----------
    resp : (L, K) responsibilities, 0 for removed components (ones (L, 1) for the single type)
    alpha_mean, log_alpha_mean : (K,)
    lam_mean, log_lam_mean : (K, V)
    M_col_var : (K, V) :math:`d^{-1}E\\|m_{kv} - \\mu_{kv}\\|^2` (the diagonal of the row covariance)
    MtM : (K, V, V) :math:`E[M_k^TM_k] = \\bar M_k^T\\bar M_k + d\\Sigma_{M_k}`
    hhT : (L, K, V, V) :math:`E[h_{ik}h_{ik}^T]`
    residual_sq : (L, K) :math:`E\\|w_i - b_k - M_kh_{ik}\\|^2`
    beta_mean, log_beta_mean : () :math:`E[\\beta]`, :math:`E[\\log\\beta]` (the fixed value when not learned)
    log_pi_mean : (K,) :math:`E[\\log\\pi_k] = \\psi(\\hat\\kappa_k) - \\psi(\\sum_j\\hat\\kappa_j)`, or None
    """

    resp: Array
    alpha_mean: Array
    log_alpha_mean: Array
    lam_mean: Array
    log_lam_mean: Array
    M_col_var: Array
    MtM: Array
    hhT: Array
    residual_sq: Array
    beta_mean: Array
    log_beta_mean: Array
    log_pi_mean: Array | None


def mixture_stats(state: MixtureState, hyper: MixtureHyper) -> MixtureStats:
    """Moments of q (App. B.1 helpers with the factor d; App. B.2 per component)."""
    L, d = state.w_mean.shape
    K = state.M_mean.shape[0]
    if state.M_var.ndim == 3:
        M_col_var = jnp.diagonal(state.M_var, axis1=-2, axis2=-1)
        M_cov = state.M_var
    else:
        M_col_var = state.M_var
        M_cov = jax.vmap(jnp.diag)(state.M_var)
    MtM = jnp.einsum("kdu,kdv->kuv", state.M_mean, state.M_mean) + d * M_cov
    hhT = state.h_cov + jnp.einsum("iku,ikv->ikuv", state.h_mean, state.h_mean)
    offset = state.w_mean[:, None, :] - state.b_mean[None]
    residual_sq = (
        jnp.sum(offset**2, axis=-1)
        + _cov_trace(state.w_cov)[:, None]
        + d * state.b_var[None]
        - 2.0 * jnp.einsum("ikd,kdv,ikv->ik", offset, state.M_mean, state.h_mean)
        + jnp.einsum("kuv,ikvu->ik", MtM, hhT)
    )
    if state.resp is None:
        resp = jnp.ones((L, K))
        log_pi_mean = None
    else:
        resp = jnp.where(state.active[None], state.resp, 0.0)
        log_pi_mean = digamma(state.pi_conc) - digamma(jnp.sum(state.pi_conc))
    learned = state.beta_learned
    beta_mean = jnp.where(learned, state.beta_shape / state.beta_rate, hyper.beta)
    log_beta_mean = jnp.where(
        learned, digamma(state.beta_shape) - jnp.log(state.beta_rate), jnp.log(hyper.beta)
    )
    return MixtureStats(
        resp=resp,
        alpha_mean=state.alpha_shape / state.alpha_rate,
        log_alpha_mean=digamma(state.alpha_shape) - jnp.log(state.alpha_rate),
        lam_mean=state.lam_shape / state.lam_rate,
        log_lam_mean=digamma(state.lam_shape) - jnp.log(state.lam_rate),
        M_col_var=M_col_var,
        MtM=MtM,
        hhT=hhT,
        residual_sq=residual_sq,
        beta_mean=beta_mean,
        log_beta_mean=log_beta_mean,
        log_pi_mean=log_pi_mean,
    )


def _keep_active(active: Array, new: Array, old: Array) -> Array:
    """``new`` for active components (leading K axis), ``old`` (frozen) for removed ones."""
    mask = active.reshape(active.shape + (1,) * (new.ndim - 1))
    return jnp.where(mask, new, old)


# --------------------------------------------------------------------------- updates
@jax.jit
def update_w(state: MixtureState, data: CaviData, hyper: MixtureHyper) -> MixtureState:
    """Update q(w_i) (Sec. 4.2.1 / App. B.2; confirmed), with :math:`E[\\beta]` for a learned beta.

    .. math::

        \\Sigma_{w_i} = \\Big(E[\\beta]\\Psi_i^T\\Psi_i + \\sum_k r_{ik}\\bar\\alpha_k I_d\\Big)^{-1},\\quad
        \\mu_{w_i} = \\Sigma_{w_i}\\Big(E[\\beta]\\Psi_i^Ty_i + \\sum_k r_{ik}\\bar\\alpha_k(\\mu_{b_k} + \\bar M_k\\mu_{h_{ik}})\\Big).

    The prior precision is a scalar per demonstration, so the shared-Psi fast path holds.
    """
    st = mixture_stats(state, hyper)
    weights = st.resp * st.alpha_mean[None]
    means = state.b_mean[None] + jnp.einsum("kdv,ikv->ikd", state.M_mean, state.h_mean)
    mean, cov = _w_posterior(
        data, st.beta_mean, jnp.sum(weights, axis=1), jnp.einsum("ik,ikd->id", weights, means)
    )
    return state._replace(w_mean=mean, w_cov=cov)


@jax.jit
def update_b(state: MixtureState, data: CaviData, hyper: MixtureHyper) -> MixtureState:
    """Update q(b_k) for every active k (Sec. 4.2.1 / App. B.2; confirmed).

    .. math::

        \\sigma_{b_k} = \\Big(\\bar\\alpha_k\\sum_i r_{ik} + \\lambda_0\\Big)^{-1},\\quad
        \\mu_{b_k} = \\sigma_{b_k}\\bar\\alpha_k\\sum_i r_{ik}(\\mu_{w_i} - \\bar M_k\\mu_{h_{ik}}).
    """
    del data
    st = mixture_stats(state, hyper)
    mean, var = jax.vmap(_b_posterior, in_axes=(1, 0, None, 1, 0, None))(
        st.resp, st.alpha_mean, state.w_mean, state.h_mean, state.M_mean, hyper.lambda0
    )
    return state._replace(
        b_mean=_keep_active(state.active, mean, state.b_mean),
        b_var=_keep_active(state.active, var, state.b_var),
    )


def _M_rows_posterior(
    weights: Array, alpha_mean: Array, hhT: Array, offset: Array, h_mean: Array, lam_mean: Array
) -> tuple[Array, Array]:
    """Row-wise q*(M): rows :math:`\\mathcal N(\\mu_{j\\cdot}, A^{-1})`, :math:`A = \\bar\\alpha S + \\operatorname{diag}\\bar\\lambda`, :math:`\\bar M = \\bar\\alpha R A^{-1}`."""
    S = jnp.einsum("i,iuv->uv", weights, hhT)
    R = jnp.einsum("i,id,iv->dv", weights, offset, h_mean)
    V = S.shape[0]
    A = alpha_mean * S + jnp.diag(lam_mean)
    chol = jnp.linalg.cholesky(A)
    cov = cho_solve((chol, True), jnp.eye(V))
    cov = 0.5 * (cov + cov.T)
    mean = cho_solve((chol, True), alpha_mean * R.T).T
    return mean, cov


@jax.jit
def update_M(state: MixtureState, data: CaviData, hyper: MixtureHyper) -> MixtureState:
    """Update q(M_k) for every active k, in the state's family (App. B.2 corrected).

    With :math:`S_k = \\sum_i r_{ik}E[h_{ik}h_{ik}^T]`,
    :math:`R_k = \\sum_i r_{ik}(\\mu_{w_i} - \\mu_{b_k})\\mu_{h_{ik}}^T` and
    :math:`A_k = \\bar\\alpha_kS_k + \\operatorname{diag}(\\bar\\lambda_k)`, both families have
    :math:`\\bar M_kA_k = \\bar\\alpha_kR_k` (B.2, like B.1, omits the coupling between
    columns); column-wise :math:`\\sigma_{kv} = 1/(A_k)_{vv}`, row-wise
    :math:`\\Sigma_{M_k} = A_k^{-1}`.
    """
    del data
    st = mixture_stats(state, hyper)
    offset = state.w_mean[:, None, :] - state.b_mean[None]
    kernel = _M_rows_posterior if state.M_var.ndim == 3 else _M_posterior
    mean, var = jax.vmap(kernel, in_axes=(1, 0, 1, 1, 1, 0))(
        st.resp, st.alpha_mean, st.hhT, offset, state.h_mean, st.lam_mean
    )
    return state._replace(
        M_mean=_keep_active(state.active, mean, state.M_mean),
        M_var=_keep_active(state.active, var, state.M_var),
    )


@jax.jit
def update_h(state: MixtureState, data: CaviData, hyper: MixtureHyper) -> MixtureState:
    """Update q(h_ik) for every i and active k (Sec. 4.2.1 / App. B.2 corrected).

    Each :math:`h_{ik}` involves component k only, weighted by its responsibility
    (Sec. 4.2.1 and B.2 sum over k inside the update; erratum):

    .. math::

        \\Sigma_{h_{ik}} = (r_{ik}\\bar\\alpha_kE[M_k^TM_k] + \\gamma I_V)^{-1},\\quad
        \\mu_{h_{ik}} = \\Sigma_{h_{ik}}r_{ik}\\bar\\alpha_k\\bar M_k^T(\\mu_{w_i} - \\mu_{b_k}).
    """
    del data
    st = mixture_stats(state, hyper)
    offset = state.w_mean[:, None, :] - state.b_mean[None]
    mean, cov = jax.vmap(_h_posterior, in_axes=(1, 0, 0, 0, 1, None), out_axes=(1, 1))(
        st.resp, st.alpha_mean, st.MtM, state.M_mean, offset, hyper.gamma
    )
    mask = state.active[None]
    return state._replace(
        h_mean=jnp.where(mask[..., None], mean, state.h_mean),
        h_cov=jnp.where(mask[..., None, None], cov, state.h_cov),
    )


@jax.jit
def update_lam(state: MixtureState, data: CaviData, hyper: MixtureHyper) -> MixtureState:
    """Update q(lam_kv) (App. B.2; confirmed): :math:`\\bar c = c_0 + d/2`, :math:`\\bar d_{kv} = d_0 + \\frac12(\\|\\mu_{kv}\\|^2 + d(\\Sigma_{M_k})_{vv})`."""
    del data
    d = state.M_mean.shape[1]
    st = mixture_stats(state, hyper)
    shape = jnp.full_like(state.lam_shape, hyper.c0 + 0.5 * d)
    rate = hyper.d0 + 0.5 * (jnp.sum(state.M_mean**2, axis=1) + d * st.M_col_var)
    return state._replace(
        lam_shape=_keep_active(state.active, shape, state.lam_shape),
        lam_rate=_keep_active(state.active, rate, state.lam_rate),
    )


@jax.jit
def update_alpha(state: MixtureState, data: CaviData, hyper: MixtureHyper) -> MixtureState:
    """Update q(alpha_k) (B.2's derivation; its final form and Sec. 4.2.1's drop the r_ik: erratum).

    .. math::

        \\bar a_k = a_0 + \\frac d2\\sum_i r_{ik},\\quad
        \\bar b_k = b_0 + \\frac12\\sum_i r_{ik}E\\|w_i - b_k - M_kh_{ik}\\|^2 .
    """
    del data
    d = state.w_mean.shape[1]
    st = mixture_stats(state, hyper)
    shape = hyper.a0 + 0.5 * d * jnp.sum(st.resp, axis=0)
    rate = hyper.b0 + 0.5 * jnp.sum(st.resp * st.residual_sq, axis=0)
    return state._replace(
        alpha_shape=_keep_active(state.active, shape, state.alpha_shape),
        alpha_rate=_keep_active(state.active, rate, state.alpha_rate),
    )


def _data_quadratic(state: MixtureState, data: CaviData) -> Array:
    """(L,) :math:`E\\|y_i - \\Psi_iw_i\\|^2` over the observed entries."""
    return (
        data.y_sq
        - 2.0 * jnp.sum(state.w_mean * data.psi_t_y, axis=-1)
        + _gram_quadratic(data.gram, state.w_mean)
        + _gram_trace(data.gram, state.w_cov)
    )


@jax.jit
def update_beta(state: MixtureState, data: CaviData, hyper: MixtureHyper) -> MixtureState:
    """Update q(beta) (not in the thesis, which fixes beta); a no-op when beta is fixed.

    .. math::

        \\hat a_\\beta = \\beta_{a0} + \\frac12\\sum_i n_i,\\quad
        \\hat b_\\beta = \\beta_{b0} + \\frac12\\sum_iE\\|y_i - \\Psi_iw_i\\|^2 .
    """
    shape = hyper.beta_a0 + 0.5 * jnp.sum(data.num_obs)
    rate = hyper.beta_b0 + 0.5 * jnp.sum(_data_quadratic(state, data))
    learned = state.beta_learned
    return state._replace(
        beta_shape=jnp.where(learned, shape, state.beta_shape),
        beta_rate=jnp.where(learned, rate, state.beta_rate),
    )


@jax.jit
def update_z(state: MixtureState, data: CaviData, hyper: MixtureHyper) -> MixtureState:
    """Update q(z_i) (Sec. 4.2.1 / App. B.2 corrected): :math:`r_{ik} \\propto \\rho_{ik}` over active k,

    .. math::

        \\log\\rho_{ik} = E[\\log\\pi_k] + \\frac d2E[\\log\\alpha_k]
        - \\frac{\\bar\\alpha_k}2E\\|w_i - b_k - M_kh_{ik}\\|^2,

    with :math:`E[\\log\\pi_k] = \\psi(\\hat\\kappa_k) - \\psi(\\sum_j\\hat\\kappa_j)` under the
    Dirichlet q(pi) (the thesis's :math:`\\log\\pi_k` of a point estimate) and
    :math:`\\bar\\alpha_k = \\bar a_k/\\bar b_k` (Sec. 4.2.1 writes :math:`\\bar a_k/2`).
    """
    del data
    d = state.w_mean.shape[1]
    st = mixture_stats(state, hyper)
    logits = st.log_pi_mean[None] + 0.5 * d * st.log_alpha_mean[None] - 0.5 * st.alpha_mean[None] * st.residual_sq
    logits = jnp.where(state.active[None], logits, -jnp.inf)
    return state._replace(resp=jax.nn.softmax(logits, axis=1))


@jax.jit
def update_pi(state: MixtureState, data: CaviData, hyper: MixtureHyper) -> MixtureState:
    """Update q(pi) = Dir(kappa_hat), :math:`\\hat\\kappa_k = \\kappa_0 + \\sum_i r_{ik}`.

    The thesis has no prior on pi and sets :math:`\\pi_k = \\frac1L\\sum_i r_{ik}`
    (App. B.2), the mode of this Dirichlet in the limit :math:`\\kappa_0 \\to 1`
    and its mean in the limit :math:`\\kappa_0 \\to 0`.
    """
    del data
    st = mixture_stats(state, hyper)
    return state._replace(pi_conc=hyper.kappa0 + jnp.sum(st.resp, axis=0))


@jax.jit
def prune(state: MixtureState, hyper: MixtureHyper) -> MixtureState:
    """Remove components with :math:`N_k = \\sum_i r_{ik}` below ``hyper.prune_threshold`` (Sec. 4.2.1).

    Equivalently :math:`E[\\pi_k] < (\\kappa_0 + \\text{threshold})/\\sum_j\\hat\\kappa_j`,
    or the thesis's :math:`\\pi_k = N_k/L` below threshold / L.  The component with
    the largest :math:`N_k` is never removed.  The responsibilities are
    renormalised over the remaining components and q(pi) is updated.
    Not a CAVI update (it changes the family), so the bound may move slightly.
    """
    if state.resp is None:
        return state
    counts = jnp.sum(jnp.where(state.active[None], state.resp, 0.0), axis=0)
    keep = state.active & (counts >= hyper.prune_threshold)
    keep = keep | (jnp.arange(counts.shape[0]) == jnp.argmax(counts))
    resp = jnp.where(keep[None], state.resp, 0.0)
    resp = resp / jnp.sum(resp, axis=1, keepdims=True)
    return state._replace(
        active=keep, resp=resp, pi_conc=hyper.kappa0 + jnp.sum(resp, axis=0)
    )


def updates_for(state: MixtureState) -> dict:
    """The updates that apply to ``state``, in sweep order: name -> update.

    ``w, b, M, h, lam, alpha`` (the order of Sec. 4.1.1), ``beta`` (a no-op
    when beta is fixed), then ``z, pi`` for the mixture.
    """
    names = {
        "w": update_w, "b": update_b, "M": update_M, "h": update_h,
        "lam": update_lam, "alpha": update_alpha, "beta": update_beta,
    }
    if state.resp is not None:
        names["z"] = update_z
        names["pi"] = update_pi
    return names


# --------------------------------------------------------------------------- bound
def _gamma_log_prior(shape0: Array, rate0: Array, log_mean: Array, mean: Array) -> Array:
    """:math:`E_q[\\log\\Gamma(x\\mid a_0, b_0)]` from :math:`E[\\log x]` and :math:`E[x]`."""
    return shape0 * jnp.log(rate0) - gammaln(shape0) + (shape0 - 1.0) * log_mean - rate0 * mean


def _xlogx(x: Array) -> Array:
    safe = jnp.where(x > 0, x, 1.0)
    return jnp.where(x > 0, x * jnp.log(safe), 0.0)


@jax.jit
def elbo(state: MixtureState, data: CaviData, hyper: MixtureHyper) -> Array:
    """Closed-form bound :math:`E_q[\\log p(y,\\theta,z) - \\log q(\\theta,z)]`, every constant kept.

    Removed components contribute nothing (see the module docstring).  Corrects
    App. C.2 (see ``docs/derivation.md``): the factor d on :math:`\\Sigma_M`, the
    :math:`\\frac d2E\\log\\lambda_{kv}` terms, :math:`d\\sigma_{b_k}` for C.2's
    :math:`d\\sigma_{b_k}^{-1}`, the weights :math:`r_{ik}` on :math:`E\\log p(w_i\\mid\\cdot)`,
    and the signs of the entropy terms.
    """
    st = mixture_stats(state, hyper)
    L, d = state.w_mean.shape
    K, V = state.lam_shape.shape
    act = state.active
    # E log p(y | w, beta)
    log_lik = jnp.sum(
        0.5 * data.num_obs * (st.log_beta_mean - _LOG_2PI) - 0.5 * st.beta_mean * _data_quadratic(state, data)
    )
    # sum_k r_ik E log N(w_i | b_k + M_k h_ik, alpha_k^-1 I)
    log_p_w = jnp.sum(
        st.resp * (0.5 * d * (st.log_alpha_mean[None] - _LOG_2PI) - 0.5 * st.alpha_mean[None] * st.residual_sq)
    )
    h_sq = jnp.sum(state.h_mean**2, axis=-1) + jnp.trace(state.h_cov, axis1=-2, axis2=-1)
    log_p_h = jnp.sum(jnp.where(act[None], 0.5 * V * (jnp.log(hyper.gamma) - _LOG_2PI) - 0.5 * hyper.gamma * h_sq, 0.0))
    b_sq = jnp.sum(state.b_mean**2, axis=-1) + d * state.b_var
    log_p_b = jnp.sum(jnp.where(act, 0.5 * d * (jnp.log(hyper.lambda0) - _LOG_2PI) - 0.5 * hyper.lambda0 * b_sq, 0.0))
    m_sq = jnp.sum(state.M_mean**2, axis=1) + d * st.M_col_var
    log_p_M = jnp.sum(
        jnp.where(act[:, None], 0.5 * d * (st.log_lam_mean - _LOG_2PI) - 0.5 * st.lam_mean * m_sq, 0.0)
    )
    log_p_alpha = jnp.sum(jnp.where(act, _gamma_log_prior(hyper.a0, hyper.b0, st.log_alpha_mean, st.alpha_mean), 0.0))
    log_p_lam = jnp.sum(
        jnp.where(act[:, None], _gamma_log_prior(hyper.c0, hyper.d0, st.log_lam_mean, st.lam_mean), 0.0)
    )
    if state.M_var.ndim == 3:
        entropy_M = d * (0.5 * V * (1.0 + _LOG_2PI) + 0.5 * _logdet_psd(state.M_var))
    else:
        entropy_M = jnp.sum(0.5 * d * (1.0 + _LOG_2PI + jnp.log(state.M_var)), axis=-1)
    entropy = (
        jnp.sum(0.5 * d * (1.0 + _LOG_2PI) + 0.5 * _cov_logdet(state.w_cov))
        + jnp.sum(jnp.where(act[None], 0.5 * V * (1.0 + _LOG_2PI) + 0.5 * _logdet_psd(state.h_cov), 0.0))
        + jnp.sum(jnp.where(act, 0.5 * d * (1.0 + _LOG_2PI + jnp.log(state.b_var)), 0.0))
        + jnp.sum(jnp.where(act, entropy_M, 0.0))
        + jnp.sum(jnp.where(act, _gamma_entropy(state.alpha_shape, state.alpha_rate), 0.0))
        + jnp.sum(jnp.where(act[:, None], _gamma_entropy(state.lam_shape, state.lam_rate), 0.0))
    )
    total = log_lik + log_p_w + log_p_h + log_p_b + log_p_M + log_p_alpha + log_p_lam + entropy
    beta_terms = _gamma_log_prior(hyper.beta_a0, hyper.beta_b0, st.log_beta_mean, st.beta_mean)
    beta_terms = beta_terms + _gamma_entropy(state.beta_shape, state.beta_rate)
    total = total + jnp.where(state.beta_learned, beta_terms, 0.0)
    if state.resp is not None:
        conc = state.pi_conc
        # E log p(z | pi) - E log q(z)
        total = total + jnp.sum(st.resp * st.log_pi_mean[None]) - jnp.sum(_xlogx(st.resp))
        # E log Dir(pi | kappa0) - E log Dir(pi | conc)
        total = total + (
            gammaln(K * hyper.kappa0) - K * gammaln(hyper.kappa0)
            + (hyper.kappa0 - 1.0) * jnp.sum(st.log_pi_mean)
            - gammaln(jnp.sum(conc)) + jnp.sum(gammaln(conc))
            - jnp.sum((conc - 1.0) * st.log_pi_mean)
        )
    return total


# --------------------------------------------------------------------------- loop
@jax.jit
def step(state: MixtureState, data: CaviData, hyper: MixtureHyper) -> tuple[MixtureState, CaviInfo]:
    """One sweep over :func:`updates_for` (``state``), then :func:`prune`; returns the state and its ELBO."""
    for update in updates_for(state).values():
        state = update(state, data, hyper)
    state = prune(state, hyper)
    return state, CaviInfo(elbo(state, data, hyper))


def _validate_options(tol, max_iter, num_restarts, family) -> None:
    _check_family(family)
    _check_options(tol, max_iter, num_restarts)


def _fit(starts, cavi_data, hyper_arr, tol, max_iter, progress, label) -> CaviFit:
    """Run every start with the compiled loop of :mod:`cavi` and keep the best final ELBO."""
    return _best_of_restarts(starts, cavi_data, hyper_arr, tol, max_iter, progress, label, step_fn=step)


def fit_cavi_mixture(
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
    prune_threshold: float = 0.5,
    search: str = "split_merge",
    max_moves: int | None = None,
) -> CaviFit:
    """Fit the mixture of LMProMPs (Sec. 4.2) by CAVI; K is ``hyper.num_components``.

    Each start clusters the ridge weights by k-means++ (scikit-learn, 10 inits, a
    seed drawn from a key split from ``key``) and runs PCA per cluster
    (:func:`lmpromp_ppl.inference.init.init_mixture_state`).  With
    ``search="split_merge"`` (default) each start is then improved by merge and
    split moves accepted only when they raise the bound
    (:mod:`lmpromp_ppl.inference.mixture_search`); ``search="none"`` runs plain
    CAVI from each start.  The best final ELBO over the starts wins.

    Parameters
    ----------
    data : padded model inputs
    hyper : hyperparameters (``num_components`` K, ``latent_dim`` V, ``kappa0``,
        ``learn_beta`` with ``beta_a0``, ``beta_b0``)
    key : jax PRNG key
    tol, max_iter, num_restarts, progress, shared_psi : as :func:`lmpromp_ppl.inference.cavi.fit_cavi`
    family : ``"columnwise"`` (thesis, default) or ``"rowwise"`` q(M), see :data:`FAMILIES`
    prune_threshold : remove a component when its expected number of
        demonstrations falls below this (see :func:`prune`); 0 disables removal
    search : ``"split_merge"`` or ``"none"`` (see :data:`lmpromp_ppl.inference.mixture_search.SEARCHES`)
    max_moves : at most this many accepted moves per start (default 2K); ignored without search

    Returns
    -------
    CaviFit
        ``state`` is a :class:`MixtureState`.
    """
    from lmpromp_ppl.inference.init import init_mixture_state  # init imports this module

    if not isinstance(hyper, Hyperparameters):
        raise LmprompError(f"hyper must be a Hyperparameters, got {type(hyper).__name__}")
    _validate_options(tol, max_iter, num_restarts, family)
    if not (isinstance(prune_threshold, (int, float)) and 0 <= prune_threshold and math.isfinite(prune_threshold)):
        raise LmprompError(f"prune_threshold must be a number >= 0, got {prune_threshold!r}")
    if search not in ("none", "split_merge"):
        raise LmprompError(f"unknown search {search!r}; choose from ['none', 'split_merge']")
    if max_moves is not None and (isinstance(max_moves, bool) or not isinstance(max_moves, (int, np.integer)) or max_moves < 0):
        raise LmprompError(f"max_moves must be an integer >= 0, got {max_moves!r}")
    _check_model_data(data)
    hyper.validate_for(data.num_weights, data.num_demos)
    if hyper.num_components > data.num_demos:
        raise LmprompError(
            f"more mixture components (K={hyper.num_components}) than demonstrations (L={data.num_demos})"
        )
    cavi_data = prepare_cavi_data(data, shared_psi)
    hyper_arr = mixture_hyper_arrays(hyper, prune_threshold)
    keys = jax.random.split(key, num_restarts)
    starts = [init_mixture_state(cavi_data, hyper, keys[r], family=family) for r in range(num_restarts)]
    if search == "none":
        return _fit(starts, cavi_data, hyper_arr, tol, max_iter, progress, "CAVI mixture")
    from lmpromp_ppl.inference.mixture_search import fit_with_search

    seed = int(jax.random.randint(jax.random.fold_in(key, 1), (), 0, np.iinfo(np.int32).max))
    return fit_with_search(
        starts, cavi_data, hyper_arr, tol=tol, max_iter=max_iter, progress=progress, max_moves=max_moves, seed=seed
    )


def fit_single_extended(
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
    """Single-type LMProMP with a row-wise q(M) and/or a learned beta (K = 1 :class:`MixtureState`).

    Starts as :func:`lmpromp_ppl.inference.cavi.fit_cavi` (thesis initialisation,
    restarts perturb it); q(beta) starts at :math:`\\hat a_\\beta = \\beta_{a0} + n/2`
    with mean ``hyper.beta``.  Called by ``fit_cavi`` for these options.
    """
    from lmpromp_ppl.inference.init import init_state

    if not isinstance(hyper, Hyperparameters):
        raise LmprompError(f"hyper must be a Hyperparameters, got {type(hyper).__name__}")
    _validate_options(tol, max_iter, num_restarts, family)
    if hyper.num_components != 1:
        raise LmprompError(
            f"the single-type CAVI engine needs num_components=1, got {hyper.num_components}"
        )
    _check_model_data(data)
    hyper.validate_for(data.num_weights, data.num_demos)
    cavi_data = prepare_cavi_data(data, shared_psi)
    hyper_arr = mixture_hyper_arrays(hyper, 0.0)
    beta = None
    if hyper.learn_beta:
        shape = hyper.beta_a0 + 0.5 * float(jnp.sum(cavi_data.num_obs))
        beta = (shape, shape / hyper.beta)
    keys = jax.random.split(key, num_restarts)
    starts = [
        lift_state(init_state(cavi_data, hyper, key=None if r == 0 else keys[r]), family, beta)
        for r in range(num_restarts)
    ]
    return _fit(starts, cavi_data, hyper_arr, tol, max_iter, progress, "CAVI")


# --------------------------------------------------------------------------- posterior summaries
def responsibilities(state: MixtureState) -> np.ndarray:
    """(L, K) responsibilities :math:`q(z_i = k)` (0 for removed components)."""
    if state.resp is None:
        raise LmprompError("a single-type state has no responsibilities")
    return np.asarray(jnp.where(state.active[None], state.resp, 0.0))


def _squeeze(draws: dict[str, Array], single: bool, axis: dict[str, int]) -> dict[str, Array]:
    if not single:
        return draws
    return {k: (jnp.squeeze(v, axis=axis[k]) if k in axis else v) for k, v in draws.items()}


def sample_q(key: Array, state: MixtureState, num_draws: int) -> dict[str, Array]:
    """Independent draws from q with a leading draw axis.

    Mixture: ``pi`` (n, K), ``b`` (n, K, d), ``M`` (n, K, d, V), ``lam`` (n, K, V),
    ``alpha`` (n, K), ``h`` (n, L, K, V), ``w`` (n, L, d), ``z`` (n, L) (int,
    from q(z)), and ``beta`` (n,) when learned.  ``pi`` is drawn from q(pi)
    restricted to the active components (a Dirichlet over them; 0 for removed
    ones); removed components' other draws come from their frozen factors.
    Single type: no ``pi``, ``z`` and no component axis.
    """
    key, k_g = jax.random.split(key)
    # one compiled Gamma sampler per number of Gamma factors (costly to compile); q(beta) is
    # always drawn so that fixed and learned beta share it, and dropped when beta is fixed
    shapes = [state.alpha_shape, state.lam_shape.reshape(-1), state.beta_shape[None]]
    if state.resp is not None:
        shapes.append(state.pi_conc)
    gammas = _gamma_draws(k_g, jnp.concatenate(shapes), num_draws)
    return _sample(key, state, gammas, num_draws, bool(state.beta_learned))


@partial(jax.jit, static_argnames=("num_draws", "learned"))
def _sample(key: Array, state: MixtureState, gammas: Array, num_draws: int, learned: bool) -> dict[str, Array]:
    """Compiled body of :func:`sample_q`; ``gammas`` are standard Gamma draws of q's Gamma/Dirichlet factors."""
    L, d = state.w_mean.shape
    K, V = state.lam_shape.shape
    k_w, k_h, k_b, k_M, k_z = jax.random.split(key, 5)
    cov = state.w_cov
    z_w = jax.random.normal(k_w, (num_draws, L, d))
    if isinstance(cov, EigenCovariance):
        w = state.w_mean + (z_w * jnp.sqrt(cov.variances)) @ cov.basis.T
    else:
        w = state.w_mean + jnp.einsum("ide,nie->nid", jnp.linalg.cholesky(cov.matrices), z_w)
    z_h = jax.random.normal(k_h, (num_draws, L, K, V))
    h = state.h_mean + jnp.einsum("ikuv,nikv->niku", jnp.linalg.cholesky(state.h_cov), z_h)
    b = state.b_mean + jnp.sqrt(state.b_var)[:, None] * jax.random.normal(k_b, (num_draws, K, d))
    z_M = jax.random.normal(k_M, (num_draws, K, d, V))
    if state.M_var.ndim == 3:
        M = state.M_mean + jnp.einsum("kuv,nkdv->nkdu", jnp.linalg.cholesky(state.M_var), z_M)
    else:
        M = state.M_mean + jnp.sqrt(state.M_var)[:, None, :] * z_M
    rates = [state.alpha_rate, state.lam_rate.reshape(-1), state.beta_rate[None]]
    if state.resp is not None:
        rates.append(jnp.ones(K))
    gammas = gammas / jnp.concatenate(rates)
    draws = {
        "b": b, "M": M, "h": h, "w": w,
        "alpha": gammas[:, :K], "lam": gammas[:, K : K + K * V].reshape(num_draws, K, V),
    }
    offset = K + K * V + 1
    if learned:
        draws["beta"] = gammas[:, offset - 1]
    if state.resp is None:
        return _squeeze(draws, True, {"b": 1, "M": 1, "h": 2, "alpha": 1, "lam": 1})
    weights = jnp.where(state.active[None], gammas[:, offset:], 0.0)
    draws["pi"] = weights / jnp.sum(weights, axis=1, keepdims=True)
    log_resp = jnp.log(jnp.where(state.active[None], state.resp, 0.0))
    draws["z"] = jax.random.categorical(k_z, log_resp, axis=-1, shape=(num_draws, L))
    return draws


def log_q(state: MixtureState, draws: dict[str, Array]) -> Array:
    r"""log q of draws (leading draw axis, the sites of :func:`sample_q`), active components only.

    Every factor of the family: q(w_i), q(h_ik), q(b_k), q(M_k) (column- or
    row-wise), q(alpha_k), q(lam_k), q(beta) when learned, and for the mixture
    q(pi) and q(z).  Used for PSIS k-hat (:mod:`lmpromp_ppl.diagnostics.metrics`).
    """
    import numpyro.distributions as dist

    mix = state.resp is not None
    act = state.active
    comp = (lambda x: x) if mix else (lambda x: x[:, None])  # noqa: E731
    h = draws["h"] if mix else draws["h"][:, :, None]
    on = lambda x, axes: jnp.where(act, x, 0.0).sum(axes)  # noqa: E731  (sum over active components)
    M = comp(draws["M"])
    if state.M_var.ndim == 3:  # rows of M_k ~ N(mu_k,j., Sigma_Mk)
        log_M = dist.MultivariateNormal(state.M_mean, state.M_var[:, None]).log_prob(M).sum(-1)
    else:
        log_M = dist.Normal(state.M_mean, jnp.sqrt(state.M_var)[:, None, :]).log_prob(M).sum((-2, -1))
    cov = state.w_cov
    w_cov = cov.matrices if hasattr(cov, "matrices") else jnp.einsum(
        "ij,nj,kj->nik", cov.basis, cov.variances, cov.basis)
    terms = [
        dist.MultivariateNormal(state.w_mean, w_cov).log_prob(draws["w"]).sum(-1),
        on(dist.MultivariateNormal(state.h_mean, state.h_cov).log_prob(h), (-2, -1)),
        on(dist.Normal(state.b_mean, jnp.sqrt(state.b_var)[:, None]).log_prob(comp(draws["b"])).sum(-1), -1),
        on(dist.Gamma(state.alpha_shape, state.alpha_rate).log_prob(comp(draws["alpha"])), -1),
        on(dist.Gamma(state.lam_shape, state.lam_rate).log_prob(comp(draws["lam"])).sum(-1), -1),
        on(log_M, -1),
        jnp.where(  # traceable: beta_learned is an array leaf of the state
            state.beta_learned,
            dist.Gamma(state.beta_shape, state.beta_rate).log_prob(draws.get("beta", 1.0)),
            0.0,
        ),
    ]
    if mix:
        terms.append(dist.Dirichlet(state.pi_conc).log_prob(draws["pi"]))
        terms.append(dist.Categorical(probs=state.resp).log_prob(draws["z"]).sum(-1))
    return sum(terms)


def point_estimate(state: MixtureState) -> dict[str, Array]:
    """Posterior means of q: ``b``, ``M``, ``alpha``, ``lam``, ``h``, ``w`` (+ ``beta``, + ``pi`` for the mixture).

    ``pi`` is :math:`E[\\pi_k]` over the active components, renormalised (0 for removed ones).
    """
    out = {
        "b": state.b_mean,
        "M": state.M_mean,
        "alpha": state.alpha_shape / state.alpha_rate,
        "lam": state.lam_shape / state.lam_rate,
        "h": state.h_mean,
        "w": state.w_mean,
    }
    if bool(state.beta_learned):
        out["beta"] = state.beta_shape / state.beta_rate
    if state.resp is None:
        return _squeeze(out, True, {"b": 0, "M": 0, "h": 1, "alpha": 0, "lam": 0})
    conc = jnp.where(state.active, state.pi_conc, 0.0)
    out["pi"] = conc / jnp.sum(conc)
    return out


def active_components(state: MixtureState) -> list[int]:
    """Indices of the components that were not removed (Sec. 4.2.1)."""
    return [int(k) for k in np.flatnonzero(np.asarray(state.active))]


def active_latent_dims(state: MixtureState, threshold: float = 1e-3) -> list[int] | list[list[int]]:
    r"""ARD per component: the rule of :func:`lmpromp_ppl.inference.cavi.active_latent_dims`.

    Single type: a list of indices; mixture: one list per component (all K, empty for removed ones).
    """
    inverse = np.asarray(state.lam_rate / state.lam_shape)  # (K, V)
    mean_sq = np.sum(np.asarray(state.M_mean) ** 2, axis=1)  # (K, V): |E[m_kv]|^2
    var = np.asarray(state.M_var)
    var = np.diagonal(var, axis1=-2, axis2=-1) if var.ndim == 3 else var  # (K, V)
    spread = state.M_mean.shape[1] * var  # tr Cov(m_kv)
    active = np.asarray(state.active)
    per_component = [
        [int(v) for v in np.flatnonzero((row > threshold * row.max()) & (mean_sq[k] > spread[k]))]
        if active[k] else []
        for k, row in enumerate(inverse)
    ]
    return per_component[0] if state.resp is None else per_component

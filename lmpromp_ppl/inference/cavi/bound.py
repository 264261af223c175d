r"""The closed-form evidence lower bound of the CAVI family, every constant kept."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax import Array
from jax.scipy.special import gammaln

from lmpromp_ppl.inference.cavi.data import CaviData, cov_logdet, logdet_psd
from lmpromp_ppl.inference.cavi.kernels import gamma_entropy, gamma_log_prior, xlogx
from lmpromp_ppl.inference.cavi.state import CaviHyper, CaviState, expected_stats
from lmpromp_ppl.inference.cavi.updates import data_quadratic

__all__ = ["elbo"]

_LOG_2PI = math.log(2.0 * math.pi)


@jax.jit
def elbo(state: CaviState, data: CaviData, hyper: CaviHyper) -> Array:
    """Closed-form bound :math:`E_q[\\log p(y,\\theta,z) - \\log q(\\theta,z)]`, every constant kept.

    Removed components contribute nothing (module docstring of :mod:`.state`).
    Corrects App. C.1 and C.2 (``docs/derivation.md``): the factor d on
    :math:`\\Sigma_M` in :math:`E\\log p(w_i\\mid\\cdot)`, the :math:`\\frac d2E\\log\\lambda_{kv}`
    terms of :math:`E\\log p(M)` (which change during the updates), :math:`d\\sigma_{b_k}`
    for C.2's :math:`d\\sigma_{b_k}^{-1}`, the weights :math:`r_{ik}` on
    :math:`E\\log p(w_i\\mid\\cdot)`, the signs of the entropy terms, and the constants.
    """
    st = expected_stats(state, hyper, logs=True)
    L, d = state.w_mean.shape
    K, V = state.lam_shape.shape
    act = state.active
    # E log p(y | w, beta): observed entries only
    log_lik = jnp.sum(
        0.5 * data.num_obs * (st.log_beta_mean - _LOG_2PI) - 0.5 * st.beta_mean * data_quadratic(state, data)
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
    # one gammaln over every shape of q and of the priors (each call is a large expression to compile)
    conc = state.pi_conc
    prior_shapes = [hyper.a0[None], hyper.c0[None], hyper.beta_a0[None]]
    if state.resp is not None:
        prior_shapes += [hyper.kappa0[None], (K * hyper.kappa0)[None], jnp.sum(conc)[None], conc]
    lg = gammaln(jnp.concatenate(
        [state.alpha_shape, state.lam_shape.reshape(-1), state.beta_shape[None]] + prior_shapes))
    lg_alpha, lg_lam, lg_beta = lg[:K], lg[K : K + K * V].reshape(K, V), lg[K + K * V]
    lg_a0, lg_c0, lg_beta_a0 = lg[K + K * V + 1], lg[K + K * V + 2], lg[K + K * V + 3]
    log_p_alpha = jnp.sum(jnp.where(
        act, gamma_log_prior(hyper.a0, hyper.b0, st.log_alpha_mean, st.alpha_mean, lg_a0), 0.0))
    log_p_lam = jnp.sum(jnp.where(
        act[:, None], gamma_log_prior(hyper.c0, hyper.d0, st.log_lam_mean, st.lam_mean, lg_c0), 0.0))
    if state.M_var.ndim == 3:
        entropy_M = d * (0.5 * V * (1.0 + _LOG_2PI) + 0.5 * logdet_psd(state.M_var))
    else:
        entropy_M = jnp.sum(0.5 * d * (1.0 + _LOG_2PI + jnp.log(state.M_var)), axis=-1)
    entropy = (
        jnp.sum(0.5 * d * (1.0 + _LOG_2PI) + 0.5 * cov_logdet(state.w_cov))
        + jnp.sum(jnp.where(act[None], 0.5 * V * (1.0 + _LOG_2PI) + 0.5 * logdet_psd(state.h_cov), 0.0))
        + jnp.sum(jnp.where(act, 0.5 * d * (1.0 + _LOG_2PI + jnp.log(state.b_var)), 0.0))
        + jnp.sum(jnp.where(act, entropy_M, 0.0))
        + jnp.sum(jnp.where(act, gamma_entropy(state.alpha_shape, state.alpha_rate, st.log_alpha_mean, lg_alpha), 0.0))
        + jnp.sum(jnp.where(act[:, None], gamma_entropy(state.lam_shape, state.lam_rate, st.log_lam_mean, lg_lam), 0.0))
    )
    total = log_lik + log_p_w + log_p_h + log_p_b + log_p_M + log_p_alpha + log_p_lam + entropy
    # q(beta)'s terms; log_beta_mean is the Gamma's own E[log beta] where beta is learned
    beta_terms = gamma_log_prior(hyper.beta_a0, hyper.beta_b0, st.log_beta_mean, st.beta_mean, lg_beta_a0)
    beta_terms = beta_terms + gamma_entropy(state.beta_shape, state.beta_rate, st.log_beta_mean, lg_beta)
    total = total + jnp.where(state.beta_learned, beta_terms, 0.0)
    if state.resp is not None:
        lg_kappa0, lg_K_kappa0, lg_sum_conc, lg_conc = lg[-K - 3], lg[-K - 2], lg[-K - 1], lg[-K:]
        # E log p(z | pi) - E log q(z)
        total = total + jnp.sum(st.resp * st.log_pi_mean[None]) - jnp.sum(xlogx(st.resp))
        # E log Dir(pi | kappa0) - E log Dir(pi | conc)
        total = total + (
            lg_K_kappa0 - K * lg_kappa0
            + (hyper.kappa0 - 1.0) * jnp.sum(st.log_pi_mean)
            - lg_sum_conc + jnp.sum(lg_conc)
            - jnp.sum((conc - 1.0) * st.log_pi_mean)
        )
    return total

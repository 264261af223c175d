r"""The closed-form CAVI updates, one per factor (thesis Sec. 4.1.1, 4.2.1, App. B.1, B.2; corrected).

Each update maximises the bound (:func:`lmpromp_ppl.inference.cavi.elbo`) over its
own factor with the others fixed; ``tests/test_cavi.py`` and
``tests/test_cavi_mixture.py`` check this by autodiff stationarity.  For the
single type (K = 1, ``resp`` None) the responsibilities are ones and the
equations reduce to those of Sec. 4.1.1 with :math:`r_{i1} = 1`.

Thesis errata implemented here (``docs/derivation.md``): the coupling between
the columns of M in :math:`\mu_{m_v}` (App. B.1, B.2), the inverse in
:math:`\sigma_b` (App. B.1), the factor d in :math:`E[M^TM]` (App. C.1), the
per-component :math:`h_{ik}` (Sec. 4.2.1 and B.2 sum over k inside the update),
:math:`r_{ik}` in the update of :math:`\alpha_k` (B.2's final form drops it), and
:math:`\bar\alpha_k = \bar a_k/\bar b_k` in :math:`r_{ik}` (Sec. 4.2.1 writes :math:`\bar a_k/2`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from lmpromp_ppl.inference.cavi.data import CaviData, cov_apply, gram_quadratic, gram_sandwich, gram_trace
from lmpromp_ppl.inference.cavi.kernels import (
    M_columns_posterior,
    M_rows_posterior,
    b_posterior,
    h_posterior,
    joint_posterior,
    w_posterior,
)
from lmpromp_ppl.inference.cavi.state import CaviHyper, CaviState, cross_solve, expected_stats, keep_active

__all__ = [
    "update_w",
    "update_b",
    "update_M",
    "update_h",
    "update_wh",
    "update_lam",
    "update_alpha",
    "update_beta",
    "update_z",
    "update_pi",
    "prune",
    "UPDATES",
    "JOINT_UPDATES",
    "updates_for",
    "data_quadratic",
]


@jax.jit
def update_w(state: CaviState, data: CaviData, hyper: CaviHyper) -> CaviState:
    """Update q(w_i) (Sec. 4.1.1 / 4.2.1, App. B.1 / B.2; confirmed), with :math:`E[\\beta]` for a learned beta.

    .. math::

        \\Sigma_{w_i} = \\Big(E[\\beta]\\Psi_i^T\\Psi_i + \\sum_k r_{ik}\\bar\\alpha_k I_d\\Big)^{-1},\\quad
        \\mu_{w_i} = \\Sigma_{w_i}\\Big(E[\\beta]\\Psi_i^Ty_i + \\sum_k r_{ik}\\bar\\alpha_k(\\mu_{b_k} + \\bar M_k\\mu_{h_{ik}})\\Big).

    :math:`\\Psi_i` holds only the observed rows (mask).  The prior precision is a
    scalar per demonstration, so on the fast path (:class:`SharedGram`)
    :math:`\\Sigma_{w_i} = U\\operatorname{diag}(1/(\\beta s + \\sum_k r_{ik}\\bar\\alpha_k))U^T`.
    """
    st = expected_stats(state, hyper)
    weights = st.resp * st.alpha_mean[None]
    means = state.b_mean[None] + jnp.einsum("kdv,ikv->ikd", state.M_mean, state.h_mean)
    mean, cov = w_posterior(
        data, st.beta_mean, jnp.sum(weights, axis=1), jnp.einsum("ik,ikd->id", weights, means)
    )
    return state._replace(w_mean=mean, w_cov=cov)


@jax.jit
def update_b(state: CaviState, data: CaviData, hyper: CaviHyper) -> CaviState:
    """Update q(b_k) for every active k (Sec. 4.1.1 / 4.2.1; App. B.1 corrected: sigma_b is an inverse).

    .. math::

        \\sigma_{b_k} = \\Big(\\bar\\alpha_k\\sum_i r_{ik} + \\lambda_0\\Big)^{-1},\\quad
        \\mu_{b_k} = \\sigma_{b_k}\\bar\\alpha_k\\sum_i r_{ik}(\\mu_{w_i} - \\bar M_k\\mu_{h_{ik}}).

    App. B.1 writes :math:`\\sigma_b = L\\bar\\alpha + \\lambda^{[0]}` (no inverse); Sec. 4.1.1 has it right.
    """
    del data
    st = expected_stats(state, hyper)
    mean, var = jax.vmap(b_posterior, in_axes=(1, 0, None, 1, 0, None))(
        st.resp, st.alpha_mean, state.w_mean, state.h_mean, state.M_mean, hyper.lambda0
    )
    return state._replace(
        b_mean=keep_active(state.active, mean, state.b_mean),
        b_var=keep_active(state.active, var, state.b_var),
    )


@jax.jit
def update_M(state: CaviState, data: CaviData, hyper: CaviHyper) -> CaviState:
    """Update q(M_k) for every active k, in the state's family (Sec. 4.1.1, App. B.1 / B.2 corrected).

    With :math:`S_k = \\sum_i r_{ik}E[h_{ik}h_{ik}^T]`,
    :math:`R_k = \\sum_i r_{ik}(\\mu_{w_i} - \\mu_{b_k})\\mu_{h_{ik}}^T` (plus :math:`\\sum_i r_{ik}C_{ik}`
    in the joint local family: :math:`E[(w_i - b_k)h_{ik}^T]`) and
    :math:`A_k = \\bar\\alpha_kS_k + \\operatorname{diag}(\\bar\\lambda_k)`, both families have
    :math:`\\bar M_kA_k = \\bar\\alpha_kR_k`; column-wise :math:`\\sigma_{kv} = 1/(A_k)_{vv}`,
    row-wise :math:`\\Sigma_{M_k} = A_k^{-1}`.

    Column v of the mean equation reads
    :math:`\\mu_{m_v} = \\sigma_{m_v}\\bar\\alpha\\sum_i[\\mu_{h_{v,i}}(\\mu_{w_i}-\\mu_b) - \\sum_{u\\ne v}\\mu_{m_u}E[h_{u,i}h_{v,i}]]`:
    the thesis (B.1, B.2) omits the coupling sum over :math:`u \\ne v`.  Solving the V
    columns jointly is the exact maximiser over all factors q(m_v) (the bound is a
    concave quadratic in :math:`\\bar M`, separable from the variances).
    """
    del data
    st = expected_stats(state, hyper)
    offset = state.w_mean[:, None, :] - state.b_mean[None]
    kernel = M_rows_posterior if state.M_var.ndim == 3 else M_columns_posterior
    # joint local family: E[(w_i - b) h_i^T] gains the cross covariance C_i
    cross = jnp.zeros_like(state.M_mean) if state.wh_cov is None else jnp.einsum(
        "ik,ikdv->kdv", st.resp, state.wh_cov)
    mean, var = jax.vmap(kernel, in_axes=(1, 0, 1, 1, 1, 0, 0))(
        st.resp, st.alpha_mean, st.hhT, offset, state.h_mean, st.lam_mean, cross
    )
    return state._replace(
        M_mean=keep_active(state.active, mean, state.M_mean),
        M_var=keep_active(state.active, var, state.M_var),
    )


@jax.jit
def update_h(state: CaviState, data: CaviData, hyper: CaviHyper) -> CaviState:
    """Update q(h_ik) for every i and active k (Sec. 4.1.1 with the factor d; Sec. 4.2.1 / B.2 corrected).

    .. math::

        \\Sigma_{h_{ik}} = (r_{ik}\\bar\\alpha_kE[M_k^TM_k] + \\gamma I_V)^{-1},\\quad
        \\mu_{h_{ik}} = \\Sigma_{h_{ik}}r_{ik}\\bar\\alpha_k\\bar M_k^T(\\mu_{w_i} - \\mu_{b_k}),

    with :math:`E[M_k^TM_k] = \\bar M_k^T\\bar M_k + d\\Sigma_{M_k}`; the d comes from
    :math:`E[m_v^Tm_v] = \\|\\mu_{m_v}\\|^2 + d\\sigma_{m_v}` (App. C.1 drops it).  Each
    :math:`h_{ik}` involves component k only (Sec. 4.2.1 and B.2 sum over k inside the update).
    """
    del data
    st = expected_stats(state, hyper)
    offset = state.w_mean[:, None, :] - state.b_mean[None]
    mean, cov = jax.vmap(h_posterior, in_axes=(1, 0, 0, 0, 1, None), out_axes=(1, 1))(
        st.resp, st.alpha_mean, st.MtM, state.M_mean, offset, hyper.gamma
    )
    mask = state.active[None]
    return state._replace(
        h_mean=jnp.where(mask[..., None], mean, state.h_mean),
        h_cov=jnp.where(mask[..., None, None], cov, state.h_cov),
    )


@jax.jit
def update_wh(state: CaviState, data: CaviData, hyper: CaviHyper) -> CaviState:
    """Update the joint q(w_i, h_i) of the single type (joint local family; ``docs/derivation.md``).

    With q(b), q(M), q(alpha) and q(beta) fixed, :math:`\\log q^*(w_i, h_i)` is quadratic, with precision
    :math:`\\begin{pmatrix}P_i & -\\bar\\alpha\\bar M\\\\ -\\bar\\alpha\\bar M^T & \\bar\\alpha E[M^TM] + \\gamma I\\end{pmatrix}`,
    :math:`P_i = \\bar\\alpha I + E[\\beta]\\Psi_i^T\\Psi_i`, and linear term
    :math:`(E[\\beta]\\Psi_i^Ty_i + \\bar\\alpha\\mu_b,\\ -\\bar\\alpha\\bar M^T\\mu_b)`.  In the
    parametrisation of :mod:`.state` (Schur complements):

    .. math::

        W_i = P_i^{-1},\\quad a_i = W_i(E[\\beta]\\Psi_i^Ty_i + \\bar\\alpha\\mu_b),\\quad
        B_i = \\bar\\alpha W_i\\bar M,\\\\
        S_i = \\big(\\bar\\alpha E[M^TM] + \\gamma I - \\bar\\alpha\\bar M^TB_i\\big)^{-1},\\quad
        \\mu_{h_i} = S_i\\bar\\alpha\\bar M^T(a_i - \\mu_b),\\quad
        \\mu_{w_i} = a_i + B_i\\mu_{h_i},\\quad C_i = B_iS_i.

    :math:`W_i` and :math:`a_i` are q*(w_i) of :func:`update_w` with :math:`h_i` integrated out of
    its prior mean, so the fast path's diagonal :math:`W_i` is kept; the extra cost is
    :math:`O(LdV^2)`.  :math:`S_i` is positive definite because :math:`\\bar\\alpha W_i \\preceq I`.
    """
    st = expected_stats(state, hyper)
    alpha = st.alpha_mean[0]
    b = state.b_mean[0]
    L, d = state.w_mean.shape
    a, W = w_posterior(data, st.beta_mean, jnp.full((L,), alpha), jnp.broadcast_to(alpha * b, (L, d)))
    w, h, S, C = joint_posterior(alpha, st.MtM[0], state.M_mean[0], a - b, a, cov_apply(W, state.M_mean[0]),
                                 hyper.gamma)
    return state._replace(w_mean=w, w_cov=W, h_mean=h[:, None], h_cov=S[:, None], wh_cov=C[:, None])


@jax.jit
def update_lam(state: CaviState, data: CaviData, hyper: CaviHyper) -> CaviState:
    """Update q(lam_kv) (Sec. 4.1.1, App. B.1 / B.2; confirmed).

    .. math::

        \\bar c_{kv} = c^{[0]} + \\frac d2, \\qquad
        \\bar d_{kv} = d^{[0]} + \\frac12(\\mu_{kv}^T\\mu_{kv} + d(\\Sigma_{M_k})_{vv}).
    """
    del data
    d = state.M_mean.shape[1]
    st = expected_stats(state, hyper)
    shape = jnp.full_like(state.lam_shape, hyper.c0 + 0.5 * d)
    rate = hyper.d0 + 0.5 * (jnp.sum(state.M_mean**2, axis=1) + d * st.M_col_var)
    return state._replace(
        lam_shape=keep_active(state.active, shape, state.lam_shape),
        lam_rate=keep_active(state.active, rate, state.lam_rate),
    )


@jax.jit
def update_alpha(state: CaviState, data: CaviData, hyper: CaviHyper) -> CaviState:
    """Update q(alpha_k) (Sec. 4.1.1 / B.1 confirmed; B.2's final form and Sec. 4.2.1 drop the r_ik: erratum).

    .. math::

        \\bar a_k = a_0 + \\frac d2\\sum_i r_{ik},\\quad
        \\bar b_k = b_0 + \\frac12\\sum_i r_{ik}E\\|w_i - b_k - M_kh_{ik}\\|^2 .

    For the single type the expectation is B.1's braces
    :math:`C_i + \\operatorname{tr}\\Sigma_{w_i} + d\\sigma_b + \\mu_{h_i}^Td\\Sigma_M\\mu_{h_i}
    + \\operatorname{tr}[(\\bar M^T\\bar M + d\\Sigma_M)\\Sigma_{h_i}]` (``ExpectedStats.residual_sq``).
    """
    del data
    d = state.w_mean.shape[1]
    st = expected_stats(state, hyper)
    shape = hyper.a0 + 0.5 * d * jnp.sum(st.resp, axis=0)
    rate = hyper.b0 + 0.5 * jnp.sum(st.resp * st.residual_sq, axis=0)
    return state._replace(
        alpha_shape=keep_active(state.active, shape, state.alpha_shape),
        alpha_rate=keep_active(state.active, rate, state.alpha_rate),
    )


def data_quadratic(state: CaviState, data: CaviData) -> jax.Array:
    """(L,) :math:`E\\|y_i - \\Psi_iw_i\\|^2` over the observed entries.

    In the joint local family the marginal covariance of :math:`w_i` is
    :math:`W_i + C_iS_i^{-1}C_i^T`, whose Gram trace is
    :math:`\\operatorname{tr}(\\Psi_i^T\\Psi_iW_i) + \\operatorname{tr}(S_i^{-1}C_i^T\\Psi_i^T\\Psi_iC_i)`.
    """
    quadratic = (
        data.y_sq
        - 2.0 * jnp.sum(state.w_mean * data.psi_t_y, axis=-1)
        + gram_quadratic(data.gram, state.w_mean)
        + gram_trace(data.gram, state.w_cov)
    )
    if state.wh_cov is None:
        return quadratic
    sandwich = gram_sandwich(data.gram, cross_solve(state), state.wh_cov[:, 0])  # (C S^-1)^T G C
    return quadratic + jnp.trace(sandwich, axis1=-2, axis2=-1)


@jax.jit
def update_beta(state: CaviState, data: CaviData, hyper: CaviHyper) -> CaviState:
    """Update q(beta) (not in the thesis, which fixes beta); a no-op when beta is fixed.

    .. math::

        \\hat a_\\beta = \\beta_{a0} + \\frac12\\sum_i n_i,\\quad
        \\hat b_\\beta = \\beta_{b0} + \\frac12\\sum_iE\\|y_i - \\Psi_iw_i\\|^2 .
    """
    shape = hyper.beta_a0 + 0.5 * jnp.sum(data.num_obs)
    rate = hyper.beta_b0 + 0.5 * jnp.sum(data_quadratic(state, data))
    learned = state.beta_learned
    return state._replace(
        beta_shape=jnp.where(learned, shape, state.beta_shape),
        beta_rate=jnp.where(learned, rate, state.beta_rate),
    )


@jax.jit
def update_z(state: CaviState, data: CaviData, hyper: CaviHyper) -> CaviState:
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
    st = expected_stats(state, hyper, logs=True)
    logits = st.log_pi_mean[None] + 0.5 * d * st.log_alpha_mean[None] - 0.5 * st.alpha_mean[None] * st.residual_sq
    logits = jnp.where(state.active[None], logits, -jnp.inf)
    return state._replace(resp=jax.nn.softmax(logits, axis=1))


@jax.jit
def update_pi(state: CaviState, data: CaviData, hyper: CaviHyper) -> CaviState:
    """Update q(pi) = Dir(kappa_hat), :math:`\\hat\\kappa_k = \\kappa_0 + \\sum_i r_{ik}`.

    The thesis has no prior on pi and sets :math:`\\pi_k = \\frac1L\\sum_i r_{ik}`
    (App. B.2), the mode of this Dirichlet in the limit :math:`\\kappa_0 \\to 1`
    and its mean in the limit :math:`\\kappa_0 \\to 0`.
    """
    del data
    st = expected_stats(state, hyper)
    return state._replace(pi_conc=hyper.kappa0 + jnp.sum(st.resp, axis=0))


@jax.jit
def prune(state: CaviState, hyper: CaviHyper) -> CaviState:
    """Remove components with :math:`N_k = \\sum_i r_{ik}` below ``hyper.prune_threshold`` (Sec. 4.2.1).

    Equivalently :math:`E[\\pi_k] < (\\kappa_0 + \\text{threshold})/\\sum_j\\hat\\kappa_j`,
    or the thesis's :math:`\\pi_k = N_k/L` below threshold / L.  The component with
    the largest :math:`N_k` is never removed.  The responsibilities are
    renormalised over the remaining components and q(pi) is updated.
    Not a CAVI update (it changes the family), so the bound may move slightly.
    A no-op for the single type.
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


#: Every update in sweep order: ``w, b, M, h, lam, alpha`` (the order of Sec. 4.1.1), ``beta``, then ``z, pi``.
UPDATES = {
    "w": update_w,
    "b": update_b,
    "M": update_M,
    "h": update_h,
    "lam": update_lam,
    "alpha": update_alpha,
    "beta": update_beta,
    "z": update_z,
    "pi": update_pi,
}


#: The sweep of the joint local family (single type): q(w_i, h_i) together, then the global factors.
JOINT_UPDATES = {
    "wh": update_wh,
    "b": update_b,
    "M": update_M,
    "lam": update_lam,
    "alpha": update_alpha,
    "beta": update_beta,
}


def updates_for(state: CaviState) -> dict:
    """The updates of :data:`UPDATES` that apply to ``state``, in sweep order: name -> update.

    ``beta`` is a no-op when beta is fixed; ``z`` and ``pi`` only for the mixture; the
    joint local family (``state.wh_cov``) sweeps :data:`JOINT_UPDATES`.
    """
    if state.wh_cov is not None:
        return dict(JOINT_UPDATES)
    if state.resp is not None:
        return dict(UPDATES)
    return {name: update for name, update in UPDATES.items() if name not in ("z", "pi")}

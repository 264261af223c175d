r"""What a fitted CAVI family offers: draws, log density, point estimates and summaries.

Draws and point estimates follow ``CONTRACTS.md``: the single type (``resp``
None) has no component axis and no ``pi`` or ``z``; the mixture has them.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference.cavi.data import EigenCovariance, cov_matrices
from lmpromp_ppl.inference.cavi.state import CaviState, cross_solve

__all__ = [
    "sample_q",
    "log_q",
    "log_q_locals",
    "point_estimate",
    "w_covariance",
    "responsibilities",
    "active_components",
    "active_latent_dims",
]


def w_covariance(state: CaviState) -> Array:
    """The marginal weight covariances :math:`\\Sigma_{w_i}` as (L, d, d) matrices, whatever the storage.

    In the joint local family this is :math:`W_i + C_iS_i^{-1}C_i^T` (:mod:`.state`).
    """
    cov = cov_matrices(state.w_cov)
    if state.wh_cov is None:
        return cov
    return cov + jnp.einsum("idv,iev->ide", cross_solve(state), state.wh_cov[:, 0])


def responsibilities(state: CaviState) -> np.ndarray:
    """(L, K) responsibilities :math:`q(z_i = k)` (0 for removed components)."""
    if state.resp is None:
        raise LmprompError("a single-type state has no responsibilities")
    return np.asarray(jnp.where(state.active[None], state.resp, 0.0))


def _squeeze(draws: dict[str, Array], single: bool, axis: dict[str, int]) -> dict[str, Array]:
    if not single:
        return draws
    return {k: (jnp.squeeze(v, axis=axis[k]) if k in axis else v) for k, v in draws.items()}


@partial(jax.jit, static_argnames="num_draws")
def _gamma_draws(key: Array, shapes: Array, num_draws: int) -> Array:
    """(num_draws, n) standard Gamma draws; one compiled sampler for every Gamma factor (costly to compile)."""
    return jax.random.gamma(key, shapes, (num_draws,) + shapes.shape)


def sample_q(key: Array, state: CaviState, num_draws: int, learned_beta: bool | None = None) -> dict[str, Array]:
    """Independent draws from q with a leading draw axis.

    Mixture: ``pi`` (n, K), ``b`` (n, K, d), ``M`` (n, K, d, V), ``lam`` (n, K, V),
    ``alpha`` (n, K), ``h`` (n, L, K, V), ``w`` (n, L, d), ``z`` (n, L) (int,
    from q(z)), and ``beta`` (n,) when learned.  ``pi`` is drawn from q(pi)
    restricted to the active components (a Dirichlet over them; 0 for removed
    ones); removed components' other draws come from their frozen factors.
    Single type: no ``pi``, ``z`` and no component axis.

    ``learned_beta`` says whether to draw ``beta``; by default it is read from
    the state, which needs a concrete state (pass it under ``jax.vmap`` or ``jit``).
    """
    key, k_g = jax.random.split(key)
    # one compiled Gamma sampler per number of Gamma factors (costly to compile); q(beta) is
    # always drawn so that fixed and learned beta share it, and dropped when beta is fixed
    shapes = [state.alpha_shape, state.lam_shape.reshape(-1), state.beta_shape[None]]
    if state.resp is not None:
        shapes.append(state.pi_conc)
    gammas = _gamma_draws(k_g, jnp.concatenate(shapes), num_draws)
    learned = bool(state.beta_learned) if learned_beta is None else bool(learned_beta)
    return _sample(key, state, gammas, num_draws, learned)


@partial(jax.jit, static_argnames=("num_draws", "learned"))
def _sample(key: Array, state: CaviState, gammas: Array, num_draws: int, learned: bool) -> dict[str, Array]:
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
    if state.wh_cov is not None:  # joint local family: w_i | h_i has mean mu_w + C S^-1 (h - mu_h)
        w = w + jnp.einsum("idv,niv->nid", cross_solve(state), h[:, :, 0] - state.h_mean[:, 0])
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


@jax.jit
def log_q(state: CaviState, draws: dict[str, Array]) -> Array:
    r"""log q of draws (leading draw axis, the sites of :func:`sample_q`), active components only.

    Every factor of the family: q(w_i) (q(w_i | h_i) in the joint local family), q(h_ik), q(b_k), q(M_k) (column- or
    row-wise), q(alpha_k), q(lam_k), q(beta) when learned, and for the mixture
    q(pi) and q(z).  Used for PSIS k-hat (:mod:`lmpromp_ppl.diagnostics.metrics`).
    Compiled as one program (op by op it took 5 s of a compare report).
    """
    import numpyro.distributions as dist

    mix = state.resp is not None
    act = state.active
    comp = (lambda x: x) if mix else (lambda x: x[:, None])  # noqa: E731
    on = lambda x, axes: jnp.where(act, x, 0.0).sum(axes)  # noqa: E731  (sum over active components)
    M = comp(draws["M"])
    if state.M_var.ndim == 3:  # rows of M_k ~ N(mu_k,j., Sigma_Mk)
        log_M = dist.MultivariateNormal(state.M_mean, state.M_var[:, None]).log_prob(M).sum(-1)
    else:
        log_M = dist.Normal(state.M_mean, jnp.sqrt(state.M_var)[:, None, :]).log_prob(M).sum((-2, -1))
    terms = [
        log_q_locals(state, draws),
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


def log_q_locals(state: CaviState, draws: dict[str, Array]) -> Array:
    """log q of the local factors at draws of ``w`` and ``h`` (leading draw axis), summed over demonstrations.

    Mean-field: q(w_i) q(h_ik) over active components; joint local family: q(h_i) q(w_i | h_i).
    """
    import numpyro.distributions as dist

    mix = state.resp is not None
    h = draws["h"] if mix else draws["h"][:, :, None]
    log_h = jnp.where(state.active, dist.MultivariateNormal(state.h_mean, state.h_cov).log_prob(h), 0.0).sum((-2, -1))
    if state.wh_cov is None:
        return log_h + dist.MultivariateNormal(state.w_mean, w_covariance(state)).log_prob(draws["w"]).sum(-1)
    mean = state.w_mean + jnp.einsum("idv,niv->nid", cross_solve(state), h[:, :, 0] - state.h_mean[:, 0])
    return log_h + dist.MultivariateNormal(mean, cov_matrices(state.w_cov)).log_prob(draws["w"]).sum(-1)


def point_estimate(state: CaviState) -> dict[str, Array]:
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


def active_components(state: CaviState) -> list[int]:
    """Indices of the components that were not removed (Sec. 4.2.1)."""
    return [int(k) for k in np.flatnonzero(np.asarray(state.active))]


def active_latent_dims(state: CaviState, threshold: float = 1e-3) -> list[int] | list[list[int]]:
    r"""Latent dimensions that ARD left switched on (per component for the mixture).

    Column v of component k is active when it passes both

    * the relative rule :math:`1/E[\lambda_{kv}] > \text{threshold}\cdot\max_u 1/E[\lambda_{ku}]`, and
    * the absolute rule :math:`\lVert E[m_{kv}] \rVert^2 > \operatorname{tr}\operatorname{Cov}_q(m_{kv})`:
      the column's mean stands out of its own posterior spread, i.e. q says the
      column is not zero.

    The relative rule alone cannot say "none": when the data switch every column
    off, all :math:`E[\lambda_v]` sit near the same large value (near
    :math:`c_0/d_0` under the thesis prior) and each passes.  A switched-off
    column has :math:`E[m_v] \approx 0` and a posterior spread of the order of
    its prior's, so the absolute rule fails for it whatever the units of the
    data; a column that explains data has a mean far outside its spread.

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

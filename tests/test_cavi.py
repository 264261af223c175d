"""Proofs for the hand-derived CAVI engine (issue 4; docs/derivation.md).

* monotone: the ELBO never decreases after any single factor update;
* stationary: after each update the autodiff gradient of the closed-form ELBO
  with respect to that factor's own parameters vanishes; the thesis's versions
  of the corrected updates do not pass this test;
* same model as NumPyro: the closed-form ELBO equals a Monte Carlo estimate
  of E_q[log p(y, theta) - log q(theta)] with log p from the declared model;
* recovery of M's column space, alpha, and ARD on synthetic data;
* the shared-Psi fast path equals the general path; no retracing; restarts;
  ConvergenceWarning; input validation.
"""

import io
import math
import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import numpyro.distributions as dist
import pytest
import scipy.linalg
from jax.scipy.special import digamma
from numpyro.infer.util import log_density

from lmpromp_ppl.basis import design_matrix
from lmpromp_ppl.data import Demonstrations, ModelData, load_dataset, model_data, standardise
from lmpromp_ppl.errors import ConvergenceWarning, DataError, LmprompError
from lmpromp_ppl.inference import cavi
from lmpromp_ppl.inference.cavi import init_state
from lmpromp_ppl.inference.cavi.data import gram_quadratic, gram_trace
from lmpromp_ppl.inference.cavi.kernels import w_posterior
from lmpromp_ppl.models.hyper import Hyperparameters
from lmpromp_ppl.models.lmpromp import lmpromp_model

D, J, V = 2, 5, 2
TRUE_ALPHA, TRUE_BETA = 100.0, 400.0
SCALES = np.array([2.0, 1.0])  # column norms of the true M: well separated from each other and the noise


def _latent_data(seed: int, L: int, T: int, width: float):
    """Synthetic LMProMP data with a shared design matrix (thesis eq. 4.1)."""
    rng = np.random.default_rng(seed)
    d = D * J
    b = rng.standard_normal(d)
    directions, _ = np.linalg.qr(rng.standard_normal((d, V)))
    M = directions * SCALES
    h = rng.standard_normal((L, V))
    w = b + h @ M.T + rng.standard_normal((L, d)) / np.sqrt(TRUE_ALPHA)
    psi = np.asarray(design_matrix(np.linspace(0.0, 1.0, T), D, J, width))
    y = w @ psi.T + rng.standard_normal((L, T * D)) / np.sqrt(TRUE_BETA)
    data = ModelData(
        jnp.asarray(np.broadcast_to(psi, (L,) + psi.shape).copy()), jnp.asarray(y), jnp.ones((L, T * D))
    )
    return data, {"b": b, "M": M, "h": h, "w": w}


def _with_missing(data: ModelData, seed: int, fraction: float) -> ModelData:
    """Drop a random fraction of entries and truncate demonstration 0 (ragged + missing)."""
    rng = np.random.default_rng(seed)
    mask = (rng.uniform(size=data.mask.shape) > fraction).astype(float)
    mask[0, mask.shape[1] // 2 :] = 0.0
    y = np.where(mask > 0, np.asarray(data.y), np.nan)  # NaN at missing entries is allowed
    return ModelData(data.psi, jnp.asarray(y), jnp.asarray(mask))


HYPER = Hyperparameters(beta=TRUE_BETA, latent_dim=V)
HYPER_ARR = cavi.hyper_arrays(HYPER)


@pytest.fixture(scope="module")
def small():
    """L=8 demonstrations, shared design (fast path) and with missing entries (general path)."""
    data, truth = _latent_data(seed=1, L=8, T=12, width=0.5)
    return {"shared": data, "missing": _with_missing(data, seed=2, fraction=0.2), "truth": truth}


def _real(spec: str, num_demos: int, every: int, num_basis: int) -> ModelData:
    demos = load_dataset(spec)
    demos = demos.subset(np.arange(num_demos))
    demos = Demonstrations(
        times=tuple(t[::every] for t in demos.times),
        positions=tuple(y[::every] for y in demos.positions),
        dof_names=demos.dof_names,
        name=demos.name,
    )
    demos, _ = standardise(demos)
    return model_data(demos, num_basis)


@pytest.fixture(scope="module")
def datasets(small):
    return {
        "synthetic-shared": small["shared"],
        "synthetic-missing": small["missing"],
        "lasa": _real("lasa:GShape?every=50", num_demos=7, every=1, num_basis=5),
        "gunpoint": _real("gunpoint", num_demos=8, every=10, num_basis=5),
    }


# --------------------------------------------------------------------------- compiled helpers
@jax.jit
def _sweep_elbos(state, data, hyper):
    """ELBO before and after each single-factor update of one sweep.

    A scan over ``lax.switch`` compiles the bound and each update once.
    """
    branches = [lambda s, u=u: u(s, data, hyper) for u in cavi.updates_for(state).values()]

    def one(state, index):
        state = jax.lax.switch(index, branches, state)
        return state, cavi.elbo(state, data, hyper)

    first = cavi.elbo(state, data, hyper)
    state, values = jax.lax.scan(one, state, jnp.arange(len(branches)))
    return state, jnp.concatenate([first[None], values])


#: The state's parameters (its boolean flags and the absent mixture factors are not parameters).
PARAMETERS = ("w_mean", "w_cov", "h_mean", "h_cov", "b_mean", "b_var", "M_mean", "M_var",
              "alpha_shape", "alpha_rate", "lam_shape", "lam_rate", "beta_shape", "beta_rate")


def _elbo_of(params, state, data, hyper):
    return cavi.elbo(state._replace(**params), data, hyper)


_elbo_grad_params = jax.jit(jax.value_and_grad(_elbo_of))


def _elbo_grad(state, data, hyper):
    """The bound and its gradient with respect to every parameter (a dict by field name)."""
    return _elbo_grad_params({name: getattr(state, name) for name in PARAMETERS}, state, data, hyper)

FACTOR_FIELDS = {
    "w": ("w_mean", "w_cov"),
    "b": ("b_mean", "b_var"),
    "M": ("M_mean", "M_var"),
    "h": ("h_mean", "h_cov"),
    "lam": ("lam_shape", "lam_rate"),
    "alpha": ("alpha_shape", "alpha_rate"),
}


#: The factors of the thesis's single-type family (eq. 4.3), fixed beta.
SINGLE_FACTORS = list(FACTOR_FIELDS)


def _single(state):
    """The K = 1 state's factors without the component axis, as eq. 4.3 and App. C.1 write them."""
    fields = {name: getattr(state, name) for name in (
        "h_mean", "h_cov", "b_mean", "b_var", "M_mean", "M_var", "alpha_shape", "alpha_rate", "lam_shape", "lam_rate")}
    squeezed = {name: (value[:, 0] if name.startswith("h_") else value[0]) for name, value in fields.items()}
    return state._replace(**squeezed)


def _grad_norm(state, data, factor):
    value, grad = _elbo_grad(state, data, HYPER_ARR)
    leaves = jax.tree.leaves([grad[f] for f in FACTOR_FIELDS[factor]])
    return float(value), float(np.sqrt(sum(np.sum(np.asarray(g) ** 2) for g in leaves)))


def _stationary(before_norm, after_norm, value):
    return after_norm <= 1e-6 * before_norm + 1e-9 * (1.0 + abs(value))


# --------------------------------------------------------------------------- monotone
@pytest.mark.parametrize("name", ["synthetic-shared", "synthetic-missing", "lasa", "gunpoint"])
def test_elbo_never_decreases_after_any_factor_update(datasets, name):
    data = cavi.sufficient_statistics(datasets[name])
    hyper = HYPER if name.startswith("synthetic") else Hyperparameters(latent_dim=V)
    hyper_arr = cavi.hyper_arrays(hyper)
    state = init_state(data, hyper, key=jax.random.key(3))  # a perturbed start: far from optimal
    increases = []
    for _ in range(25):
        state, values = _sweep_elbos(state, data, hyper_arr)
        values = np.asarray(values)
        assert np.all(np.isfinite(values))
        change = np.diff(values)
        assert np.all(change >= -1e-10 * np.abs(values[:-1])), (name, change)
        increases.append(values[-1] - values[0])
    assert increases[0] > 0  # the check is not vacuous: the bound moved


# --------------------------------------------------------------------------- stationary
@pytest.fixture(scope="module")
def midway(small):
    """A state on the general path two sweeps after a perturbed start: no factor is optimal."""
    data = cavi.sufficient_statistics(small["missing"])
    state = init_state(data, HYPER, key=jax.random.key(4))
    for _ in range(2):
        state, _ = _sweep_elbos(state, data, HYPER_ARR)
    return data, _perturb(state, seed=4)


def _perturb(state, seed):
    """An arbitrary valid non-optimal state: shifted means, rescaled covariances and Gammas."""
    rng = np.random.default_rng(seed)
    shift = lambda a, scale: a + scale * rng.standard_normal(a.shape)  # noqa: E731
    return state._replace(
        w_mean=shift(state.w_mean, 0.1),
        w_cov=cavi.FullCovariance(1.7 * cavi.w_covariance(state)),
        h_mean=shift(state.h_mean, 0.3),
        h_cov=0.6 * state.h_cov,
        b_mean=shift(state.b_mean, 0.1),
        b_var=3.0 * state.b_var,
        M_mean=shift(state.M_mean, 0.1),
        M_var=2.0 * state.M_var,
        alpha_shape=0.5 * state.alpha_shape,
        alpha_rate=0.7 * state.alpha_rate,
        lam_shape=1.3 * state.lam_shape,
        lam_rate=1.5 * state.lam_rate,
    )


@pytest.mark.parametrize("factor", SINGLE_FACTORS)
def test_each_update_is_stationary_by_autodiff(midway, factor):
    data, state = midway
    _, before = _grad_norm(state, data, factor)
    assert before > 1e-6  # not stationary before the update
    updated = cavi.UPDATES[factor](state, data, HYPER_ARR)
    value, after = _grad_norm(updated, data, factor)
    assert _stationary(before, after, value), (factor, before, after)


def _thesis_M_mean(state, data, hyper):
    """Sec. 4.1.1 / App. B.1: mu_m_v = sigma_m_v sum_i alpha mu_h_vi (mu_w_i - mu_b), no coupling."""
    stats = cavi.expected_stats(state, hyper)
    state = cavi.update_M(state, data, hyper)  # sigma_m (correct in the thesis), then the thesis mean
    R = (state.w_mean - state.b_mean[0]).T @ state.h_mean[:, 0]
    return state._replace(M_mean=(state.M_var[0] * stats.alpha_mean[0] * R)[None])


def _thesis_b_var(state, data, hyper):
    """App. B.1: sigma_b = L alpha + lambda0 (without the inverse)."""
    state = cavi.update_b(state, data, hyper)
    precision = 1.0 / state.b_var
    return state._replace(b_mean=state.b_mean * precision**2, b_var=precision)


def _without_d(state):
    """E[M^T M] without the factor d (as App. C.1 writes it)."""
    d = state.M_mean.shape[1]
    return state._replace(M_var=state.M_var / d)


def _h_without_d(state, data, hyper):
    updated = cavi.update_h(_without_d(state), data, hyper)
    return state._replace(h_mean=updated.h_mean, h_cov=updated.h_cov)


def _alpha_without_d(state, data, hyper):
    updated = cavi.update_alpha(_without_d(state), data, hyper)
    return state._replace(alpha_shape=updated.alpha_shape, alpha_rate=updated.alpha_rate)


@pytest.mark.parametrize(
    "factor, thesis_update",
    [
        ("M", _thesis_M_mean),  # erratum 1: the coupling to the other columns is missing
        ("b", _thesis_b_var),  # erratum 2: sigma_b without its inverse
        ("h", _h_without_d),  # Sigma_h with Sigma_M in place of d Sigma_M (C.1's expectation)
        ("alpha", _alpha_without_d),  # b_bar with Sigma_M in place of d Sigma_M (C.1's expectation)
    ],
)
def test_thesis_versions_are_not_stationary(midway, factor, thesis_update):
    """The thesis's forms fail the test the corrected updates pass (errata 1, 2, and the d of C.1)."""
    data, state = midway
    _, before = _grad_norm(state, data, factor)
    value, after = _grad_norm(thesis_update(state, data, HYPER_ARR), data, factor)
    assert not _stationary(before, after, value)
    assert after > 1e-3 * before


def _thesis_c1_bound(state, data, hyper):
    """The lower bound exactly as App. C.1 writes it (its constants dropped)."""
    s = _single(state)
    d = s.M_mean.shape[0]
    alpha_bar = s.alpha_shape / s.alpha_rate
    e_log_alpha = digamma(s.alpha_shape) - jnp.log(s.alpha_rate)
    lam_bar = s.lam_shape / s.lam_rate
    e_log_lam = digamma(s.lam_shape) - jnp.log(s.lam_rate)
    sigma_M = jnp.diag(s.M_var)
    w_cov = cavi.w_covariance(s)
    gram = data.gram
    mean_gram = gram_quadratic(gram, s.w_mean)
    log_lik = -0.5 * hyper.beta * jnp.sum(
        -2.0 * jnp.sum(s.w_mean * data.psi_t_y, -1) + mean_gram + gram_trace(gram, s.w_cov)
    )
    C = jnp.sum((s.w_mean - s.b_mean - s.h_mean @ s.M_mean.T) ** 2, -1)
    bracket = (
        C + jnp.trace(w_cov, axis1=-2, axis2=-1) + d * s.b_var
        + jnp.einsum("iu,uv,iv->i", s.h_mean, sigma_M, s.h_mean)
        + jnp.einsum("uv,ivu->i", s.M_mean.T @ s.M_mean + sigma_M, s.h_cov)
    )
    log_p_w = jnp.sum(0.5 * d * e_log_alpha - 0.5 * alpha_bar * bracket)
    log_p_h = jnp.sum(-0.5 * hyper.gamma * (jnp.sum(s.h_mean**2, -1) + jnp.trace(s.h_cov, axis1=-2, axis2=-1)))
    log_p_b = -0.5 * hyper.lambda0 * (jnp.sum(s.b_mean**2) + d * s.b_var)
    log_p_M = jnp.sum(-0.5 * lam_bar * (jnp.sum(s.M_mean**2, 0) + d * s.M_var))
    log_p_alpha = (hyper.a0 - 1.0) * e_log_alpha - hyper.b0 * alpha_bar
    log_p_lam = jnp.sum((hyper.c0 - 1.0) * e_log_lam - hyper.d0 * lam_bar)
    neg_log_q = (
        0.5 * jnp.sum(jnp.linalg.slogdet(w_cov)[1]) + 0.5 * jnp.sum(jnp.linalg.slogdet(s.h_cov)[1])
        + 0.5 * d * jnp.log(s.b_var) + jnp.sum(0.5 * d * jnp.log(s.M_var))
        - (-jax.scipy.special.gammaln(s.alpha_shape) + jnp.log(s.alpha_rate)
           + (s.alpha_shape - 1.0) * digamma(s.alpha_shape) - s.alpha_shape)
        - jnp.sum(-jax.scipy.special.gammaln(s.lam_shape) + jnp.log(s.lam_rate)
                  + (s.lam_shape - 1.0) * digamma(s.lam_shape) - s.lam_shape)
    )
    return log_lik + log_p_w + log_p_h + log_p_b + log_p_M + log_p_alpha + log_p_lam + neg_log_q


def _c1_missing_terms(state):
    """What App. C.1 drops: (d - 1) times the Sigma_M terms of E log p(w) and (d/2) sum_v E log lam_v."""
    s = _single(state)
    d = s.M_mean.shape[0]
    alpha_bar = s.alpha_shape / s.alpha_rate
    hhT = s.h_cov + jnp.einsum("iu,iv->iuv", s.h_mean, s.h_mean)
    sigma_terms = jnp.einsum("v,ivv->", s.M_var, hhT)
    e_log_lam = digamma(s.lam_shape) - jnp.log(s.lam_rate)
    return -0.5 * alpha_bar * (d - 1) * sigma_terms + 0.5 * d * jnp.sum(e_log_lam)


def test_thesis_c1_bound_differs_by_more_than_constants(midway):
    """Erratum 4: C.1 minus our bound changes with q; adding back the dropped terms leaves a constant."""
    data, state = midway
    other = cavi.update_M(cavi.update_lam(state, data, HYPER_ARR), data, HYPER_ARR)
    gaps, corrected = [], []
    for s in (state, other):
        ours = float(cavi.elbo(s, data, HYPER_ARR))
        thesis = float(_thesis_c1_bound(s, data, HYPER_ARR))
        gaps.append(ours - thesis)
        corrected.append(ours - thesis - float(_c1_missing_terms(s)))
    assert abs(gaps[0] - gaps[1]) > 1e-3
    assert corrected[0] == pytest.approx(corrected[1], rel=0, abs=1e-8 * (1 + abs(gaps[0])))


# --------------------------------------------------------------------------- same model as NumPyro
def _log_q(state, draws):
    """log q(theta) of each draw from NumPyro distributions with q's parameters."""
    w_cov = cavi.w_covariance(state)
    state = _single(state)
    terms = [
        dist.MultivariateNormal(state.w_mean, w_cov).log_prob(draws["w"]).sum(-1),
        dist.MultivariateNormal(state.h_mean, state.h_cov).log_prob(draws["h"]).sum(-1),
        dist.Normal(state.b_mean, jnp.sqrt(state.b_var)).log_prob(draws["b"]).sum(-1),
        dist.Normal(state.M_mean, jnp.sqrt(state.M_var)).log_prob(draws["M"]).sum((-2, -1)),
        dist.Gamma(state.alpha_shape, state.alpha_rate).log_prob(draws["alpha"]),
        dist.Gamma(state.lam_shape, state.lam_rate).log_prob(draws["lam"]).sum(-1),
    ]
    return sum(terms)


NUM_DRAWS = 4000


@jax.jit
def _log_p_minus_log_q(draws, state, model_data_):
    log_p = jax.vmap(lambda p: log_density(lmpromp_model, (model_data_, HYPER), {}, p)[0])(draws)
    return log_p - _log_q(state, draws)


def _mc_elbo(key, state, model_data_):
    values = np.asarray(_log_p_minus_log_q(cavi.sample_q(key, state, NUM_DRAWS), state, model_data_))
    return values.mean(), values.std(ddof=1) / np.sqrt(NUM_DRAWS)


@pytest.mark.parametrize("which", ["converged-shared", "perturbed-missing"])
def test_closed_form_elbo_matches_numpyro_monte_carlo(small, which):
    if which == "converged-shared":
        data = small["shared"]
        state = cavi.fit(data, HYPER, jax.random.key(0)).state
    else:  # an arbitrary non-optimal state: shifted means, inflated covariances, moved Gammas
        data = small["missing"]
        state = _perturb(init_state(cavi.sufficient_statistics(data), HYPER, key=jax.random.key(5)), seed=6)
    closed = float(cavi.elbo(state, cavi.sufficient_statistics(data), HYPER_ARR))
    mean, standard_error = _mc_elbo(jax.random.key(7), state, data)
    assert abs(closed - mean) <= 4.0 * standard_error, (closed, mean, standard_error)
    # the test has the resolution to see the non-constant terms that App. C.1 drops
    assert 4.0 * standard_error < abs(float(_c1_missing_terms(state)))


# --------------------------------------------------------------------------- recovery
@pytest.fixture(scope="module")
def recovery():
    return _latent_data(seed=11, L=30, T=30, width=0.5)


def test_recovers_column_space_and_alpha(recovery):
    data, truth = recovery
    fit = cavi.fit(data, HYPER, jax.random.key(0))
    assert fit.converged
    learned = np.asarray(fit.state.M_mean[0])
    angles = scipy.linalg.subspace_angles(learned, truth["M"])
    # First-order PCA perturbation: sin(theta) ~ sqrt((d - V) s2 / (L m_V^2)) with per-weight
    # noise variance s2 <= 1/alpha + 1/(beta * min eig(Psi^T Psi)) ~ 0.025 (m_V = 1 is the
    # weaker column, L = 30, d = 10): about 0.08 rad (4.7 deg); we allow twice that.
    assert np.max(angles) < np.radians(10.0), np.degrees(angles)
    # alpha from ~ dL - d - dV - LV = 210 residual degrees of freedom: relative sd sqrt(2/210) ~ 0.1;
    # we allow 3 sd.
    alpha = float(cavi.point_estimate(fit.state)["alpha"])
    assert abs(alpha / TRUE_ALPHA - 1.0) < 0.3, alpha


def test_ard_switches_off_surplus_dimensions(recovery):
    """With V=4 > 2 true dimensions two columns are switched off.

    The column precisions need a vague Gamma prior for this (c0 = d0 = 1e-5, as the thesis's
    a0, b0): under Gamma(c0, d0) the posterior mean satisfies E[lam_v] <= (c0 + d/2)/d0, so
    with c0 = d0 = 1 no column can fall below the 1e-3 threshold of the contract.
    """
    data, truth = recovery
    hyper = HYPER.replace(latent_dim=4, c0=1e-5, d0=1e-5)
    fit = cavi.fit(data, hyper, jax.random.key(0))
    active = cavi.active_latent_dims(fit.state)
    assert len(active) == 2, (active, fit.state.lam_shape / fit.state.lam_rate)
    angles = scipy.linalg.subspace_angles(np.asarray(fit.state.M_mean[0])[:, active], truth["M"])
    assert np.max(angles) < np.radians(10.0)


def _state_with_columns(state, lam_mean, scale):
    """``state`` with E[lam_v] = ``lam_mean``, q(m_v) = N(scale_v * 1, 1/lam_v I) (shape kept)."""
    lam_mean = jnp.asarray(lam_mean, dtype=float)
    d = state.M_mean.shape[1]
    M_mean = jnp.ones((1, d, 1)) * jnp.asarray(scale, dtype=float)[None, None, :]
    return state._replace(lam_rate=state.lam_shape / lam_mean, M_mean=M_mean, M_var=(1.0 / lam_mean)[None])


def test_ard_reports_none_active_when_every_column_is_off(midway):
    """All E[lam_v] ~ 1400 and E[m_v] ~ 0 (every column switched off): no dimension is active,
    although each passes the relative rule; columns whose mean stands out of q's spread are reported."""
    _, state = midway
    V = state.lam_shape.shape[1]
    lam_off = np.linspace(1380.0, 1420.0, V)
    off = _state_with_columns(state, lam_off, np.full(V, 1e-3))
    inverse = 1.0 / lam_off
    assert np.all(inverse > 1e-3 * inverse.max())  # the relative rule alone would say "all"
    assert cavi.active_latent_dims(off) == []
    mixed = _state_with_columns(state, [2.0] + [1400.0] * (V - 1), [1.0] + [1e-3] * (V - 1))
    assert cavi.active_latent_dims(mixed) == [0]
    on = _state_with_columns(state, np.linspace(0.5, 20.0, V), np.linspace(2.0, 0.5, V))
    assert cavi.active_latent_dims(on) == list(range(V))
    # the rule is unit-free: a small but well-determined column (entries 0.01, s.d. 0.001) is active
    small = _state_with_columns(state, [1e6] * V, [1e-2] * V)
    assert cavi.active_latent_dims(small) == list(range(V))


def test_ard_on_a_fit_without_structure_reports_none(recovery):
    """Demonstrations that differ only by noise: CAVI switches every column off and says so,
    while the fit with two true dimensions (test above) reports them."""
    data, _ = recovery
    mean = np.nanmean(np.asarray(data.y), axis=0, keepdims=True)
    noise = 0.01 * np.random.default_rng(5).normal(size=np.shape(data.y))
    flat = data._replace(y=jnp.asarray(np.where(np.asarray(data.mask), mean + noise, 0.0)))
    fit = cavi.fit(flat, HYPER.replace(latent_dim=3), jax.random.key(0))
    lam = np.asarray(fit.state.lam_shape / fit.state.lam_rate)
    assert np.all(lam > 100.0), lam  # ARD switched every column off
    assert cavi.active_latent_dims(fit.state) == []


# --------------------------------------------------------------------------- engineering
def test_shared_psi_fast_path_equals_general_path(small):
    data = small["shared"]
    fast, general = cavi.sufficient_statistics(data, shared_psi=True), cavi.sufficient_statistics(data, shared_psi=False)
    assert isinstance(fast.gram, cavi.SharedGram) and isinstance(general.gram, cavi.DemoGrams)
    start_fast = init_state(fast, HYPER, key=jax.random.key(8))
    start_general = init_state(general, HYPER, key=jax.random.key(8))
    assert isinstance(start_fast.w_cov, cavi.EigenCovariance)
    # the same number of plain sweeps on both paths (tol < 0 never stops early), so that the states
    # are compared at the same point of the same iteration; max_iter as in cavi.fit's default.  The
    # eigen-direction scaling exists on the fast path only (tests/test_cavi_transform.py compares the
    # paths' optima with the accelerations)
    plain = cavi.hyper_arrays(HYPER, accelerate="none")
    out_fast = cavi.run(start_fast, fast, plain, -1.0, 2000)
    out_general = cavi.run(start_general, general, plain, -1.0, 2000)
    n = min(int(out_fast.iterations), int(out_general.iterations))
    assert n == 2000
    np.testing.assert_allclose(out_fast.elbo_trace[:n], out_general.elbo_trace[:n], rtol=1e-9)
    for field in cavi.CaviState._fields:
        a, b = getattr(out_fast.state, field), getattr(out_general.state, field)
        if field == "w_cov":
            a, b = cavi.w_covariance(out_fast.state), cavi.w_covariance(out_general.state)
        elif a is None or np.asarray(a).dtype == bool:  # no q(z), q(pi); the structural flags
            assert (a is None and b is None) or np.array_equal(a, b), field
            continue
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * float(np.max(np.abs(b))), err_msg=field)


def test_fast_path_accepts_per_demonstration_prior_precision(small):
    """Mixture-ready: a different prior precision per demonstration stays diagonal in the U basis."""
    data = small["shared"]
    fast, general = cavi.sufficient_statistics(data, shared_psi=True), cavi.sufficient_statistics(data, shared_psi=False)
    L, d = data.psi.shape[0], data.psi.shape[2]
    precision = jnp.linspace(0.5, 50.0, L)
    linear = jnp.asarray(np.random.default_rng(9).standard_normal((L, d)))
    mean_f, cov_f = w_posterior(fast, HYPER_ARR.beta, precision, linear)
    mean_g, cov_g = w_posterior(general, HYPER_ARR.beta, precision, linear)
    np.testing.assert_allclose(mean_f, mean_g, rtol=1e-9, atol=1e-12)
    full_f = jnp.einsum("dj,ij,ej->ide", cov_f.basis, cov_f.variances, cov_f.basis)
    np.testing.assert_allclose(full_f, cov_g.matrices, rtol=1e-9, atol=1e-12)


def test_step_does_not_recompile(small):
    data = cavi.sufficient_statistics(small["shared"])
    traces = []

    def counted(state, data, hyper):
        traces.append(None)
        return cavi.step(state, data, hyper)

    jitted = jax.jit(counted)
    state = init_state(data, HYPER)
    state, info = jitted(state, data, HYPER_ARR)
    state, info2 = jitted(state, data, HYPER_ARR)  # state out has the dtypes of state in
    jitted(state, data, cavi.hyper_arrays(HYPER.replace(beta=50.0)))  # new values, same trace
    assert len(traces) == 1
    assert info2.elbo >= info.elbo
    assert state.alpha_shape.dtype == jnp.float64 and not state.alpha_shape.weak_type


def test_restarts_keep_the_best_elbo(small):
    fit = cavi.fit(small["shared"], HYPER, jax.random.key(1), num_restarts=3)
    assert len(fit.restart_elbos) == 3
    assert len(set(fit.restart_elbos)) > 1  # restarts start from different points
    assert fit.elbo == max(fit.restart_elbos)
    assert fit.elbo == pytest.approx(float(cavi.elbo(fit.state, cavi.sufficient_statistics(small["shared"]), HYPER_ARR)), rel=1e-12)
    assert fit.elbo_trace.shape == (fit.iterations,) and fit.elbo_trace[-1] == fit.elbo
    assert fit.seconds > 0 and fit.compile_seconds >= 0


def test_max_iter_warns_and_progress_chunks_agree(small, monkeypatch):
    # 100 sweeps from the start do not reach a relative change of 1e-14; with progress the
    # loop runs in two chunks of 50 that must continue exactly where the first stopped
    with pytest.warns(ConvergenceWarning):
        fit = cavi.fit(small["missing"], HYPER, jax.random.key(0), max_iter=100, tol=1e-14)
    assert fit.iterations == 100 and not fit.converged and fit.elbo_trace.shape == (100,)

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    terminal = Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)  # progress bars are drawn on a terminal only
    with pytest.warns(ConvergenceWarning):
        chunked = cavi.fit(
            small["missing"], HYPER, jax.random.key(0), max_iter=100, tol=1e-14, progress=True
        )
    assert "50/100" in terminal.getvalue()  # the bar after the first chunk
    np.testing.assert_allclose(chunked.elbo_trace, fit.elbo_trace, rtol=1e-12)


def test_converged_fit_does_not_warn(small):
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)
        fit = cavi.fit(small["shared"], HYPER, jax.random.key(0))
    assert fit.converged and fit.iterations < 2000
    assert np.all(np.diff(fit.elbo_trace) >= -1e-10 * np.abs(fit.elbo_trace[1:]))


def test_posterior_summaries_have_contract_shapes(small):
    state = init_state(cavi.sufficient_statistics(small["missing"]), HYPER)
    L, d = small["missing"].psi.shape[0], small["missing"].psi.shape[2]
    n = NUM_DRAWS  # the Gamma sampler compiled for the Monte Carlo test is reused
    draws = cavi.sample_q(jax.random.key(0), state, n)
    shapes = {"b": (n, d), "M": (n, d, V), "h": (n, L, V), "w": (n, L, d), "alpha": (n,), "lam": (n, V)}
    assert {k: v.shape for k, v in draws.items()} == shapes
    assert {k: v.shape for k, v in cavi.point_estimate(state).items()} == {k: s[1:] for k, s in shapes.items()}


def test_invalid_input_is_refused(small):
    data = small["shared"]
    with pytest.raises(LmprompError, match="fewer demonstrations"):
        cavi.fit(data, HYPER.replace(latent_dim=9), jax.random.key(0))
    bad = ModelData(data.psi, data.y.at[0, 0].set(jnp.nan), data.mask)
    with pytest.raises(DataError, match="NaN"):
        cavi.fit(bad, HYPER, jax.random.key(0))
    with pytest.raises(DataError, match="share"):
        cavi.sufficient_statistics(small["missing"], shared_psi=True)
    with pytest.raises(LmprompError, match="max_iter"):
        cavi.fit(data, HYPER, jax.random.key(0), max_iter=0)
    # NaN at masked (missing) entries is allowed
    assert math.isfinite(cavi.fit(small["missing"], HYPER, jax.random.key(0), tol=1.0).elbo)

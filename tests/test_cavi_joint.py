"""The joint local family q(w_i, h_i) of the CAVI engine: the proofs of ``docs/derivation.md`` (structured family).

* every update of the joint sweep never lowers the closed-form bound, on synthetic
  and real data, on both data paths;
* each update is stationary by autodiff of the bound, in every parameter of its factor;
* the closed-form bound equals a Monte Carlo ELBO of the NumPyro declaration
  (independent log q of the joint Gaussian) within 4 standard errors;
* with the global factors at point masses the joint factor is the exact posterior of
  (w_i, h_i) (brute-force Gaussian conditioning), which the mean-field family is not;
* the fast path equals the general path, and the accelerations keep their optimum.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import numpyro.distributions as dist
import pytest
from numpyro.infer.util import log_density
from test_cavi import (  # noqa: F401  (small is a fixture)
    HYPER,
    HYPER_ARR,
    _perturb,
    _real,
    _stationary,
    _sweep_elbos,
    small,
)

from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference import cavi
from lmpromp_ppl.inference.cavi import init_state
from lmpromp_ppl.models.hyper import Hyperparameters
from lmpromp_ppl.models.lmpromp import lmpromp_model

V = HYPER.latent_dim


def _joint_start(data, hyper, seed, family="columnwise"):
    return cavi.with_joint_locals(init_state(data, hyper, key=jax.random.key(seed), family=family))


@pytest.mark.parametrize("name", ["synthetic-shared", "synthetic-missing", "lasa", "gunpoint"])
def test_joint_sweep_never_lowers_the_bound(small, name):
    model_data = {
        "synthetic-shared": lambda: small["shared"],
        "synthetic-missing": lambda: small["missing"],
        "lasa": lambda: _real("lasa:GShape?every=50", num_demos=7, every=1, num_basis=5),
        "gunpoint": lambda: _real("gunpoint", num_demos=8, every=10, num_basis=5),
    }[name]()
    data = cavi.sufficient_statistics(model_data)
    hyper = HYPER if name.startswith("synthetic") else Hyperparameters(latent_dim=V)
    hyper_arr = cavi.hyper_arrays(hyper)
    state = _joint_start(data, hyper, 3)
    assert list(cavi.updates_for(state)) == ["wh", "b", "M", "lam", "alpha", "beta"]
    increases = []
    for _ in range(25):
        state, values = _sweep_elbos(state, data, hyper_arr)
        values = np.asarray(values)
        assert np.all(np.isfinite(values))
        assert np.all(np.diff(values) >= -1e-10 * np.abs(values[:-1])), (name, np.diff(values))
        increases.append(values[-1] - values[0])
    assert increases[0] > 0


# --------------------------------------------------------------------------- stationarity
JOINT_FIELDS = {
    "wh": ("w_mean", "w_cov", "h_mean", "h_cov", "wh_cov"),
    "b": ("b_mean", "b_var"),
    "M": ("M_mean", "M_var"),
    "lam": ("lam_shape", "lam_rate"),
    "alpha": ("alpha_shape", "alpha_rate"),
    "beta": ("beta_shape", "beta_rate"),
}
PARAMETERS = sorted({f for fields in JOINT_FIELDS.values() for f in fields})


def _elbo_of(params, state, data, hyper):
    return cavi.elbo(state._replace(**params), data, hyper)


_value_and_grad = jax.jit(jax.value_and_grad(_elbo_of))


def _grad_norm(state, data, hyper_arr, factor):
    value, grad = _value_and_grad({name: getattr(state, name) for name in PARAMETERS}, state, data, hyper_arr)
    leaves = jax.tree.leaves([grad[f] for f in JOINT_FIELDS[factor]])
    return float(value), float(np.sqrt(sum(np.sum(np.asarray(g) ** 2) for g in leaves)))


@pytest.fixture(scope="module")
def midway(small):
    """A joint state on the general path with learned beta, two sweeps after a perturbed start, perturbed again."""
    data = cavi.sufficient_statistics(small["missing"])
    hyper = Hyperparameters(beta=400.0, latent_dim=V, learn_beta=True)
    hyper_arr = cavi.hyper_arrays(hyper)
    state = _joint_start(data, hyper, 4, family="rowwise")
    for _ in range(2):
        state, _ = _sweep_elbos(state, data, hyper_arr)
    joint = state.wh_cov
    state = _perturb(state._replace(wh_cov=None), seed=4)  # the mean-field factors as test_cavi perturbs them
    rng = np.random.default_rng(5)
    state = state._replace(wh_cov=0.5 * joint + 1e-3 * rng.standard_normal(joint.shape),
                           beta_shape=0.8 * state.beta_shape)
    return data, hyper_arr, state


@pytest.mark.parametrize("factor", list(JOINT_FIELDS))
def test_each_joint_update_is_stationary_by_autodiff(midway, factor):
    data, hyper_arr, state = midway
    _, before = _grad_norm(state, data, hyper_arr, factor)
    assert before > 1e-6
    updated = cavi.JOINT_UPDATES[factor](state, data, hyper_arr)
    value, after = _grad_norm(updated, data, hyper_arr, factor)
    assert _stationary(before, after, value), (factor, before, after)


def test_joint_update_is_the_mean_field_update_when_uncoupled(midway):
    """With M = 0 nothing couples w_i and h_i: the joint update has C = 0 and the mean-field factors."""
    data, hyper_arr, state = midway
    state = state._replace(M_mean=jnp.zeros_like(state.M_mean))
    joint = cavi.update_wh(state, data, hyper_arr)
    assert float(jnp.max(jnp.abs(joint.wh_cov))) == 0.0
    meanfield = state._replace(wh_cov=None)
    meanfield = cavi.update_h(cavi.update_w(meanfield, data, hyper_arr), data, hyper_arr)
    np.testing.assert_allclose(joint.w_mean, meanfield.w_mean, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(joint.h_cov, meanfield.h_cov, rtol=1e-10)


# --------------------------------------------------------------------------- same model as NumPyro
def _joint_log_q(state, draws):
    """log q of each draw, the joint Gaussian of (w_i, h_i) written as one (d + V)-dimensional normal."""
    W = cavi.data.cov_matrices(state.w_cov)
    S, C = state.h_cov[:, 0], state.wh_cov[:, 0]
    marginal = W + C @ jnp.linalg.solve(S, jnp.swapaxes(C, -1, -2))
    cov = jnp.concatenate([jnp.concatenate([marginal, C], -1),
                           jnp.concatenate([jnp.swapaxes(C, -1, -2), S], -1)], -2)
    mean = jnp.concatenate([state.w_mean, state.h_mean[:, 0]], -1)
    x = jnp.concatenate([draws["w"], draws["h"]], -1)
    M_cov = state.M_var[0] if state.M_var.ndim == 3 else jnp.diag(state.M_var[0])
    return (
        dist.MultivariateNormal(mean, cov).log_prob(x).sum(-1)
        + dist.Normal(state.b_mean[0], jnp.sqrt(state.b_var[0])).log_prob(draws["b"]).sum(-1)
        + dist.MultivariateNormal(state.M_mean[0], M_cov).log_prob(draws["M"]).sum(-1)
        + dist.Gamma(state.alpha_shape[0], state.alpha_rate[0]).log_prob(draws["alpha"])
        + dist.Gamma(state.lam_shape[0], state.lam_rate[0]).log_prob(draws["lam"]).sum(-1)
    )


NUM_DRAWS = 4000


@jax.jit
def _log_p_minus_log_q(draws, state, model_data):
    log_p = jax.vmap(lambda p: log_density(lmpromp_model, (model_data, HYPER), {}, p)[0])(draws)
    return log_p - _joint_log_q(state, draws)


@pytest.mark.parametrize("which", ["converged-shared", "perturbed-missing"])
def test_joint_bound_matches_numpyro_monte_carlo(small, midway, which):
    if which == "converged-shared":
        model_data = small["shared"]
        state = cavi.fit(model_data, HYPER, jax.random.key(0), local="joint", family="rowwise").state
    else:
        model_data = small["missing"]
        _, _, state = midway  # an arbitrary member: a larger cross covariance than any optimum's
        noise = 0.05 * np.random.default_rng(8).standard_normal(state.wh_cov.shape)
        state = state._replace(beta_learned=jnp.asarray(False), wh_cov=4.0 * state.wh_cov + noise)
    closed = float(cavi.elbo(state, cavi.sufficient_statistics(model_data), HYPER_ARR))
    values = np.asarray(_log_p_minus_log_q(cavi.sample_q(jax.random.key(7), state, NUM_DRAWS), state, model_data))
    mean, standard_error = values.mean(), values.std(ddof=1) / np.sqrt(NUM_DRAWS)
    assert abs(closed - mean) <= 4.0 * standard_error, (closed, mean, standard_error)
    # resolution: the cross-covariance terms of the bound are larger than the Monte Carlo error
    uncoupled = float(cavi.elbo(state._replace(wh_cov=jnp.zeros_like(state.wh_cov)),
                                cavi.sufficient_statistics(model_data), HYPER_ARR))
    assert 4.0 * standard_error < abs(closed - uncoupled)


def test_log_q_of_the_engine_is_the_joint_density(midway):
    _, _, state = midway
    draws = cavi.sample_q(jax.random.key(9), state, 50)
    reference = _joint_log_q(state, draws) + dist.Gamma(state.beta_shape, state.beta_rate).log_prob(draws["beta"])
    np.testing.assert_allclose(cavi.log_q(state, draws), reference, rtol=1e-9)


# --------------------------------------------------------------------------- exact case
def test_joint_factor_is_the_exact_posterior_given_the_globals(small):
    """Global factors at point masses: p(w_i, h_i | y_i, b, M, alpha) is Gaussian, and update_wh is it."""
    model_data = small["missing"]
    data = cavi.sufficient_statistics(model_data)
    truth = small["truth"]
    alpha, gamma, beta = 100.0, float(HYPER.gamma), float(HYPER.beta)
    state = _joint_start(data, HYPER, 0)
    point = 1e14  # shape of q(alpha): a point mass at alpha to 1e-7
    state = state._replace(
        b_mean=jnp.asarray(truth["b"])[None], b_var=jnp.asarray([1e-16]),
        M_mean=jnp.asarray(truth["M"])[None], M_var=jnp.full((1, V), 1e-16),
        alpha_shape=jnp.asarray([point]), alpha_rate=jnp.asarray([point / alpha]),
    )
    joint = cavi.update_wh(state, data, HYPER_ARR)
    meanfield = state._replace(wh_cov=None)
    for _ in range(3):
        meanfield = cavi.update_h(cavi.update_w(meanfield, data, HYPER_ARR), data, HYPER_ARR)
    b, M = truth["b"], truth["M"]
    d = b.shape[0]
    psi, y, mask = (np.asarray(a) for a in model_data)
    for i in range(psi.shape[0]):
        keep = mask[i] > 0
        # prior of x = (w, h): h ~ N(0, I/gamma), w = b + M h + e, e ~ N(0, I/alpha); y = Psi w + noise
        prior_mean = np.concatenate([b, np.zeros(V)])
        prior_cov = np.block([[M @ M.T / gamma + np.eye(d) / alpha, M / gamma], [M.T / gamma, np.eye(V) / gamma]])
        A = np.concatenate([psi[i][keep], np.zeros((keep.sum(), V))], axis=1)
        gain = prior_cov @ A.T @ np.linalg.inv(A @ prior_cov @ A.T + np.eye(keep.sum()) / beta)
        post_mean = prior_mean + gain @ (y[i][keep] - A @ prior_mean)
        post_cov = prior_cov - gain @ A @ prior_cov
        cov = np.asarray(cavi.w_covariance(joint))[i]
        np.testing.assert_allclose(joint.w_mean[i], post_mean[:d], rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(joint.h_mean[i, 0], post_mean[d:], rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(cov, post_cov[:d, :d], rtol=1e-6, atol=1e-10)
        np.testing.assert_allclose(joint.wh_cov[i, 0], post_cov[:d, d:], rtol=1e-6, atol=1e-10)
        np.testing.assert_allclose(joint.h_cov[i, 0], post_cov[d:, d:], rtol=1e-6, atol=1e-10)
        # the mean-field family cannot be exact here: it has no cross covariance and a smaller h variance
        assert np.max(np.abs(post_cov[:d, d:])) > 1e-3
        assert np.all(np.diag(meanfield.h_cov[i, 0]) < 0.99 * np.diag(post_cov[d:, d:]))


# --------------------------------------------------------------------------- engineering
def test_fast_path_equals_general_path_and_accelerations_keep_the_optimum(small):
    model_data = small["shared"]
    fits = {}
    for shared in (True, False):
        for accelerate in ("scale", "none"):
            fits[shared, accelerate] = cavi.fit(model_data, HYPER, jax.random.key(0), local="joint",
                                                shared_psi=shared, accelerate=accelerate, tol=1e-12, max_iter=20000)
    best = fits[True, "scale"]
    assert isinstance(best.state.w_cov, cavi.EigenCovariance)
    for key, fit in fits.items():
        assert fit.elbo == pytest.approx(best.elbo, rel=1e-8, abs=1e-6), key
        np.testing.assert_allclose(cavi.w_covariance(fit.state), cavi.w_covariance(best.state), rtol=1e-4,
                                   atol=1e-9, err_msg=str(key))
    # the joint family's optimum is above the mean-field one's (it contains it)
    meanfield = cavi.fit(model_data, HYPER, jax.random.key(0), tol=1e-12, max_iter=20000)
    assert best.elbo > meanfield.elbo + 0.1


def test_joint_family_is_refused_for_the_mixture(small):
    hyper = Hyperparameters(beta=400.0, latent_dim=V, num_components=2)
    with pytest.raises(LmprompError, match="single-type"):
        cavi.fit(small["shared"], hyper, jax.random.key(0), mixture=True, local="joint")
    with pytest.raises(LmprompError, match="unknown local family"):
        cavi.fit(small["shared"], HYPER, jax.random.key(0), local="structured")

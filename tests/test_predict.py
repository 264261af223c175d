"""Prediction by conditioning (lmpromp_ppl.predict) against dense Gaussian algebra, Bayes and Monte Carlo."""

import numpy as np
import pytest
import jax
from scipy.special import logsumexp as np_logsumexp
from scipy.stats import multivariate_normal

from lmpromp_ppl.basis import design_matrix, velocity_design_matrix
from lmpromp_ppl.data import Scaling
from lmpromp_ppl.errors import DataError, LmprompError
from lmpromp_ppl.predict import (
    GaussianMixture,
    concatenate,
    condition,
    condition_draws,
    condition_lmpromp,
    empty_observation,
    log_predictive_density,
    observe,
    prior,
    rmse,
    sample_trajectories,
    score_heldout,
    trajectory_distribution,
    unstandardise,
    unstandardise_samples,
    via_point,
)

D, J, V = 2, 4, 2
d = D * J
BASIS = dict(num_dofs=D, num_basis=J)
QUERY = np.linspace(0.0, 1.0, 7)


# --------------------------------------------------------------------- helpers
def random_spd(rng, n, scale=1.0):
    a = rng.normal(size=(n, n))
    return scale * (a @ a.T / n + 0.2 * np.eye(n))


def promp_params(rng):
    return {"mu_w": rng.normal(size=d), "Sigma_w": random_spd(rng, d)}


def lmpromp_params(rng, alpha=3.0):
    return {"b": rng.normal(size=d), "M": rng.normal(size=(d, V)), "alpha": np.array(alpha)}


def mixture_params(rng, num_components=3):
    pi = rng.uniform(0.5, 1.5, size=num_components)
    return {
        "pi": pi / pi.sum(),
        "b": 1.5 * rng.normal(size=(num_components, d)),
        "M": rng.normal(size=(num_components, d, V)),
        "alpha": rng.uniform(2.0, 6.0, size=num_components),
    }


def dense_condition(mean, cov, index, values):
    """Condition N(mean, cov) on x[index] = values by dense solves (reference)."""
    rest = np.setdiff1d(np.arange(mean.size), index)
    s_oo = cov[np.ix_(index, index)]
    s_ro = cov[np.ix_(rest, index)]
    gain = np.linalg.solve(s_oo, s_ro.T).T
    cond_mean = mean[rest] + gain @ (values - mean[index])
    cond_cov = cov[np.ix_(rest, rest)] - gain @ s_ro.T
    return cond_mean, cond_cov


def lmpromp_joint(params, gamma, obs):
    """Dense joint of (h, w, w_new, o): w = b + M h + e, w_new = b + M h + e', o = Psi w + eps."""
    b, M, alpha = params["b"], params["M"], float(params["alpha"])
    psi = np.asarray(obs.psi)
    n = psi.shape[0]
    # x = T z + c with independent z = (h, e, e', eps).
    z_var = np.concatenate([np.full(V, 1 / gamma), np.full(d, 1 / alpha), np.full(d, 1 / alpha), np.asarray(obs.noise_var)])
    T = np.zeros((V + 2 * d + n, z_var.size))
    T[:V, :V] = np.eye(V)
    T[V:V + d, :V] = M
    T[V:V + d, V:V + d] = np.eye(d)
    T[V + d:V + 2 * d, :V] = M
    T[V + d:V + 2 * d, V + d:V + 2 * d] = np.eye(d)
    T[V + 2 * d:, :V] = psi @ M
    T[V + 2 * d:, V:V + d] = psi
    T[V + 2 * d:, V + 2 * d:] = np.eye(n)
    mean = np.concatenate([np.zeros(V), b, b, psi @ b])
    return mean, T @ np.diag(z_var) @ T.T


def single(conditioned):
    w = conditioned.weights
    assert w.means.shape[0] == 1
    return np.asarray(w.means[0]), np.asarray(w.covs[0])


def few_rows(rng, noise_sd=0.1):
    """3 rows (N <= d: observation-space Cholesky), partial: DoF 0 twice, DoF 1 once."""
    a = observe([0.15, 0.6], rng.normal(size=(2, 1)), dofs=[0], noise_sd=noise_sd, **BASIS)
    b = observe([0.4], rng.normal(size=(1, 1)), dofs=[1], noise_sd=2 * noise_sd, **BASIS)
    return concatenate(a, b)


def many_rows(rng, noise_sd=0.1):
    """12 rows (N > d: weight-space Woodbury form)."""
    return observe(np.linspace(0.05, 0.7, 6), rng.normal(size=(6, D)), noise_sd=[noise_sd, 2 * noise_sd], **BASIS)


ROWS = {"few_rows": few_rows, "many_rows": many_rows}


# --------------------------------------------------------- conditioning (dense)
@pytest.mark.parametrize("rows", sorted(ROWS))
def test_promp_conditioning_equals_dense(rows):
    rng = np.random.default_rng(1)
    params = promp_params(rng)
    obs = ROWS[rows](rng)
    psi, noise = np.asarray(obs.psi), np.diag(np.asarray(obs.noise_var))
    n = psi.shape[0]
    joint_mean = np.concatenate([params["mu_w"], psi @ params["mu_w"]])
    s = params["Sigma_w"]
    joint_cov = np.block([[s, s @ psi.T], [psi @ s, psi @ s @ psi.T + noise]])
    ref_mean, ref_cov = dense_condition(joint_mean, joint_cov, np.arange(d, d + n), np.asarray(obs.values))
    out = condition("promp", params, obs)
    mean, cov = single(out)
    np.testing.assert_allclose(mean, ref_mean, atol=1e-10)
    np.testing.assert_allclose(cov, ref_cov, atol=1e-10)
    ref_log = multivariate_normal(joint_mean[d:], joint_cov[d:, d:]).logpdf(np.asarray(obs.values))
    np.testing.assert_allclose(float(out.log_evidence), ref_log, rtol=1e-10)
    assert out.latent is None


@pytest.mark.parametrize("rows", sorted(ROWS))
def test_lmpromp_conditioning_equals_dense_joint(rows):
    rng = np.random.default_rng(2)
    params = lmpromp_params(rng)
    gamma = 2.5  # != 1: tests that gamma is a precision everywhere
    obs = ROWS[rows](rng)
    mean, cov = lmpromp_joint(params, gamma, obs)
    n = obs.num_rows
    o_index = np.arange(V + 2 * d, V + 2 * d + n)
    cond_mean, cond_cov = dense_condition(mean, cov, o_index, np.asarray(obs.values))
    h, w, w_new = slice(0, V), slice(V, V + d), slice(V + d, V + 2 * d)

    thesis = condition_lmpromp(params, obs, gamma, exact=False)
    exact = condition_lmpromp(params, obs, gamma)
    # eqs. (4.4), (4.5): p(h | o), identical in both forms
    for out in (thesis, exact):
        np.testing.assert_allclose(np.asarray(out.latent.means[0]), cond_mean[h], atol=1e-10)
        np.testing.assert_allclose(np.asarray(out.latent.covs[0]), cond_cov[h, h], atol=1e-10)
    # exact=True: p(w | o) of the observed movement's own weights
    np.testing.assert_allclose(single(exact)[0], cond_mean[w], atol=1e-10)
    np.testing.assert_allclose(single(exact)[1], cond_cov[w, w], atol=1e-10)
    # eqs. (4.6), (4.7): p(w_new | o) of a new execution sharing h but not the alpha^-1 I noise
    np.testing.assert_allclose(single(thesis)[0], cond_mean[w_new], atol=1e-10)
    np.testing.assert_allclose(single(thesis)[1], cond_cov[w_new, w_new], atol=1e-10)
    # the two differ by alpha^-1 Psi_o^T A^-1 (o - Psi_o b) in the mean
    a_matrix = cov[np.ix_(o_index, o_index)]
    resid = np.asarray(obs.values) - np.asarray(obs.psi) @ params["b"]
    shift = np.asarray(obs.psi).T @ np.linalg.solve(a_matrix, resid) / params["alpha"]
    np.testing.assert_allclose(single(exact)[0] - single(thesis)[0], shift, atol=1e-10)
    assert np.max(np.abs(shift)) > 1e-2
    ref_log = multivariate_normal(mean[o_index], a_matrix).logpdf(np.asarray(obs.values))
    np.testing.assert_allclose(float(exact.log_evidence), ref_log, rtol=1e-10)
    np.testing.assert_allclose(float(thesis.log_evidence), ref_log, rtol=1e-10)


def test_conditioning_on_nothing_returns_the_prior():
    rng = np.random.default_rng(3)
    gamma = 4.0
    p = promp_params(rng)
    np.testing.assert_allclose(single(prior("promp", p))[0], p["mu_w"], atol=1e-14)
    np.testing.assert_allclose(single(prior("promp", p))[1], p["Sigma_w"], atol=1e-14)
    p = lmpromp_params(rng)
    marginal = np.eye(d) / p["alpha"] + p["M"] @ p["M"].T / gamma
    for exact in (False, True):
        out = condition("lmpromp", p, empty_observation(d), gamma, exact=exact)
        np.testing.assert_allclose(single(out)[0], p["b"], atol=1e-14)
        np.testing.assert_allclose(single(out)[1], marginal, atol=1e-12)
        np.testing.assert_allclose(np.asarray(out.latent.covs[0]), np.eye(V) / gamma, atol=1e-14)
        assert float(out.log_evidence) == 0.0
    p = mixture_params(rng)
    out = prior("mixture", p, gamma)
    np.testing.assert_allclose(np.asarray(out.weights.weights), p["pi"], rtol=1e-12)
    np.testing.assert_allclose(np.asarray(out.weights.means), p["b"], atol=1e-14)


def test_noiseless_observations_are_reproduced_by_exact_conditioning_only():
    rng = np.random.default_rng(4)
    phase = np.array([0.2, 0.55, 0.9])
    values = rng.normal(size=(3, D))  # 6 rows < d = 8, so A is positive definite
    obs = observe(phase, values, noise_sd=0.0, **BASIS)
    fits = {
        "promp": condition("promp", promp_params(rng), obs),
        "lmpromp_exact": condition("lmpromp", lmpromp_params(rng), obs, exact=True),
    }
    for out in fits.values():
        traj = trajectory_distribution(out.weights, phase, **BASIS)
        np.testing.assert_allclose(np.asarray(traj.mean), values, atol=1e-8)
        np.testing.assert_allclose(np.asarray(traj.sd), 0.0, atol=1e-6)
    # Eq. (4.6) keeps the mean in the V-dimensional plane b + M h: 6 generic
    # values cannot all be met with V = 2.
    thesis = condition("lmpromp", lmpromp_params(rng), obs, exact=False)
    traj = trajectory_distribution(thesis.weights, phase, **BASIS)
    assert np.max(np.abs(np.asarray(traj.mean) - values)) > 1e-2


def test_gamma_is_a_precision_prior_sd_scales_as_gamma_to_minus_half():
    rng = np.random.default_rng(5)
    params = lmpromp_params(rng, alpha=1e10)  # only h-driven variation
    phi = np.asarray(design_matrix(QUERY, D, J))
    num = 20000
    sds = {}
    for gamma in (1.0, 4.0):
        sds[gamma] = np.asarray(trajectory_distribution(prior("lmpromp", params, gamma).weights, QUERY, **BASIS).sd)
        # Monte Carlo from the generative definition h ~ N(0, gamma^-1 I)
        h = rng.normal(size=(num, V)) / np.sqrt(gamma)
        paths = (params["b"] + h @ params["M"].T) @ phi.T  # (num, T * D), time-major
        mc_sd = paths.std(axis=0, ddof=1).reshape(QUERY.size, D)
        se = mc_sd / np.sqrt(2 * (num - 1))
        assert np.all(np.abs(sds[gamma] - mc_sd) < 4 * se)
    np.testing.assert_allclose(sds[4.0] / sds[1.0], 0.5, rtol=1e-8)


# ------------------------------------------------------------------- mixtures
def test_mixture_responsibilities_and_moments_equal_brute_force_bayes():
    rng = np.random.default_rng(6)
    params = mixture_params(rng)
    gamma = 2.0
    obs = few_rows(rng, noise_sd=0.3)
    psi, noise = np.asarray(obs.psi), np.diag(np.asarray(obs.noise_var))
    out = condition("mixture", params, obs, gamma)
    joint = []
    for k in range(3):
        cov_k = np.eye(d) / params["alpha"][k] + params["M"][k] @ params["M"][k].T / gamma
        density = multivariate_normal(psi @ params["b"][k], psi @ cov_k @ psi.T + noise).pdf(np.asarray(obs.values))
        joint.append(params["pi"][k] * density)
    joint = np.array(joint)
    np.testing.assert_allclose(np.asarray(out.weights.weights), joint / joint.sum(), rtol=1e-9)
    np.testing.assert_allclose(float(out.log_evidence), np.log(joint.sum()), rtol=1e-10)
    # each component is the single-type conditioning of that component
    for k in range(3):
        comp = {"b": params["b"][k], "M": params["M"][k], "alpha": params["alpha"][k]}
        mean_k, cov_k = single(condition("lmpromp", comp, obs, gamma))
        np.testing.assert_allclose(np.asarray(out.weights.means[k]), mean_k, atol=1e-10)
        np.testing.assert_allclose(np.asarray(out.weights.covs[k]), cov_k, atol=1e-10)
    # moment-matched mixture: E[w] and E[w w^T] - E[w] E[w]^T by hand
    z = joint / joint.sum()
    means, covs = np.asarray(out.weights.means), np.asarray(out.weights.covs)
    ref_mean = z @ means
    ref_cov = np.einsum("k,kij->ij", z, covs + np.einsum("ki,kj->kij", means, means)) - np.outer(ref_mean, ref_mean)
    mean, cov = out.weights.moments()
    np.testing.assert_allclose(np.asarray(mean), ref_mean, atol=1e-10)
    np.testing.assert_allclose(np.asarray(cov), ref_cov, atol=1e-10)


@pytest.fixture(scope="module")
def bimodal():
    """Two modes at trajectory level +2 and -2 (the basis rows sum to one)."""
    rng = np.random.default_rng(7)
    return {
        "pi": np.array([0.5, 0.5]),
        "b": np.stack([np.full(d, 2.0), np.full(d, -2.0)]),
        "M": 0.1 * rng.normal(size=(2, d, V)),
        "alpha": np.array([100.0, 100.0]),
    }


def test_bimodal_mixture_mean_lies_between_modes_components_on_modes(bimodal):
    ambiguous = observe([0.5], [[0.0, 0.0]], noise_sd=3.0, **BASIS)
    out = condition("mixture", bimodal, ambiguous)
    traj = trajectory_distribution(out.weights, QUERY, **BASIS)
    z = np.asarray(traj.component_weights)
    assert np.all((z > 0.3) & (z < 0.7))
    modes = np.array([2.0, -2.0])[:, None, None]
    assert np.all(np.abs(np.asarray(traj.component_means) - modes) < 0.1)
    assert np.all(np.abs(np.asarray(traj.mean)) < 1.0)  # between the modes, where there is no mass
    assert np.all(np.asarray(traj.sd) > 1.5)  # the mixture sd covers both modes
    assert np.all(np.asarray(traj.component_sds) < 0.5)


def test_observations_near_one_mode_select_that_component(bimodal):
    near = observe([0.2, 0.5, 0.8], np.full((3, D), 1.9), noise_sd=0.1, **BASIS)
    out = condition("mixture", bimodal, near)
    z = np.asarray(out.weights.weights)
    assert z[0] > 1 - 1e-9
    traj = trajectory_distribution(out.weights, QUERY, **BASIS)
    np.testing.assert_allclose(np.asarray(traj.mean), np.asarray(traj.component_means[0]), atol=1e-8)


# --------------------------------------------------- partial obs and via-points
@pytest.mark.parametrize("model", ["promp", "lmpromp"])
def test_partial_observation_moves_unobserved_dof_by_prior_correlations(model):
    rng = np.random.default_rng(8)
    params = promp_params(rng) if model == "promp" else lmpromp_params(rng)
    if model == "promp":
        mu, sigma = params["mu_w"], params["Sigma_w"]
    else:
        mu, sigma = params["b"], np.eye(d) / params["alpha"] + params["M"] @ params["M"].T
    obs = observe([0.1, 0.4], [[1.5], [2.0]], dofs=[0], noise_sd=0.05, **BASIS)
    out = condition(model, params, obs, exact=True)
    traj = trajectory_distribution(out.weights, QUERY, **BASIS)
    # dense: joint of (y at QUERY, o)
    phi = np.asarray(design_matrix(QUERY, D, J))
    psi = np.asarray(obs.psi)
    full = np.vstack([phi, psi])
    joint_cov = full @ sigma @ full.T
    joint_cov[phi.shape[0]:, phi.shape[0]:] += np.diag(np.asarray(obs.noise_var))
    index = np.arange(phi.shape[0], full.shape[0])
    ref_mean, ref_cov = dense_condition(full @ mu, joint_cov, index, np.asarray(obs.values))
    ref_mean = ref_mean.reshape(QUERY.size, D)
    ref_sd = np.sqrt(np.diag(ref_cov)).reshape(QUERY.size, D)
    np.testing.assert_allclose(np.asarray(traj.mean), ref_mean, atol=1e-9)
    np.testing.assert_allclose(np.asarray(traj.sd), ref_sd, atol=1e-9)
    prior_mean = (phi @ mu).reshape(QUERY.size, D)
    assert np.max(np.abs(np.asarray(traj.mean)[:, 1] - prior_mean[:, 1])) > 0.05  # unobserved DoF moved


@pytest.mark.parametrize("model", ["promp", "lmpromp"])
def test_via_point_position_and_velocity(model):
    rng = np.random.default_rng(9)
    params = promp_params(rng) if model == "promp" else lmpromp_params(rng)
    phase, duration, sd = 0.37, 2.0, 1e-3
    position, velocity = np.array([1.5, -0.7]), np.array([0.8, -1.2])
    obs = via_point(phase, position, velocity=velocity, position_sd=sd, velocity_sd=sd, duration=duration, **BASIS)
    assert obs.num_rows == 2 * D
    np.testing.assert_allclose(np.asarray(obs.psi[D:]), np.asarray(velocity_design_matrix([phase], D, J, duration)))
    out = condition(model, params, obs, exact=True)
    at = trajectory_distribution(out.weights, np.array([phase]), **BASIS)
    assert np.all(np.abs(np.asarray(at.mean[0]) - position) <= sd)
    assert np.all(np.asarray(at.sd[0]) <= sd)
    eps = 1e-5
    ends = trajectory_distribution(out.weights, np.array([phase - eps, phase + eps]), **BASIS)
    derivative = (np.asarray(ends.mean[1]) - np.asarray(ends.mean[0])) / (2 * eps) / duration
    assert np.all(np.abs(derivative - velocity) <= sd)


# --------------------------------------------------------- Bayesian predictive
def stack(params_list, shape):
    return {k: np.stack([p[k] for p in params_list]).reshape(shape + np.shape(params_list[0][k])) for k in params_list[0]}


@pytest.mark.parametrize("model", ["promp", "lmpromp", "mixture"])
def test_bayesian_predictive_over_identical_draws_equals_plug_in(model):
    rng = np.random.default_rng(10)
    params = {"promp": promp_params, "lmpromp": lmpromp_params, "mixture": mixture_params}[model](rng)
    obs = few_rows(rng)
    target = observe([0.8, 0.95], rng.normal(size=(2, D)), noise_sd=0.1, **BASIS)
    draws = stack([params] * 6, (2, 3))  # (chain, draw)
    draws["w"] = np.zeros((2, 3, 5, d))  # sites the model does not read are ignored
    plug = condition(model, params, obs, 1.5)
    bayes = condition_draws(model, draws, obs, 1.5)
    assert bayes.weights.num_components == 6 * plug.weights.num_components
    for a, b in zip(trajectory_distribution(plug.weights, QUERY, **BASIS)[1:3],
                    trajectory_distribution(bayes.weights, QUERY, **BASIS)[1:3]):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), atol=1e-10)
    np.testing.assert_allclose(float(bayes.log_evidence), float(plug.log_evidence), rtol=1e-10)
    np.testing.assert_allclose(
        float(log_predictive_density(bayes.weights, target)), float(log_predictive_density(plug.weights, target)), rtol=1e-10
    )


@pytest.mark.parametrize("model", ["lmpromp", "mixture"])
def test_bayesian_predictive_over_two_draws_is_the_equal_mixture(model):
    rng = np.random.default_rng(11)
    make = {"lmpromp": lmpromp_params, "mixture": lambda r: mixture_params(r, 2)}[model]
    first, second = make(rng), make(rng)
    obs = few_rows(rng)
    target = observe([0.8, 0.95], rng.normal(size=(2, D)), noise_sd=0.1, **BASIS)
    draws = stack([first, second], (2,))  # (draw,)
    bayes = condition_draws(model, draws, obs)
    parts = [condition(model, p, obs) for p in (first, second)]
    trajs = [trajectory_distribution(p.weights, QUERY, **BASIS) for p in parts]
    m = np.stack([np.asarray(t.mean) for t in trajs])
    v = np.stack([np.asarray(t.sd) ** 2 for t in trajs])
    ref_mean = m.mean(axis=0)
    ref_var = (v + m**2).mean(axis=0) - ref_mean**2
    traj = trajectory_distribution(bayes.weights, QUERY, **BASIS)
    np.testing.assert_allclose(np.asarray(traj.mean), ref_mean, atol=1e-10)
    np.testing.assert_allclose(np.asarray(traj.sd) ** 2, ref_var, atol=1e-10)
    logs = np.array([float(log_predictive_density(p.weights, target)) for p in parts])
    np.testing.assert_allclose(float(log_predictive_density(bayes.weights, target)), np_logsumexp(logs) - np.log(2), rtol=1e-10)
    evidences = np.array([float(p.log_evidence) for p in parts])
    np.testing.assert_allclose(float(bayes.log_evidence), np_logsumexp(evidences) - np.log(2), rtol=1e-10)
    # reweight=True: draw weights proportional to p(o | theta_s)
    reweighted = condition_draws(model, draws, obs, reweight=True)
    per_draw = np.asarray(reweighted.weights.weights).reshape(2, -1).sum(axis=1)
    np.testing.assert_allclose(per_draw, np.exp(evidences - np_logsumexp(evidences)), rtol=1e-9)


def test_draws_with_bad_sample_dims_are_rejected():
    rng = np.random.default_rng(12)
    params = lmpromp_params(rng)
    obs = few_rows(rng)
    with pytest.raises(LmprompError, match="sample"):
        condition_draws("lmpromp", params, obs)  # no sample dims
    bad = stack([params] * 4, (4,))
    bad["alpha"] = np.ones(3)
    with pytest.raises(LmprompError, match="sample shapes"):
        condition_draws("lmpromp", bad, obs)


# ------------------------------------------------------------ held-out scoring
@pytest.mark.parametrize("model", ["promp", "lmpromp"])
def test_heldout_log_density_and_rmse_equal_dense(model):
    rng = np.random.default_rng(13)
    params = promp_params(rng) if model == "promp" else lmpromp_params(rng)
    if model == "promp":
        mu, sigma = params["mu_w"], params["Sigma_w"]
    else:
        mu, sigma = params["b"], np.eye(d) / params["alpha"] + params["M"] @ params["M"].T
    phase = np.linspace(0, 1, 9)
    y = rng.normal(size=(9, D))
    noise_sd = 0.1
    observed = observe(phase[:3], y[:3], noise_sd=noise_sd, **BASIS)  # 6 rows <= d
    remainder = observe(phase[3:], y[3:], noise_sd=noise_sd, **BASIS)  # 12 rows > d
    whole = concatenate(observed, remainder)
    psi = np.asarray(whole.psi)
    joint_cov = psi @ sigma @ psi.T + noise_sd**2 * np.eye(psi.shape[0])
    joint_mean = psi @ mu
    # whole held-out demonstration under the prior
    ref_whole = multivariate_normal(joint_mean, joint_cov).logpdf(y.reshape(-1))
    prior_weights = prior(model, params).weights
    np.testing.assert_allclose(float(log_predictive_density(prior_weights, whole)), ref_whole, rtol=1e-10)
    # remainder given the observed part (exact conditioning)
    post = condition(model, params, observed, exact=True)
    index = np.arange(6)
    rest_mean, rest_cov = dense_condition(joint_mean, joint_cov, index, y[:3].reshape(-1))
    ref_rest = multivariate_normal(rest_mean, rest_cov).logpdf(y[3:].reshape(-1))
    score = score_heldout(post.weights, remainder)
    np.testing.assert_allclose(float(score.log_density), ref_rest, rtol=1e-10)
    np.testing.assert_allclose(float(score.log_density_per_row), ref_rest / 12, rtol=1e-10)
    np.testing.assert_allclose(float(score.log_density), ref_whole - float(post.log_evidence), rtol=1e-10)
    np.testing.assert_allclose(float(score.rmse), np.sqrt(np.mean((y[3:].reshape(-1) - rest_mean) ** 2)), rtol=1e-10)
    # in original units: y_orig = mean + scale * y
    scaling = Scaling(np.array([3.0, -1.0]), np.array([2.0, 0.5]))
    scale_rows = np.tile(scaling.scale, 6)
    ref_orig = multivariate_normal(
        np.tile(scaling.mean, 6) + scale_rows * rest_mean, rest_cov * np.outer(scale_rows, scale_rows)
    ).logpdf(scaling.invert(y[3:]).reshape(-1))
    np.testing.assert_allclose(float(log_predictive_density(post.weights, remainder, scaling)), ref_orig, rtol=1e-10)
    orig_resid = scaling.invert(y[3:]).reshape(-1) - (np.tile(scaling.mean, 6) + scale_rows * rest_mean)
    np.testing.assert_allclose(float(rmse(post.weights, remainder, scaling)), np.sqrt(np.mean(orig_resid**2)), rtol=1e-10)


def test_mixture_heldout_log_density_is_log_sum_exp():
    rng = np.random.default_rng(14)
    params = mixture_params(rng)
    target = observe(np.linspace(0, 1, 5), rng.normal(size=(5, D)), noise_sd=0.2, **BASIS)
    psi = np.asarray(target.psi)
    parts = []
    for k in range(3):
        cov_k = np.eye(d) / params["alpha"][k] + params["M"][k] @ params["M"][k].T
        parts.append(np.log(params["pi"][k]) + multivariate_normal(
            psi @ params["b"][k], psi @ cov_k @ psi.T + 0.04 * np.eye(psi.shape[0])).logpdf(np.asarray(target.values)))
    np.testing.assert_allclose(float(log_predictive_density(prior("mixture", params).weights, target)),
                               np_logsumexp(parts), rtol=1e-10)


# ------------------------------------------------------------------- sampling
def test_conditioned_trajectory_samples_match_analytic_moments():
    rng = np.random.default_rng(15)
    params = lmpromp_params(rng)
    obs = few_rows(rng)
    out = condition("lmpromp", params, obs, 2.0)
    phase = np.array([0.1, 0.5, 0.9])
    beta = 50.0
    num = 4000
    samples = np.asarray(sample_trajectories(jax.random.key(0), out.weights, phase, num, beta=beta, **BASIS))
    assert samples.shape == (num, 3, D)
    flat = samples.reshape(num, -1)
    phi = np.asarray(design_matrix(phase, D, J))
    mean = phi @ np.asarray(out.weights.means[0])
    cov = phi @ np.asarray(out.weights.covs[0]) @ phi.T + np.eye(phi.shape[0]) / beta
    assert np.all(np.abs(flat.mean(axis=0) - mean) < 4 * np.sqrt(np.diag(cov) / num))
    sample_cov = np.cov(flat, rowvar=False)
    # standard error of a Gaussian sample covariance: sqrt((C_ii C_jj + C_ij^2) / (n - 1))
    se = np.sqrt((np.outer(np.diag(cov), np.diag(cov)) + cov**2) / (num - 1))
    assert np.all(np.abs(sample_cov - cov) < 4 * se)
    traj = trajectory_distribution(out.weights, phase, beta=beta, **BASIS)
    np.testing.assert_allclose(np.asarray(traj.sd).reshape(-1), np.sqrt(np.diag(cov)), rtol=1e-10)


def test_mixture_prior_samples_match_mixture_moments(bimodal):
    num = 4000
    weights = prior("mixture", bimodal).weights
    samples = np.asarray(sample_trajectories(jax.random.key(1), weights, QUERY, num, **BASIS))
    traj = trajectory_distribution(weights, QUERY, **BASIS)
    mean, sd = np.asarray(traj.mean), np.asarray(traj.sd)
    assert np.all(np.abs(samples.mean(axis=0) - mean) < 4 * sd / np.sqrt(num))
    centred = samples - samples.mean(axis=0)
    var = (centred**2).mean(axis=0)
    se_var = np.sqrt(((centred**4).mean(axis=0) - var**2) / num)
    assert np.all(np.abs(samples.var(axis=0, ddof=1) - sd**2) < 4 * se_var)
    # both modes are populated
    assert 0.4 < np.mean(samples[:, 3, 0] > 0) < 0.6


# ------------------------------------------------- observations and plumbing
def test_observe_partial_mask_scaling_and_row_layout():
    rng = np.random.default_rng(16)
    phase = np.array([0.1, 0.5, 0.7])
    values = rng.normal(size=(3, D))
    full = observe(phase, values, noise_sd=[0.1, 0.2], **BASIS)
    psi = np.asarray(design_matrix(phase, D, J))
    np.testing.assert_array_equal(np.asarray(full.psi), psi)
    np.testing.assert_array_equal(np.asarray(full.values), values.reshape(-1))
    np.testing.assert_allclose(np.asarray(full.noise_var), np.tile([0.01, 0.04], 3))
    np.testing.assert_array_equal(np.asarray(full.dof), np.tile([0, 1], 3))
    mask = np.array([[True, False], [False, True], [True, True]])
    part = observe(phase, values, noise_sd=[0.1, 0.2], mask=mask, **BASIS)
    keep = np.flatnonzero(mask.reshape(-1))
    np.testing.assert_array_equal(np.asarray(part.psi), psi[keep])
    np.testing.assert_array_equal(np.asarray(part.values), values.reshape(-1)[keep])
    only_one = observe(phase, values[:, 1], dofs=[1], noise_sd=0.2, **BASIS)
    np.testing.assert_array_equal(np.asarray(only_one.psi), psi[1::2])
    scaling = Scaling(np.array([1.0, -2.0]), np.array([2.0, 4.0]))
    scaled = observe(phase, scaling.invert(values), noise_sd=[0.2, 0.8], scaling=scaling, **BASIS)
    np.testing.assert_allclose(np.asarray(scaled.values), values.reshape(-1), atol=1e-14)
    np.testing.assert_allclose(np.asarray(scaled.noise_var), np.tile([0.01, 0.04], 3), atol=1e-14)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(values=np.zeros((3, 1))), "shape"),
        (dict(values=np.full((3, D), np.nan)), "NaN"),
        (dict(noise_sd=-1.0), "non-negative"),
        (dict(dofs=[2], values=np.zeros((3, 1))), "out of range"),
        (dict(noise_sd=[0.1, 0.1, 0.1]), "one entry per observed DoF"),
    ],
)
def test_observe_rejects_bad_input(kwargs, match):
    args = dict(phase=np.array([0.1, 0.2, 0.3]), values=np.zeros((3, D)))
    args.update(kwargs)
    with pytest.raises(DataError, match=match):
        observe(args.pop("phase"), args.pop("values"), **args, **BASIS)


def test_condition_rejects_bad_parameters():
    rng = np.random.default_rng(17)
    obs = few_rows(rng)
    with pytest.raises(LmprompError, match="unknown model"):
        condition("gmm", {}, obs)
    with pytest.raises(LmprompError, match="lack site"):
        condition("lmpromp", {"b": np.zeros(d)}, obs)
    with pytest.raises(LmprompError, match="weight dimension"):
        condition("promp", {"mu_w": np.zeros(d + 1), "Sigma_w": np.eye(d + 1)}, obs)
    with pytest.raises(LmprompError, match="alpha"):
        condition("mixture", dict(mixture_params(rng), alpha=np.ones(5)), obs)


def test_conditioning_jits_without_recompiling_for_new_values():
    rng = np.random.default_rng(18)
    fn = jax.jit(condition, static_argnames=("model", "exact"))
    first, second = lmpromp_params(rng), lmpromp_params(rng)
    obs = few_rows(rng)
    for params, gamma in ((first, 1.0), (second, 3.0)):
        jitted = fn("lmpromp", params, obs, gamma, exact=True)
        eager = condition("lmpromp", params, obs, gamma, exact=True)
        np.testing.assert_allclose(np.asarray(jitted.weights.covs), np.asarray(eager.weights.covs), atol=1e-12)
    assert fn._cache_size() == 1


def test_unstandardise_maps_back_to_original_units():
    rng = np.random.default_rng(19)
    scaling = Scaling(np.array([1.0, -2.0]), np.array([2.0, 4.0]))
    weights = prior("lmpromp", lmpromp_params(rng)).weights
    traj = trajectory_distribution(weights, QUERY, **BASIS)
    back = unstandardise(traj, scaling)
    np.testing.assert_allclose(np.asarray(back.mean), scaling.invert(np.asarray(traj.mean)), atol=1e-12)
    np.testing.assert_allclose(np.asarray(back.sd), scaling.invert_sd(np.asarray(traj.sd)), atol=1e-12)
    samples = sample_trajectories(jax.random.key(2), weights, QUERY, 3, **BASIS)
    np.testing.assert_allclose(np.asarray(unstandardise_samples(samples, scaling)), scaling.invert(np.asarray(samples)), atol=1e-12)


def test_gaussian_mixture_moments_of_a_single_component_are_its_own():
    rng = np.random.default_rng(20)
    cov = random_spd(rng, 3)
    mix = GaussianMixture(np.zeros(1), rng.normal(size=(1, 3)), cov[None])
    mean, out = mix.moments()
    np.testing.assert_allclose(np.asarray(mean), np.asarray(mix.means[0]))
    np.testing.assert_allclose(np.asarray(out), cov, atol=1e-14)

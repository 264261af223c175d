"""Collapsed models and the exact conditionals p(w | theta, y), p(h | w, theta).

* each collapsed log density equals a hand-written scipy density (dense S x S
  covariances here, never in the models);
* independently, log p(y, theta) = log p(y, w, theta) - log p(w | y, theta) at an
  arbitrary w (full model minus the dense conditional of eqs. 3.2-3.3), the same
  for h, and for the mixture the log-sum-exp over every assignment z;
* draws of sample_w_given_theta / sample_h_given_theta have the mean and
  covariance of the exact conditional within 4 Monte Carlo standard errors;
* the LMProMP with b integrated out as well (``"whb"``): its density equals one
  dense Gaussian over all demonstrations' observed entries, and
  log p(y, b, theta) - log p(b | y, theta) at an arbitrary b.
"""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpy.testing import assert_allclose
from numpyro import handlers
from numpyro.infer import Predictive
from numpyro.infer.util import log_density
from scipy import special, stats
from scipy.linalg import block_diag

from lmpromp_ppl.data.core import Demonstrations, ModelData, model_data
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.models import (
    Hyperparameters,
    lmpromp_collapsed_model,
    lmpromp_model,
    mixture_collapsed_model,
    mixture_model,
    promp_collapsed_model,
    promp_model,
    sample_h_given_theta,
    sample_w_given_theta,
)
from lmpromp_ppl.models.collapsed import lmpromp_offset_collapsed_model
from lmpromp_ppl.models.conditionals import data_statistics, gaussian_conditional, offset_marginal
from lmpromp_ppl.models.lmpromp import masked_observations

HYPER = Hyperparameters(
    beta=4.0, lambda0=0.7, gamma=1.3, a0=2.5, b0=0.6, c0=1.7, d0=0.9, latent_dim=2,
    num_components=2, kappa0=0.8, beta_a0=3.0, beta_b0=0.5, promp_scale=0.8,
    lkj_concentration=1.5,
)


@pytest.fixture(scope="module")
def data() -> ModelData:
    """L = 3 ragged demonstrations (lengths 6, 4, 5; D = 2, J = 2: d = 4, S = 12), one
    missing entry inside demonstration 1, garbage in every masked entry and psi row."""
    rng = np.random.default_rng(0)
    lengths = (6, 4, 5)
    demos = Demonstrations(
        [np.sort(rng.uniform(0, 1, n)) + np.arange(n) for n in lengths],
        [rng.normal(size=(n, 2)) for n in lengths],
    )
    psi, y, mask = (np.array(a) for a in model_data(demos, 2).dense())
    mask[1, 3] = 0.0
    y[mask == 0] = 1e3
    y[1, 3] = np.nan
    psi[mask == 0] = 7.0
    return ModelData(jnp.asarray(psi), jnp.asarray(y), jnp.asarray(mask))


def draw(model_name, hyper, data, seed):
    """Random values of the sites of ``model_name`` other than w (numpy)."""
    rng = np.random.default_rng(seed)
    L, _, d = data.psi.shape
    V, K = hyper.latent_dim, hyper.num_components
    if model_name == "promp":
        a = rng.normal(size=(d, d + 2))
        cov = a @ a.T
        corr_chol = np.linalg.cholesky(cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov))))
        scale = rng.gamma(2.0, 0.5, size=d)
        chol = scale[:, None] * corr_chol
        p = {"mu_w": rng.normal(size=d), "w_scale": scale, "w_corr_chol": corr_chol, "Sigma_w": chol @ chol.T}
    else:
        prefix = () if model_name == "lmpromp" else (K,)
        lam = rng.gamma(2.0, 1.0, size=prefix + (V,))
        p = {
            "b": rng.normal(size=prefix + (d,)),
            "lam": lam,
            "M": rng.normal(size=prefix + (d, V)) / np.sqrt(lam)[..., None, :],
            "alpha": rng.gamma(3.0, 1.0, size=prefix),
            "h": rng.normal(size=(L,) + prefix + (V,)),
        }
        if model_name == "mixture":
            p["pi"] = rng.dirichlet(np.ones(K))
    if hyper.learn_beta:
        p["beta"] = rng.gamma(4.0, 1.0)
    return p


def logp(model, data, hyper, params, **kwargs):
    return float(log_density(model, (data, hyper), kwargs, params)[0])


def observed_rows(data, i):
    psi, y, mask = (np.asarray(a) for a in data)
    o = mask[i] == 1
    return psi[i, o], y[i, o]


def beta_of(hyper, p):
    return p["beta"] if hyper.learn_beta else hyper.beta


# --------------------------------------------------------- hand-written (dense) densities
def prior_logp(hyper, p, model_name, keep_h):
    """log prior of every site but w (scipy)."""
    lp = stats.gamma.logpdf(p["beta"], hyper.beta_a0, scale=1 / hyper.beta_b0) if hyper.learn_beta else 0.0
    if model_name == "promp":
        d = len(p["mu_w"])
        eta = hyper.lkj_concentration
        k = np.arange(1, d)
        log_c = np.sum(  # Lewandowski, Kurowicka & Joe (2009), eq. 16
            (2 * eta - 2 + d - k) * (d - k) * np.log(2)
            + (d - k) * special.betaln(eta + (d - k - 1) / 2, eta + (d - k - 1) / 2)
        )
        lkj = np.sum((d - np.arange(2, d + 1) + 2 * eta - 2) * np.log(np.diag(p["w_corr_chol"])[1:])) - log_c
        return (
            lp + lkj
            + stats.norm.logpdf(p["mu_w"], 0, hyper.lambda0**-0.5).sum()
            + stats.halfnorm.logpdf(p["w_scale"], scale=hyper.promp_scale).sum()
        )
    lp += (
        stats.norm.logpdf(p["b"], 0, hyper.lambda0**-0.5).sum()
        + stats.gamma.logpdf(p["lam"], hyper.c0, scale=1 / hyper.d0).sum()
        + stats.norm.logpdf(p["M"], 0, 1 / np.sqrt(p["lam"])[..., None, :]).sum()
        + stats.gamma.logpdf(p["alpha"], hyper.a0, scale=1 / hyper.b0).sum()
    )
    if keep_h:
        lp += stats.norm.logpdf(p["h"], 0, hyper.gamma**-0.5).sum()
    if model_name == "mixture":
        lp += stats.dirichlet.logpdf(p["pi"], np.full(hyper.num_components, hyper.kappa0))
    return lp


def weight_prior(hyper, p, i, k=None, keep_h=True):
    """Mean and covariance of p(w_i | theta) (of component k for the mixture)."""
    if "mu_w" in p:
        return p["mu_w"], p["Sigma_w"]
    b, M, alpha = (p[n] if k is None else p[n][k] for n in ("b", "M", "alpha"))
    d = len(b)
    if keep_h:
        h = p["h"][i] if k is None else p["h"][i, k]
        return b + M @ h, np.eye(d) / alpha
    return b, np.eye(d) / alpha + M @ M.T / hyper.gamma


def dense_marginal(data, hyper, p, i, k=None, keep_h=True):
    """log N(y_i | Psi m, beta^-1 I + Psi C Psi^T) over the observed entries, dense."""
    psi, y = observed_rows(data, i)
    m, C = weight_prior(hyper, p, i, k, keep_h)
    cov = psi @ C @ psi.T + np.eye(len(y)) / beta_of(hyper, p)
    return stats.multivariate_normal.logpdf(y, psi @ m, cov)


def hand_collapsed(data, hyper, p, model_name, keep_h=True):
    lp = prior_logp(hyper, p, model_name, keep_h)
    for i in range(data.psi.shape[0]):
        if model_name == "mixture":
            lp += special.logsumexp(
                [np.log(p["pi"][k]) + dense_marginal(data, hyper, p, i, k, keep_h)
                 for k in range(hyper.num_components)]
            )
        else:
            lp += dense_marginal(data, hyper, p, i, None, keep_h)
    return lp


def dense_w_conditional(data, hyper, p, i, k=None, keep_h=True):
    """Mean and covariance of p(w_i | theta, y_i), covariance form (eqs. 3.2-3.3)."""
    psi, y = observed_rows(data, i)
    m, C = weight_prior(hyper, p, i, k, keep_h)
    gain = C @ psi.T @ np.linalg.inv(np.eye(len(y)) / beta_of(hyper, p) + psi @ C @ psi.T)
    return m + gain @ (y - psi @ m), C - gain @ psi @ C


# ----------------------------------------------------------------- scipy densities
COLLAPSED = {"lmpromp": lmpromp_collapsed_model, "mixture": mixture_collapsed_model}


@pytest.mark.parametrize("learn_beta", [False, True])
@pytest.mark.parametrize("model_name", ["lmpromp", "mixture"])
@pytest.mark.parametrize("collapse_h", [False, True])
def test_collapsed_log_density_matches_scipy(data, model_name, collapse_h, learn_beta):
    hyper = HYPER.replace(learn_beta=learn_beta)
    p = draw(model_name, hyper, data, 1)
    if collapse_h:
        del p["h"]
    expected = hand_collapsed(data, hyper, p, model_name, keep_h=not collapse_h)
    actual = logp(COLLAPSED[model_name], data, hyper, p, collapse_h=collapse_h)
    assert np.isfinite(expected)
    assert actual == pytest.approx(expected, rel=1e-10)


@pytest.mark.parametrize("learn_beta", [False, True])
def test_promp_collapsed_log_density_matches_scipy(data, learn_beta):
    hyper = HYPER.replace(learn_beta=learn_beta)
    p = draw("promp", hyper, data, 2)
    expected = hand_collapsed(data, hyper, p, "promp")
    p_model = {k: v for k, v in p.items() if k != "Sigma_w"}
    assert logp(promp_collapsed_model, data, hyper, p_model) == pytest.approx(expected, rel=1e-10)


# ------------------------------------------------------------------ independent routes
def test_collapsing_w_equals_joint_minus_conditional(data):
    """log p(y, theta) = log p(y, w, theta) - log p(w | y, theta) at an arbitrary w."""
    rng = np.random.default_rng(3)
    for model_name, full, collapsed in [
        ("lmpromp", lmpromp_model, lmpromp_collapsed_model),
        ("promp", promp_model, promp_collapsed_model),
    ]:
        p = draw(model_name, HYPER, data, 4)
        w = rng.normal(size=(3, 4))
        log_cond = sum(
            stats.multivariate_normal.logpdf(w[i], *dense_w_conditional(data, HYPER, p, i))
            for i in range(3)
        )
        sites = {k: v for k, v in p.items() if k != "Sigma_w"}
        joint = logp(full, data, HYPER, {**sites, "w": w})
        assert joint - log_cond == pytest.approx(logp(collapsed, data, HYPER, sites), rel=1e-10)


def test_collapsing_h_equals_joint_minus_conditional(data):
    """log p(y, theta without h) = log p(y, h, theta) - log p(h | y, theta) (w integrated out)."""
    p = draw("lmpromp", HYPER, data, 5)
    h = np.random.default_rng(6).normal(size=(3, 2))
    log_cond = 0.0
    for i in range(3):
        psi, y = observed_rows(data, i)
        design = psi @ p["M"]
        cov_y = np.eye(len(y)) / HYPER.beta + psi @ psi.T / p["alpha"]
        precision = HYPER.gamma * np.eye(2) + design.T @ np.linalg.solve(cov_y, design)
        mean = np.linalg.solve(precision, design.T @ np.linalg.solve(cov_y, y - psi @ p["b"]))
        log_cond += stats.multivariate_normal.logpdf(h[i], mean, np.linalg.inv(precision))
    with_h = logp(lmpromp_collapsed_model, data, HYPER, {**p, "h": h})
    without_h = logp(lmpromp_collapsed_model, data, HYPER, {k: v for k, v in p.items() if k != "h"}, collapse_h=True)
    assert with_h - log_cond == pytest.approx(without_h, rel=1e-10)


def test_collapsed_mixture_is_logsumexp_over_assignments_of_joint_minus_conditional(data):
    """log p(y, h, theta) = logsumexp_z [log p(y, w, h, z, theta) - log p(w | y, h, z, theta)]."""
    p = draw("mixture", HYPER, data, 7)
    w = np.random.default_rng(8).normal(size=(3, 4))
    terms = []
    for z in itertools.product(range(2), repeat=3):
        joint = logp(mixture_model, data, HYPER, {**p, "w": w, "z": np.array(z)}, marginalize=False)
        log_cond = sum(
            stats.multivariate_normal.logpdf(w[i], *dense_w_conditional(data, HYPER, p, i, z[i]))
            for i in range(3)
        )
        terms.append(joint - log_cond)
    assert special.logsumexp(terms) == pytest.approx(logp(mixture_collapsed_model, data, HYPER, p), rel=1e-10)


# ------------------------------------------------------------------ exact conditionals
def test_gaussian_conditional_matches_dense():
    rng = np.random.default_rng(9)
    n, p = 7, 3
    A, o, m = rng.normal(size=(n, p)), rng.normal(size=n), rng.normal(size=p)
    B = rng.normal(size=(p, p))
    prior_prec, nu = B @ B.T + np.eye(p), 2.5
    mean, chol, log_evidence = gaussian_conditional(A.T @ A, A.T @ o, o @ o, float(n), nu, m, prior_prec)
    C = np.linalg.inv(prior_prec)
    cov_o = np.eye(n) / nu + A @ C @ A.T
    gain = C @ A.T @ np.linalg.inv(cov_o)
    assert_allclose(mean, m + gain @ (o - A @ m), rtol=1e-10)
    assert_allclose(np.linalg.inv(chol @ chol.T), C - gain @ A @ C, rtol=1e-10, atol=1e-14)
    assert float(log_evidence) == pytest.approx(stats.multivariate_normal.logpdf(o, A @ m, cov_o), rel=1e-12)


NUM_DRAWS = 2000


def stack_chains(p0, p1):
    """Parameters with sample dims (chain=2, draw=NUM_DRAWS): chain c repeats p_c."""
    return {k: np.stack([np.broadcast_to(p0[k], (NUM_DRAWS,) + np.shape(p0[k])),
                         np.broadcast_to(p1[k], (NUM_DRAWS,) + np.shape(p1[k]))]) for k in p0}


def assert_moments(samples, mean, cov):
    """Sample mean and covariance (about the exact mean) within 4 Monte Carlo standard errors."""
    n = samples.shape[0]
    se = samples.std(axis=0, ddof=1) / np.sqrt(n)
    assert np.all(np.abs(samples.mean(axis=0) - mean) <= 4 * se), (samples.mean(axis=0), mean, se)
    centred = samples - mean
    products = centred[:, :, None] * centred[:, None, :]
    se = products.std(axis=0, ddof=1) / np.sqrt(n)
    assert np.all(np.abs(products.mean(axis=0) - cov) <= 4 * se), (products.mean(axis=0), cov, se)


def mixture_conditional(data, hyper, p, i, keep_h):
    """Exact mean and covariance of the Gaussian-mixture p(w_i | theta, y_i) (z summed out)."""
    log_r = [np.log(p["pi"][k]) + dense_marginal(data, hyper, p, i, k, keep_h) for k in range(2)]
    r = np.exp(log_r - special.logsumexp(log_r))
    parts = [dense_w_conditional(data, hyper, p, i, k, keep_h) for k in range(2)]
    mean = sum(r[k] * parts[k][0] for k in range(2))
    second = sum(r[k] * (parts[k][1] + np.outer(parts[k][0], parts[k][0])) for k in range(2))
    return r, mean, second - np.outer(mean, mean)


@pytest.mark.parametrize(
    "model_name, keep_h", [("lmpromp", True), ("lmpromp", False), ("mixture", True), ("mixture", False), ("promp", True)]
)
def test_sample_w_given_theta_matches_exact_conditional(data, model_name, keep_h):
    hyper = HYPER.replace(beta=1.0)  # weakly informative y: the mixture's responsibilities stay mixed
    p0, p1 = draw(model_name, hyper, data, 10), draw(model_name, hyper, data, 11)
    if model_name == "mixture":
        # components close enough that both explain some demonstrations
        for p in (p0, p1):
            p["b"][1] = p["b"][0] + 0.5
            p["alpha"][:] = 2.0
    if not keep_h:
        del p0["h"], p1["h"]
    w = np.asarray(sample_w_given_theta(jax.random.key(12), data, hyper, stack_chains(p0, p1)))
    assert w.shape == (2, NUM_DRAWS, 3, 4)
    mixed = 0
    for chain, p in enumerate((p0, p1)):
        for i in range(3):
            if model_name == "mixture":
                r, mean, cov = mixture_conditional(data, hyper, p, i, keep_h)
                mixed += bool(0.05 < r[0] < 0.95)
            else:
                mean, cov = dense_w_conditional(data, hyper, p, i, None, keep_h)
            assert_moments(w[chain, :, i], mean, cov)
    if model_name == "mixture":
        assert mixed >= 2  # the draw of z was exercised


def test_sample_w_given_theta_uses_given_z_and_learned_beta(data):
    hyper = HYPER.replace(learn_beta=True)
    p = draw("mixture", hyper, data, 13)
    z = np.array([1, 0, 1])
    params = stack_chains({**p, "z": z}, {**p, "z": 1 - z})
    del params["pi"]
    w = np.asarray(sample_w_given_theta(jax.random.key(14), data, hyper, params))
    for chain, zc in enumerate((z, 1 - z)):
        for i in range(3):
            assert_moments(w[chain, :, i], *dense_w_conditional(data, hyper, p, i, zc[i]))


def test_sample_h_given_theta_matches_exact_conditional(data):
    rng = np.random.default_rng(15)
    gamma = HYPER.gamma
    # single type: h_i | w_i ~ N(alpha P^-1 M^T (w_i - b), P^-1), P = gamma I + alpha M^T M
    p = draw("lmpromp", HYPER, data, 16)
    del p["h"]
    p["w"] = rng.normal(size=(3, 4))
    h = np.asarray(sample_h_given_theta(jax.random.key(17), HYPER, stack_chains(p, p)))
    assert h.shape == (2, NUM_DRAWS, 3, 2)
    for i in range(3):
        precision = gamma * np.eye(2) + p["alpha"] * p["M"].T @ p["M"]
        cov = np.linalg.inv(precision)
        assert_moments(h.reshape(-1, 3, 2)[:, i], p["alpha"] * cov @ p["M"].T @ (p["w"][i] - p["b"]), cov)
    # mixture, z summed out: with prob r_k, h_ik from the conditional and the other h_ij from the prior
    q = draw("mixture", HYPER, data, 18)
    del q["h"]
    q["b"][1] = q["b"][0] + 0.3
    q["w"] = q["b"][0] + rng.normal(size=(3, 4))
    h = np.asarray(sample_h_given_theta(jax.random.key(19), HYPER, stack_chains(q, q))).reshape(-1, 3, 2, 2)
    for i in range(3):
        log_r, means, covs = [], [], []
        for k in range(2):
            M, alpha, resid = q["M"][k], q["alpha"][k], q["w"][i] - q["b"][k]
            log_r.append(np.log(q["pi"][k]) + stats.multivariate_normal.logpdf(
                resid, np.zeros(4), np.eye(4) / alpha + M @ M.T / gamma))
            covs.append(np.linalg.inv(gamma * np.eye(2) + alpha * M.T @ M))
            means.append(alpha * covs[k] @ M.T @ resid)
        r = np.exp(log_r - special.logsumexp(log_r))
        mean = np.concatenate([r[k] * means[k] for k in range(2)])
        cov = np.zeros((4, 4))
        for k in range(2):
            block = r[k] * (covs[k] + np.outer(means[k], means[k])) + (1 - r[k]) * np.eye(2) / gamma
            cov[2 * k:2 * k + 2, 2 * k:2 * k + 2] = block
        assert_moments(h[:, i].reshape(-1, 4), mean, cov - np.outer(mean, mean))


def test_conditional_samplers_refuse_bad_params(data):
    p = draw("lmpromp", HYPER, data, 0)
    with pytest.raises(LmprompError, match="lack"):
        sample_w_given_theta(jax.random.key(0), data, HYPER, {"b": p["b"], "M": p["M"]})
    with pytest.raises(LmprompError, match="shape"):
        sample_w_given_theta(jax.random.key(0), data, HYPER, {**p, "alpha": np.ones(3)})
    with pytest.raises(LmprompError, match="beta"):
        sample_w_given_theta(jax.random.key(0), data, HYPER.replace(learn_beta=True), p)
    with pytest.raises(LmprompError, match="needs 'w'"):
        sample_h_given_theta(jax.random.key(0), HYPER, p)


def test_collapsed_prior_predictive(data):
    """observed=False: y is sampled (no padding factor); for fixed theta its draws have the
    mean and covariance of the mixture of low-rank Gaussians sum_k pi_k N(Psi b_k, beta^-1 I + Psi C_k Psi^T)."""
    p = draw("mixture", HYPER, data, 20)
    del p["h"]
    trace = handlers.trace(handlers.substitute(handlers.seed(mixture_collapsed_model, 0), p)).get_trace(
        data, HYPER, collapse_h=True, observed=False
    )
    assert trace["y"]["value"].shape == (3, 12) and "y_missing" not in trace
    num = 4000
    fixed = {k: np.broadcast_to(v, (num,) + np.shape(v)) for k, v in p.items()}
    predictive = Predictive(mixture_collapsed_model, posterior_samples=fixed, return_sites=["y"])
    y = np.asarray(predictive(jax.random.key(1), data, HYPER, collapse_h=True, observed=False)["y"])
    mask = np.asarray(data.mask)
    for i in range(3):
        psi, _ = observed_rows(data, i)
        means, seconds = [], []
        for k in range(2):
            m, C = weight_prior(HYPER, p, i, k, keep_h=False)
            means.append(psi @ m)
            seconds.append(psi @ C @ psi.T + np.eye(len(psi)) / HYPER.beta + np.outer(psi @ m, psi @ m))
        mean = sum(p["pi"][k] * means[k] for k in range(2))
        cov = sum(p["pi"][k] * seconds[k] for k in range(2)) - np.outer(mean, mean)
        assert_moments(y[:, i, mask[i] == 1], mean, cov)


def test_traced_data_and_finite_gradients(data):
    """Under jit (data traced, value checks skipped) the density is unchanged, and the NaN
    held by a masked entry of y does not reach the gradient."""
    p = draw("mixture", HYPER, data, 21)
    del p["h"]

    def f(params, data):
        return log_density(mixture_collapsed_model, (data, HYPER), {"collapse_h": True}, params)[0]

    value, grads = jax.jit(jax.value_and_grad(f))(p, data)
    assert float(value) == pytest.approx(logp(mixture_collapsed_model, data, HYPER, p, collapse_h=True), rel=1e-12)
    assert all(np.all(np.isfinite(g)) for g in jax.tree_util.tree_leaves(grads))


# ------------------------------------------------------------- b integrated out ("whb")
@pytest.mark.parametrize("learn_beta", [False, True])
def test_offset_collapsed_density_matches_one_dense_gaussian(data, learn_beta):
    """b couples the demonstrations: y (all observed entries) ~ N(0, blockdiag K_i + Psi Psi^T / lambda0)."""
    hyper = HYPER.replace(learn_beta=learn_beta)
    p = draw("lmpromp", hyper, data, 7)
    rows = [observed_rows(data, i) for i in range(data.psi.shape[0])]
    psi_all = np.concatenate([r[0] for r in rows])
    y_all = np.concatenate([r[1] for r in rows])
    blocks = [psi @ weight_prior(hyper, p, i, keep_h=False)[1] @ psi.T + np.eye(len(y)) / beta_of(hyper, p)
              for i, (psi, y) in enumerate(rows)]
    cov = block_diag(*blocks) + psi_all @ psi_all.T / hyper.lambda0
    prior = prior_logp(hyper, p, "lmpromp", keep_h=False) - stats.norm.logpdf(p["b"], 0, hyper.lambda0**-0.5).sum()
    expected = prior + stats.multivariate_normal.logpdf(y_all, np.zeros(len(y_all)), cov)
    sites = {k: v for k, v in p.items() if k not in ("b", "h")}
    assert logp(lmpromp_offset_collapsed_model, data, hyper, sites) == pytest.approx(expected, rel=1e-10)


def test_collapsing_b_equals_joint_minus_conditional(data):
    """log p(y, theta) = log p(y, b, theta) - log p(b | y, theta) for every b (w and h integrated out).

    The identity holds for all b only when both the marginal and the conditional
    of :func:`offset_marginal` are exact.
    """
    hyper = HYPER.replace(learn_beta=True)
    p = draw("lmpromp", hyper, data, 8)
    sites = {k: v for k, v in p.items() if k not in ("b", "h")}
    collapsed = logp(lmpromp_offset_collapsed_model, data, hyper, sites)
    _, mean, chol = offset_marginal(
        data_statistics(masked_observations(data)), p["M"], p["alpha"], p["beta"], hyper.lambda0, hyper.gamma
    )
    cov = np.linalg.inv(np.asarray(chol) @ np.asarray(chol).T)
    rng = np.random.default_rng(9)
    for _ in range(3):
        b = rng.normal(size=mean.shape)
        joint = logp(lmpromp_collapsed_model, data, hyper, {**sites, "b": b}, collapse_h=True)
        assert joint - stats.multivariate_normal.logpdf(b, mean, cov) == pytest.approx(collapsed, rel=1e-10)

"""The full model declarations (promp, lmpromp, mixture) against hand-written densities.

Every log density of :mod:`lmpromp_ppl.models` is compared with one written
here with scipy.stats on ragged, padded data whose masked entries hold garbage;
prior-predictive moments are compared with their closed forms within 4 Monte
Carlo standard errors.
"""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpyro.infer.util import log_density
from scipy import special, stats

from lmpromp_ppl.data.core import Demonstrations, ModelData, model_data
from lmpromp_ppl.errors import DataError, LmprompError
from lmpromp_ppl.inference.classical import classical_promp
from lmpromp_ppl.models import (
    PROPER,
    SIMULATION,
    THESIS,
    Hyperparameters,
    get_model,
    lmpromp_model,
    mixture_model,
    promp_model,
    sample_prior,
    sample_prior_predictive,
)
from lmpromp_ppl.models.prior import check_simulable

NUM_BASIS = 2
# every hyperparameter distinct, so that a swapped one changes the density
HYPER = Hyperparameters(
    beta=4.0, lambda0=0.7, gamma=1.3, a0=2.5, b0=0.6, c0=1.7, d0=0.9, latent_dim=2,
    num_components=2, kappa0=0.8, beta_a0=3.0, beta_b0=0.5, promp_scale=0.8,
    lkj_concentration=1.5,
)


def ragged_data(seed: int = 0) -> ModelData:
    """L = 3 demonstrations of lengths 6, 4, 5 with D = 2 (d = 4, S = 12), one missing
    entry inside demonstration 1, and garbage (NaN, large values) in every masked entry."""
    rng = np.random.default_rng(seed)
    lengths = (6, 4, 5)
    times = [np.sort(rng.uniform(0, 1, n)) + np.arange(n) for n in lengths]
    positions = [rng.normal(size=(n, 2)) for n in lengths]
    data = model_data(Demonstrations(times, positions), NUM_BASIS)
    psi, y, mask = (np.array(a) for a in data.dense())
    mask[1, 3] = 0.0
    y[mask == 0] = 1e3
    y[1, 3] = np.nan
    psi[mask == 0] = 7.0
    return ModelData(jnp.asarray(psi), jnp.asarray(y), jnp.asarray(mask))


@pytest.fixture(scope="module")
def data():
    return ragged_data()


def draw(model_name, hyper, data, seed):
    """Random parameter values (numpy) for every latent site of ``model_name``."""
    rng = np.random.default_rng(seed)
    L, _, d = data.psi.shape
    V, K = hyper.latent_dim, hyper.num_components
    p = {}
    if model_name == "promp":
        p["mu_w"] = rng.normal(size=d)
        p["w_scale"] = rng.gamma(2.0, 0.5, size=d)
        a = rng.normal(size=(d, d + 2))
        cov = a @ a.T
        p["w_corr_chol"] = np.linalg.cholesky(cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov))))
        chol = p["w_scale"][:, None] * p["w_corr_chol"]
        p["Sigma_w"] = chol @ chol.T
        p["w"] = p["mu_w"] + rng.normal(size=(L, d)) @ chol.T
    else:
        prefix = () if model_name == "lmpromp" else (K,)
        p["b"] = rng.normal(size=prefix + (d,))
        p["lam"] = rng.gamma(2.0, 1.0, size=prefix + (V,))
        p["M"] = rng.normal(size=prefix + (d, V)) / np.sqrt(p["lam"])[..., None, :]
        p["alpha"] = rng.gamma(3.0, 1.0, size=prefix)
        p["h"] = rng.normal(size=(L,) + prefix + (V,))
        p["w"] = rng.normal(size=(L, d))
        if model_name == "mixture":
            p["pi"] = rng.dirichlet(np.ones(K))
            p["z"] = rng.integers(0, K, size=L)
    if hyper.learn_beta:
        p["beta"] = rng.gamma(4.0, 1.0)
    return p


def numpyro_logp(model, data, hyper, params, **kwargs):
    return float(log_density(model, (data, hyper), kwargs, params)[0])


# ------------------------------------------------------------ hand-written densities
def y_loglik(data, w, beta):
    psi, y, mask = (np.asarray(a) for a in data)
    total = 0.0
    for i in range(psi.shape[0]):
        o = mask[i] == 1
        total += stats.norm.logpdf(y[i, o], psi[i, o] @ w[i], beta**-0.5).sum()
    return total


def beta_of(hyper, p):
    if hyper.learn_beta:
        return p["beta"], stats.gamma.logpdf(p["beta"], hyper.beta_a0, scale=1 / hyper.beta_b0)
    return hyper.beta, 0.0


def component_logp(hyper, b, lam, M, alpha):
    """Priors of b, lam, M, alpha of one component (Sec. 4.1)."""
    return (
        stats.norm.logpdf(b, 0, hyper.lambda0**-0.5).sum()
        + stats.gamma.logpdf(lam, hyper.c0, scale=1 / hyper.d0).sum()
        + stats.norm.logpdf(M, 0, 1 / np.sqrt(lam)[None, :]).sum()
        + stats.gamma.logpdf(alpha, hyper.a0, scale=1 / hyper.b0)
    )


def hand_lmpromp(data, hyper, p):
    beta, lp_beta = beta_of(hyper, p)
    lp = component_logp(hyper, p["b"], p["lam"], p["M"], p["alpha"]) + lp_beta
    lp += stats.norm.logpdf(p["h"], 0, hyper.gamma**-0.5).sum()
    for i in range(p["w"].shape[0]):
        lp += stats.norm.logpdf(p["w"][i], p["b"] + p["M"] @ p["h"][i], p["alpha"] ** -0.5).sum()
    return lp + y_loglik(data, p["w"], beta)


def hand_mixture(data, hyper, p, z=None):
    """Eq. 4.8 with z summed out (z None) or given."""
    beta, lp_beta = beta_of(hyper, p)
    K = hyper.num_components
    lp = stats.dirichlet.logpdf(p["pi"], np.full(K, hyper.kappa0)) + lp_beta
    for k in range(K):
        lp += component_logp(hyper, p["b"][k], p["lam"][k], p["M"][k], p["alpha"][k])
    lp += stats.norm.logpdf(p["h"], 0, hyper.gamma**-0.5).sum()
    for i in range(p["w"].shape[0]):
        terms = [
            np.log(p["pi"][k])
            + stats.norm.logpdf(
                p["w"][i], p["b"][k] + p["M"][k] @ p["h"][i, k], p["alpha"][k] ** -0.5
            ).sum()
            for k in range(K)
        ]
        lp += special.logsumexp(terms) if z is None else terms[z[i]]
    return lp + y_loglik(data, p["w"], beta)


def lkj_cholesky_logpdf(chol, eta):
    """LKJ density of a correlation Cholesky factor: det(C)^(eta-1) / c_d times the Jacobian
    prod_i L_ii^(d-i) of C = L L^T, with c_d from Lewandowski, Kurowicka & Joe (2009), eq. 16."""
    d = chol.shape[0]
    i = np.arange(2, d + 1)
    unnormalised = np.sum((d - i + 2 * eta - 2) * np.log(np.diag(chol)[1:]))
    k = np.arange(1, d)
    log_c = np.sum(
        (2 * eta - 2 + d - k) * (d - k) * np.log(2)
        + (d - k) * special.betaln(eta + (d - k - 1) / 2, eta + (d - k - 1) / 2)
    )
    return unnormalised - log_c


def hand_promp(data, hyper, p):
    beta, lp_beta = beta_of(hyper, p)
    sigma = np.diag(p["w_scale"]) @ p["w_corr_chol"] @ p["w_corr_chol"].T @ np.diag(p["w_scale"])
    lp = (
        stats.norm.logpdf(p["mu_w"], 0, hyper.lambda0**-0.5).sum()
        + stats.halfnorm.logpdf(p["w_scale"], scale=hyper.promp_scale).sum()
        + lkj_cholesky_logpdf(p["w_corr_chol"], hyper.lkj_concentration)
        + lp_beta
    )
    lp += sum(stats.multivariate_normal.logpdf(w, p["mu_w"], sigma) for w in p["w"])
    return lp + y_loglik(data, p["w"], beta)


# ---------------------------------------------------------------------- densities
@pytest.mark.parametrize("learn_beta", [False, True])
def test_lmpromp_log_density_matches_scipy(data, learn_beta):
    hyper = HYPER.replace(learn_beta=learn_beta)
    for seed in range(2):
        p = draw("lmpromp", hyper, data, seed)
        assert ("beta" in p) == learn_beta
        expected = hand_lmpromp(data, hyper, p)
        assert np.isfinite(expected)
        assert numpyro_logp(lmpromp_model, data, hyper, p) == pytest.approx(expected, rel=1e-10)


@pytest.mark.parametrize("learn_beta", [False, True])
def test_mixture_log_density_matches_scipy(data, learn_beta):
    hyper = HYPER.replace(learn_beta=learn_beta)
    p = draw("mixture", hyper, data, 3)
    z = p.pop("z")
    assert p["h"].shape == (3, 2, 2) and p["M"].shape == (2, 4, 2)
    marginal = numpyro_logp(mixture_model, data, hyper, p)
    assert marginal == pytest.approx(hand_mixture(data, hyper, p), rel=1e-10)
    explicit = numpyro_logp(mixture_model, data, hyper, {**p, "z": z}, marginalize=False)
    assert explicit == pytest.approx(hand_mixture(data, hyper, p, z), rel=1e-10)


def test_marginal_mixture_is_logsumexp_over_assignments(data):
    p = draw("mixture", HYPER, data, 4)
    del p["z"]
    L, K = data.psi.shape[0], HYPER.num_components
    explicit = [
        numpyro_logp(mixture_model, data, HYPER, {**p, "z": np.array(z)}, marginalize=False)
        for z in itertools.product(range(K), repeat=L)
    ]
    assert len(explicit) == K**L == 8
    marginal = numpyro_logp(mixture_model, data, HYPER, p)
    assert marginal == pytest.approx(special.logsumexp(explicit), rel=1e-10)


def test_lkj_reference_density_is_the_beta_law_for_d2():
    # for d = 2 the correlation r = L_21 satisfies (r + 1) / 2 ~ Beta(eta, eta)
    for r, eta in [(0.3, 1.5), (-0.8, 2.0)]:
        chol = np.array([[1.0, 0.0], [r, np.sqrt(1 - r**2)]])
        expected = stats.beta.logpdf((r + 1) / 2, eta, eta) - np.log(2)
        assert lkj_cholesky_logpdf(chol, eta) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("learn_beta", [False, True])
def test_promp_log_density_matches_scipy(data, learn_beta):
    hyper = HYPER.replace(learn_beta=learn_beta)
    p = draw("promp", hyper, data, 5)
    sigma = p.pop("Sigma_w")
    chol = p["w_scale"][:, None] * p["w_corr_chol"]
    np.testing.assert_allclose(sigma, chol @ chol.T, rtol=1e-12)
    assert numpyro_logp(promp_model, data, hyper, p) == pytest.approx(
        hand_promp(data, hyper, p), rel=1e-10
    )


def test_masked_entries_do_not_contribute(data):
    """The same density with the masked entries removed from a demonstration's end."""
    p = draw("lmpromp", HYPER, data, 6)
    psi, y, mask = (np.array(a) for a in data.dense())
    # demonstration 2 without its padding: truncate every demonstration to its own length
    keep = mask[2] == 1
    short = ModelData(jnp.asarray(psi[2:, keep]), jnp.asarray(y[2:, keep]), jnp.ones((1, keep.sum())))
    one = {**p, "h": p["h"][2:], "w": p["w"][2:]}
    padded = ModelData(*(jnp.asarray(a[2:]) for a in (psi, y, mask)))
    assert numpyro_logp(lmpromp_model, padded, HYPER, one) == pytest.approx(
        numpyro_logp(lmpromp_model, short, HYPER, one), rel=1e-12
    )


# ------------------------------------------------------------------ registry, errors
def test_get_model_registry():
    assert get_model("lmpromp") is lmpromp_model
    assert get_model("promp") is promp_model
    assert get_model("lmpromp_mixture") is mixture_model
    assert get_model("mixture", marginalize=False).keywords == {"marginalize": False}
    assert get_model("mixture", collapsed=True, collapse_h=True).func.__name__ == "mixture_collapsed_model"
    with pytest.raises(LmprompError, match="unknown model"):
        get_model("gmm")
    with pytest.raises(LmprompError, match="no option"):
        get_model("lmpromp", marginalize=False)


def test_bad_data_is_refused(data):
    p = draw("lmpromp", HYPER, data, 0)
    psi, y, mask = (np.array(a) for a in data.dense())
    y[0, 0] = np.nan
    with pytest.raises(DataError, match="NaN"):
        numpyro_logp(lmpromp_model, ModelData(psi, y, mask), HYPER, p)
    with pytest.raises(DataError, match="shape"):
        numpyro_logp(lmpromp_model, ModelData(psi, y[:, :-1], mask), HYPER, p)
    with pytest.raises(DataError, match="mask"):
        numpyro_logp(lmpromp_model, ModelData(psi, np.asarray(data.y), mask * 0.5), HYPER, p)
    with pytest.raises(LmprompError, match="exceeds"):
        numpyro_logp(lmpromp_model, data, HYPER.replace(latent_dim=5), p)


def test_prior_simulation_refuses_near_improper_priors(data):
    for hyper in (THESIS, PROPER):
        with pytest.raises(LmprompError, match="simulation"):
            sample_prior("lmpromp", jax.random.key(0), data, hyper, 2)
    with pytest.raises(LmprompError, match="beta_a0"):
        sample_prior("promp", jax.random.key(0), data, SIMULATION.replace(learn_beta=True, beta_a0=1e-3), 2)
    with pytest.raises(LmprompError, match="unknown model"):
        sample_prior("gmm", jax.random.key(0), data, SIMULATION, 2)
    # the ProMP has no Gamma prior unless beta is learned; SIMULATION is simulable
    check_simulable("promp", THESIS)
    for name in ("promp", "lmpromp", "mixture"):
        check_simulable(name, SIMULATION.replace(learn_beta=True))


# ------------------------------------------------------------- prior predictive moments
# shapes above 4 give 1/alpha, 1/lam, 1/beta finite fourth moments, so the
# Monte Carlo standard errors of the second moments below are themselves reliable
MOMENT_HYPER = Hyperparameters(
    beta=4.0, lambda0=2.0, gamma=1.5, a0=6.0, b0=5.0, c0=6.0, d0=5.0, latent_dim=2,
    num_components=2, kappa0=2.0, learn_beta=True, beta_a0=6.0, beta_b0=2.5, promp_scale=0.8,
)
NUM_DRAWS = 4000


def assert_mean_within_4se(samples, expected):
    """Mean over axis 0 equals ``expected`` within 4 Monte Carlo standard errors."""
    samples = np.asarray(samples)
    se = samples.std(axis=0, ddof=1) / np.sqrt(samples.shape[0])
    assert np.all(se > 0)
    assert np.all(np.abs(samples.mean(axis=0) - expected) <= 4 * se), (samples.mean(axis=0), expected, se)


def weight_variance(hyper, model_name):
    """Var[w_j]: 1/lambda0 + V E[1/lam] / gamma + E[1/alpha] (Gamma: E[1/x] = rate / (shape - 1));
    for the ProMP 1/lambda0 + E[w_scale^2] = 1/lambda0 + promp_scale^2."""
    if model_name == "promp":
        return 1 / hyper.lambda0 + hyper.promp_scale**2
    inv_lam = hyper.d0 / (hyper.c0 - 1)
    inv_alpha = hyper.b0 / (hyper.a0 - 1)
    return 1 / hyper.lambda0 + hyper.latent_dim * inv_lam / hyper.gamma + inv_alpha


@pytest.mark.parametrize("model_name", ["lmpromp", "mixture", "promp"])
def test_prior_predictive_moments(data, model_name):
    # beta learned in one model only: each Gamma site costs a sampler compilation
    hyper = MOMENT_HYPER.replace(learn_beta=model_name == "lmpromp")
    draws = sample_prior_predictive(model_name, jax.random.key(11), data, hyper, NUM_DRAWS)
    w = np.asarray(draws["w"])
    y = np.asarray(draws["y"])
    assert w.shape == (NUM_DRAWS, 3, 4) and y.shape == (NUM_DRAWS, 3, 12)
    var_w = weight_variance(hyper, model_name)
    # E[w] = 0, E[w_j^2] = Var[w_j]; the prior covariance of w is isotropic
    assert_mean_within_4se(w.reshape(NUM_DRAWS, -1), 0.0)
    assert_mean_within_4se(w.reshape(NUM_DRAWS, -1) ** 2, var_w)
    assert_mean_within_4se(w[:, 0, 0] * w[:, 0, 1], 0.0)
    # y_s = psi_s w + noise: Var = |psi_s|^2 Var[w_j] + E[1/beta]; masked entries are 0
    psi, _, mask = (np.asarray(a) for a in data)
    observed = mask == 1
    inv_beta = hyper.beta_b0 / (hyper.beta_a0 - 1) if hyper.learn_beta else 1 / hyper.beta
    var_y = np.sum(psi**2, axis=-1) * var_w + inv_beta
    assert np.all(y[:, ~observed] == 0)
    assert_mean_within_4se(y[:, observed] ** 2, var_y[observed])
    if model_name == "mixture":
        assert draws["z"].shape == (NUM_DRAWS, 3)
        assert_mean_within_4se(np.asarray(draws["pi"]), 1 / 2)
        assert_mean_within_4se(np.asarray(draws["z"] == 0, dtype=float), 1 / 2)


# ------------------------------------------------------------------- classical ProMP
def test_classical_promp(data):
    psi, y, mask = (np.asarray(a) for a in data)
    mu, sigma, w_hat = classical_promp(data, ridge=0.0, shrinkage=0.0)
    for i in range(3):
        o = mask[i] == 1
        np.testing.assert_allclose(w_hat[i], np.linalg.lstsq(psi[i, o], y[i, o], rcond=None)[0], rtol=1e-9)
    np.testing.assert_allclose(mu, w_hat.mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(sigma, np.cov(w_hat, rowvar=False), rtol=1e-12)
    _, shrunk, _ = classical_promp(data, ridge=0.0, shrinkage=0.5)
    target = np.trace(sigma) / 4 * np.eye(4)
    np.testing.assert_allclose(shrunk, 0.5 * sigma + 0.5 * target, rtol=1e-12)
    _, lw, _ = classical_promp(data, ridge=0.0)
    from sklearn.covariance import ledoit_wolf

    np.testing.assert_allclose(lw, ledoit_wolf(w_hat)[0], rtol=1e-12)
    assert np.all(np.linalg.eigvalsh(lw) > 0)
    # the same from Demonstrations, and the ridge shrinks the fit toward 0
    rng = np.random.default_rng(1)
    demos = Demonstrations([np.linspace(0, 1, n) for n in (5, 7, 6)], [rng.normal(size=(n, 2)) for n in (5, 7, 6)])
    from_demos = classical_promp(demos, num_basis=3)
    from_data = classical_promp(model_data(demos, 3))
    np.testing.assert_allclose(from_demos[2], from_data[2], rtol=1e-12)
    ridged = classical_promp(demos, num_basis=3, ridge=10.0)[2]
    assert np.linalg.norm(ridged) < np.linalg.norm(from_demos[2])
    with pytest.raises(LmprompError, match="num_basis"):
        classical_promp(demos)
    with pytest.raises(LmprompError, match="shrinkage"):
        classical_promp(data, shrinkage=1.5)

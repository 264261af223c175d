"""NUTS engine (lmpromp_ppl.inference.nuts): exactness on a conjugate case, layout, models.

Sizes follow the contracts' budget (L <= 8, d <= 8, V <= 2, 2 chains x 300 draws).
"""

import numpy as np
import pytest
import jax
import arviz_stats

from lmpromp_ppl.data.core import model_data, standardise
from lmpromp_ppl.data.synthetic import latent_manifold
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.diagnostics.metrics import quantity_reliability
from lmpromp_ppl.inference.nuts import fit_nuts
from lmpromp_ppl.quantities import invariant_quantities
from lmpromp_ppl.models.hyper import preset

NUM_DRAWS = 300


@pytest.fixture(scope="module")
def data():
    demos = latent_manifold(L=4, D=2, J=3, V=2, T=10, seed=1)
    return model_data(standardise(demos)[0], 3)


@pytest.fixture(scope="module")
def hyper():
    return preset("proper", latent_dim=2, learn_beta=False)  # the exact posteriors below take beta as known


@pytest.fixture(scope="module")
def theta(data):
    """Fixed b, M, alpha, lam: the posterior of (w, h) is then Gaussian."""
    rng = np.random.default_rng(3)
    d = data.psi.shape[2]
    return {
        "b": rng.normal(size=d),
        "M": rng.normal(size=(d, 2)),
        "alpha": np.asarray(4.0),
        "lam": np.array([1.0, 2.0]),
    }


def exact_posterior(data, hyper, theta):
    r"""Mean (L, d + V) and covariance (L, d + V, d + V) of p(w_i, h_i | theta, y_i).

    -log p = alpha/2 |w - b - M h|^2 + gamma/2 |h|^2 + beta/2 |y - Psi w|^2 (observed rows):
    precision [[alpha I + beta Psi^T Psi, -alpha M], [-alpha M^T, gamma I + alpha M^T M]],
    linear term [beta Psi^T y + alpha b, -alpha M^T b].
    """
    psi = np.asarray(data.psi) * np.asarray(data.mask)[..., None]
    y = np.asarray(data.y) * np.asarray(data.mask)
    b, M, alpha = theta["b"], theta["M"], float(theta["alpha"])
    d, V = M.shape
    means, covs = [], []
    for psi_i, y_i in zip(psi, y):
        precision = np.block([
            [alpha * np.eye(d) + hyper.beta * psi_i.T @ psi_i, -alpha * M],
            [-alpha * M.T, hyper.gamma * np.eye(V) + alpha * M.T @ M],
        ])
        linear = np.concatenate([hyper.beta * psi_i.T @ y_i + alpha * b, -alpha * M.T @ b])
        cov = np.linalg.inv(precision)
        means.append(cov @ linear)
        covs.append(cov)
    return np.array(means), np.array(covs)


@pytest.fixture(scope="module")
def conjugate_runs(data, hyper, theta):
    """NUTS on the full model and on the w-collapsed model, both with theta fixed."""
    return {
        collapsed: fit_nuts(
            "lmpromp", data, hyper, jax.random.key(11), collapsed=collapsed, num_chains=2,
            num_warmup=NUM_DRAWS, num_samples=NUM_DRAWS, fixed=theta,
        )
        for collapsed in ("none", "w")
    }


@pytest.mark.parametrize("collapsed", ["none", "w"])
def test_nuts_recovers_exact_gaussian_posterior(conjugate_runs, data, hyper, theta, collapsed):
    """Means, s.d.s and random projections of (w_i, h_i) match the exact posterior within 4 MCSE.

    With collapsed="w", NUTS samples h only and w is drawn from p(w | theta, h, y),
    so this also checks that the conditional draws complete the joint posterior.
    """
    result = conjugate_runs[collapsed]
    mean, cov = exact_posterior(data, hyper, theta)
    draws = np.concatenate([result.samples["w"], result.samples["h"]], axis=-1)  # (C, N, L, d + V)
    num_demos, dim = mean.shape
    # every coordinate plus 3 random directions per demonstration (these test the correlations)
    rng = np.random.default_rng(0)
    directions = np.concatenate([np.eye(dim), rng.normal(size=(3, dim))])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    for i in range(num_demos):
        projected = draws[:, :, i] @ directions.T  # (C, N, P)
        exact_mean = directions @ mean[i]
        exact_sd = np.sqrt(np.einsum("pd,de,pe->p", directions, cov[i], directions))
        for p in range(directions.shape[0]):
            x = projected[:, :, p]
            mcse_mean = float(arviz_stats.mcse(x, method="mean", chain_axis=0, draw_axis=1))
            mcse_sd = float(arviz_stats.mcse(x, method="sd", chain_axis=0, draw_axis=1))
            assert abs(x.mean() - exact_mean[p]) <= 4 * mcse_mean, (i, p)
            assert abs(x.std(ddof=1) - exact_sd[p]) <= 4 * mcse_sd, (i, p)


def test_nuts_result_layout(conjugate_runs, data):
    """Sites, shapes (chain, draw, ...), sample statistics; fixed sites left out."""
    num_demos, _, d = data.psi.shape
    full, collapsed = conjugate_runs["none"], conjugate_runs["w"]
    for result in (full, collapsed):
        assert set(result.samples) == {"w", "h"}
        assert result.samples["w"].shape == (2, NUM_DRAWS, num_demos, d)
        assert result.samples["h"].shape == (2, NUM_DRAWS, num_demos, 2)
        assert set(result.sample_stats) == {
            "diverging", "tree_depth", "step_size", "accept_prob", "energy", "num_steps"
        }
        for value in result.sample_stats.values():
            assert value.shape == (2, NUM_DRAWS)
        stats = result.sample_stats
        assert stats["diverging"].dtype == np.bool_
        assert int(stats["diverging"].sum()) == 0  # a Gaussian target has no divergences
        assert np.all((stats["num_steps"] >= 1) & (stats["num_steps"] <= 2**10 - 1))
        # tree depth k holds 2^(k-1) .. 2^k - 1 leapfrog steps
        assert np.all(2 ** (stats["tree_depth"] - 1) <= stats["num_steps"])
        assert np.all(stats["num_steps"] <= 2 ** stats["tree_depth"] - 1)
        # the step size is adapted during warm-up only
        assert np.all(stats["step_size"] == stats["step_size"][:, :1])
        assert np.all((stats["accept_prob"] >= 0) & (stats["accept_prob"] <= 1))
        assert result.seconds > 0 and result.compile_seconds > 0
    # the non-centred w of the full model is reported under its own name only
    assert full.options["noncentered"] == ["w"]
    assert full.options["fixed"] == ["M", "alpha", "b", "lam"]


def test_nuts_compiled_program_is_reused(conjugate_runs, data, hyper, theta):
    """Same configuration and key: the cached program runs again with identical draws."""
    first = conjugate_runs["w"]
    again = fit_nuts(
        "lmpromp", data, hyper, jax.random.key(11), collapsed="w", num_chains=2,
        num_warmup=NUM_DRAWS, num_samples=NUM_DRAWS, fixed=theta,
    )
    assert again.compile_seconds < first.compile_seconds
    np.testing.assert_array_equal(again.samples["w"], first.samples["w"])


@pytest.mark.parametrize(
    "model_name, latent_dim, num_components, expected",
    [
        ("promp", 1, 1, {"mu_w": (6,), "w_scale": (6,), "w_corr_chol": (6, 6), "Sigma_w": (6, 6), "w": (4, 6)}),
        ("mixture", 1, 2, {"pi": (2,), "b": (2, 6), "lam": (2, 1), "M": (2, 6, 1), "alpha": (2,),
                           "h": (4, 2, 1), "w": (4, 6)}),
    ],
)
def test_nuts_runs_each_model(data, model_name, latent_dim, num_components, expected):
    """The ProMP baseline and the mixture (z summed out) run collapsed and return their sites."""
    hyper = preset("proper", latent_dim=latent_dim, num_components=num_components, learn_beta=False)
    result = fit_nuts(model_name, data, hyper, jax.random.key(2), num_chains=2, num_warmup=60, num_samples=40)
    assert {k: v.shape[2:] for k, v in result.samples.items()} == expected
    assert all(v.shape[:2] == (2, 40) and np.all(np.isfinite(v)) for v in result.samples.values())


def test_identifiable_quantities_and_reliability():
    """Rotation-invariant summaries; R-hat flags chains stuck at different values."""
    rng = np.random.default_rng(0)
    M = rng.normal(size=(2, 200, 5, 2))
    rotation = np.array([[0.6, -0.8], [0.8, 0.6]])
    samples = {"b": rng.normal(size=(2, 200, 5)), "alpha": rng.gamma(2.0, size=(2, 200)),
               "lam": rng.gamma(2.0, size=(2, 200, 2)), "M": M}
    q = invariant_quantities(samples)
    rotated = invariant_quantities(dict(samples, M=M @ rotation))
    np.testing.assert_allclose(q["gram_eig"], rotated["gram_eig"], rtol=1e-10, atol=1e-12)
    assert np.all(np.diff(q["gram_eig"], axis=-1) <= 0)
    assert np.all(np.diff(q["lam_sorted"], axis=-1) >= 0)
    iid = quantity_reliability({"alpha": q["alpha"]})["alpha"]
    assert iid["rhat_max"] < 1.05 and iid["ess_bulk_min"] > 100
    stuck = quantity_reliability({"alpha": q["alpha"] + np.array([[0.0], [5.0]])})["alpha"]
    assert stuck["rhat_max"] > 1.5


def test_nuts_rejects_bad_options(data, hyper):
    with pytest.raises(LmprompError, match="unknown model"):
        fit_nuts("lmpromps", data, hyper, jax.random.key(0))
    with pytest.raises(LmprompError, match="collapsed"):
        fit_nuts("lmpromp", data, hyper, jax.random.key(0), collapsed="hw")
    with pytest.raises(LmprompError, match="no control variables"):
        fit_nuts("promp", data, hyper, jax.random.key(0), collapsed="wh")
    with pytest.raises(LmprompError, match="offsets"):
        fit_nuts("mixture", data, preset("proper", latent_dim=1, num_components=2), jax.random.key(0), collapsed="whb")
    with pytest.raises(LmprompError, match="init must be"):
        fit_nuts("lmpromp", data, hyper, jax.random.key(0), init="pathfinder")
    with pytest.raises(LmprompError, match="CAVI start"):
        fit_nuts("promp", data, preset("proper", latent_dim=1), jax.random.key(0), init="cavi")
    with pytest.raises(LmprompError, match="one per chain"):
        fit_nuts("lmpromp", data, hyper, jax.random.key(0), init_values={"alpha": np.ones(3)})
    with pytest.raises(LmprompError, match="unknown sites"):
        fit_nuts("lmpromp", data, hyper, jax.random.key(0), fixed={"beta": 1.0})
    with pytest.raises(LmprompError, match="shape"):
        fit_nuts("lmpromp", data, hyper, jax.random.key(0), fixed={"b": np.zeros(3)})
    with pytest.raises(LmprompError, match="target_accept"):
        fit_nuts("lmpromp", data, hyper, jax.random.key(0), target_accept=1.0)


def test_nuts_starts_from_cavi_and_integrates_b(data):
    """``collapsed="whb"``, ``init="cavi"``: ``b`` integrated out and drawn afterwards, one CAVI
    start per chain, and the noise learned (the sampling engines' preset infers beta, docs/defaults.md)."""
    hyper = preset("proper", latent_dim=2)
    assert hyper.learn_beta
    result = fit_nuts("lmpromp", data, hyper, jax.random.key(4), num_chains=2, num_warmup=60, num_samples=40,
                      collapsed="whb", init="cavi")
    assert np.all(result.samples["beta"] > 0)
    assert result.options["collapsed"] == "whb" and result.options["init"] == "cavi"
    assert result.options["init_seconds"] > 0
    shapes = {k: v.shape for k, v in result.samples.items()}
    L, _, d = data.psi.shape
    assert shapes["b"] == (2, 40, d) and shapes["w"] == (2, 40, L, d) and shapes["h"] == (2, 40, L, 2)
    assert all(np.all(np.isfinite(v)) for v in result.samples.values())
    # b is a fresh draw of its conditional at every step: it moves whenever M or alpha move
    assert np.all(np.std(result.samples["b"], axis=1) > 0)


def test_per_chain_starts_are_used(data, hyper):
    """``init_values`` with a chain axis: chain c starts at its own value.

    Same key twice: with per-chain starts (s0, s1) and with s0 shared, chain 0 is
    identical in the two runs and chain 1 is not.
    """
    d = data.psi.shape[2]
    M = np.random.default_rng(7).normal(size=(2, d, 2))
    per_chain = {"alpha": np.array([2.0, 50.0]), "lam": np.array([[1.0, 2.0], [30.0, 40.0]]), "M": M}
    shared = {k: v[0] for k, v in per_chain.items()}
    runs = [
        fit_nuts("lmpromp", data, hyper, jax.random.key(6), num_chains=2, num_warmup=5, num_samples=3, init_values=v)
        for v in (per_chain, shared)
    ]
    assert runs[0].options["init"] == "uniform"
    np.testing.assert_array_equal(runs[0].samples["alpha"][0], runs[1].samples["alpha"][0])
    assert not np.array_equal(runs[0].samples["alpha"][1], runs[1].samples["alpha"][1])

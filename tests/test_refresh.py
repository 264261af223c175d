"""The exact-conditional (Gibbs) refresh of LMProMP draws (lmpromp_ppl.inference.refresh).

* Each block's conditional equals the NumPyro declaration restricted to that block: the log
  joint minus the conditional's log density is the same at every value of the block
  (ragged demonstrations with a missing entry, learned beta, every hyperparameter distinct).
* The kernel leaves the posterior invariant (Geweke's test): sweeps started at the true
  parameters of datasets simulated from the prior leave the parameters distributed as the
  prior; the means of their log precisions and offset match the prior's within 4 Monte
  Carlo standard errors.
* The API: shapes, the locals redrawn, bad input.
"""

import jax
import jax.numpy as jnp
import numpy as np
import numpyro.distributions as dist
import pytest
from numpyro.infer.util import log_density
from scipy import special

from lmpromp_ppl.data.core import Demonstrations, ModelData, model_data
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference import refresh as rf
from lmpromp_ppl.models import SIMULATION, Hyperparameters, lmpromp_model, sample_prior_predictive
from lmpromp_ppl.models.collapsed import lmpromp_collapsed_model
from lmpromp_ppl.models.conditionals import data_statistics, woodbury_precision

HYPER = Hyperparameters(beta=4.0, lambda0=0.7, gamma=1.3, a0=2.5, b0=0.6, c0=1.7, d0=0.9, latent_dim=2,
                        learn_beta=True, beta_a0=3.0, beta_b0=0.5)


@pytest.fixture(scope="module")
def ragged():
    """L = 4 demonstrations of lengths 9, 6, 8, 7, D = 2, J = 3 (d = 6), one missing entry."""
    rng = np.random.default_rng(3)
    lengths = (9, 6, 8, 7)
    times = [np.sort(rng.uniform(0, 1, n)) for n in lengths]
    positions = [rng.normal(size=(n, 2)) for n in lengths]
    psi, y, mask = (np.array(a) for a in model_data(Demonstrations(times, positions), 3).dense())
    mask[1, 2] = 0.0
    y[1, 2] = np.nan
    return ModelData(jnp.asarray(psi), jnp.asarray(y), jnp.asarray(mask))


def _point(rng, L, d, V):
    return {"b": rng.normal(size=d), "M": rng.normal(size=(d, V)), "alpha": 1.7, "lam": rng.gamma(2.0, size=V),
            "beta": 3.1, "h": rng.normal(size=(L, V)), "w": rng.normal(size=(L, d))}


def _joint(data, point):
    return float(log_density(lmpromp_model, (data, HYPER), {}, {k: jnp.asarray(v) for k, v in point.items()})[0])


def _mvn(x, mean, chol_precision):
    """log N(x | mean, (L L^T)^-1), batched over leading dims."""
    z = jnp.einsum("...ji,...j->...i", chol_precision, jnp.asarray(x) - mean)  # L^T (x - mean)
    logdet = jnp.sum(jnp.log(jnp.diagonal(chol_precision, axis1=-2, axis2=-1)), axis=-1)
    return -0.5 * z.shape[-1] * np.log(2 * np.pi) + logdet - 0.5 * jnp.sum(z**2, axis=-1)


def _constant(values):
    values = np.asarray(values, dtype=float)
    assert np.ptp(values) < 1e-8 * max(1.0, np.max(np.abs(values))), values


def test_each_conditional_is_the_declared_joint_restricted_to_its_block(ragged):
    stats = data_statistics(ragged)
    L, d = np.shape(stats[1])
    V = HYPER.latent_dim
    rng = np.random.default_rng(0)
    base = _point(rng, L, d, V)
    gaps = {name: [] for name in ("b", "w", "h", "M", "lam", "alpha", "beta")}
    for _ in range(3):
        x = _point(rng, L, d, V)
        # b | M, alpha, beta, y with w and h integrated: the collapsed declaration
        p = {k: jnp.asarray(base[k]) for k in ("M", "alpha", "lam", "beta")}
        collapsed = float(log_density(lmpromp_collapsed_model, (ragged, HYPER), {"collapse_h": True},
                                      dict(p, b=jnp.asarray(x["b"])))[0])
        mean, chol = rf.conditional_b(stats, p["M"], p["alpha"], p["beta"], HYPER)
        gaps["b"].append(collapsed - float(_mvn(x["b"], mean, chol)))
        # w | b, M, alpha, beta, y with h integrated: N(w | b, C) times the likelihood
        point = dict(base, w=x["w"])
        cov = jnp.linalg.inv(woodbury_precision(jnp.asarray(base["alpha"]), jnp.asarray(base["M"]), HYPER.gamma))
        prior_h = dist.Normal(jnp.asarray(base["b"]) + jnp.asarray(base["h"]) @ jnp.asarray(base["M"]).T,
                              base["alpha"] ** -0.5).log_prob(x["w"]).sum()
        likelihood = _joint(ragged, point) - _joint(ragged, dict(point, w=base["w"])) - prior_h + dist.Normal(
            jnp.asarray(base["b"]) + jnp.asarray(base["h"]) @ jnp.asarray(base["M"]).T, base["alpha"] ** -0.5
        ).log_prob(base["w"]).sum()
        integrated = dist.MultivariateNormal(jnp.asarray(base["b"]), cov).log_prob(x["w"]).sum() + likelihood
        mean, chol = rf.conditional_locals(stats, jnp.asarray(base["b"]), jnp.asarray(base["M"]),
                                           jnp.asarray(base["alpha"]), jnp.asarray(base["beta"]), HYPER)
        gaps["w"].append(float(integrated) - float(jnp.sum(_mvn(jnp.asarray(x["w"]), mean, chol))))
        # the blocks drawn given w and h: the full declaration
        mean, chol = rf._conditional_h(jnp.asarray(base["w"]), jnp.asarray(base["b"]), jnp.asarray(base["M"]),
                                       jnp.asarray(base["alpha"]), HYPER.gamma)
        gaps["h"].append(_joint(ragged, dict(base, h=x["h"])) - float(jnp.sum(_mvn(jnp.asarray(x["h"]), mean, chol))))
        mean, chol = rf.conditional_M(*(jnp.asarray(base[k]) for k in ("w", "h", "b", "alpha", "lam")))
        gaps["M"].append(_joint(ragged, dict(base, M=x["M"])) - float(jnp.sum(_mvn(jnp.asarray(x["M"]), mean, chol))))
        shape, rate = rf.conditional_lam(jnp.asarray(base["M"]), HYPER)
        gaps["lam"].append(_joint(ragged, dict(base, lam=x["lam"]))
                           - float(jnp.sum(dist.Gamma(shape, rate).log_prob(jnp.asarray(x["lam"])))))
        value = rng.gamma(3.0)
        shape, rate = rf.conditional_alpha(*(jnp.asarray(base[k]) for k in ("w", "h", "b", "M")), HYPER)
        gaps["alpha"].append(_joint(ragged, dict(base, alpha=value)) - float(dist.Gamma(shape, rate).log_prob(value)))
        shape, rate = rf.conditional_beta(stats, jnp.asarray(base["w"]), HYPER)
        gaps["beta"].append(_joint(ragged, dict(base, beta=value)) - float(dist.Gamma(shape, rate).log_prob(value)))
    for name, values in gaps.items():
        _constant(values)


def test_a_wrong_conditional_is_caught(ragged):
    """The check above can fail: a Gamma shape off by one half changes the gap with the value."""
    stats = data_statistics(ragged)
    L, d = np.shape(stats[1])
    base = _point(np.random.default_rng(1), L, d, HYPER.latent_dim)
    shape, rate = rf.conditional_alpha(*(jnp.asarray(base[k]) for k in ("w", "h", "b", "M")), HYPER)
    gaps = [_joint(ragged, dict(base, alpha=v)) - float(dist.Gamma(shape + 0.5, rate).log_prob(v)) for v in (0.5, 2.0)]
    assert abs(gaps[0] - gaps[1]) > 0.1


@pytest.mark.parametrize("path", ["general", "eigenbasis"])
def test_sweeps_leave_the_posterior_invariant(path):
    """Geweke: (theta, y) from the joint, sweeps from theta; theta after is again a prior draw.
    Both paths: the per-demonstration statistics, and the shared design's eigenbasis."""
    from lmpromp_ppl.basis import design_matrix
    from lmpromp_ppl.data.core import SharedDesign, shared_design

    hyper = SIMULATION.replace(latent_dim=2)
    R, L, J, T, sweeps = 400, 6, 4, 12, 3
    psi = np.asarray(design_matrix(np.linspace(0.0, 1.0, T), 1, J))
    empty = ModelData(jnp.asarray(np.broadcast_to(psi, (L,) + psi.shape)), jnp.zeros((L, T)), jnp.ones((L, T)))
    prior = sample_prior_predictive("lmpromp", jax.random.key(0), empty, hyper, R)
    U = jnp.eye(J)
    if path == "general":
        stats = jax.vmap(lambda y: tuple(data_statistics(empty._replace(y=y))))(prior["y"])
    else:
        design = shared_design(empty)
        U = design.rotation
        stats = jax.vmap(lambda y: SharedDesign(design.rotation, design.eig, y @ (psi @ U), jnp.sum(y**2, axis=1),
                                                design.count))(prior["y"])

    def chain(key, theta, stats_one):
        def body(t, k):
            return rf.sweep(k, t, stats_one, hyper), None

        theta = dict(theta, b=theta["b"] @ U, M=U.T @ theta["M"])
        out = jax.lax.scan(body, theta, jax.random.split(key, sweeps))[0]
        return dict(out, b=out["b"] @ U.T, M=U @ out["M"])

    theta = {k: prior[k] for k in ("b", "M", "alpha", "lam")}
    after = jax.jit(jax.vmap(chain))(jax.random.split(jax.random.key(1), R), theta, stats)
    moved = np.mean(np.abs(np.asarray(after["alpha"]) - np.asarray(theta["alpha"])) > 1e-6)
    assert moved > 0.9  # the sweeps do move the draws
    checks = {
        "log alpha": (np.log(np.asarray(after["alpha"])), special.digamma(hyper.a0) - np.log(hyper.b0)),
        "log lam": (np.log(np.asarray(after["lam"][:, 0])), special.digamma(hyper.c0) - np.log(hyper.d0)),
        "b_0": (np.asarray(after["b"][:, 0]), 0.0),
        "M^2": (np.asarray(after["M"][:, 0, 0]) ** 2, hyper.d0 / (hyper.c0 - 1.0)),
    }
    for name, (values, expected) in checks.items():
        se = np.std(values, ddof=1) / np.sqrt(R)
        assert abs(np.mean(values) - expected) < 4 * se, (name, np.mean(values), expected, se)


def test_refresh_shapes_locals_and_bad_input(ragged):
    stats = data_statistics(ragged)
    L, d = np.shape(stats[1])
    V, n = HYPER.latent_dim, 5
    rng = np.random.default_rng(2)
    draws = {"b": rng.normal(size=(n, d)), "M": rng.normal(size=(n, d, V)), "alpha": rng.gamma(3.0, size=n),
             "lam": rng.gamma(3.0, size=(n, V)), "beta": rng.gamma(3.0, size=n)}
    out = rf.refresh(jax.random.key(0), draws, ragged, HYPER, 2)
    assert {k: v.shape for k, v in out.items()} == {
        "b": (n, d), "M": (n, d, V), "alpha": (n,), "lam": (n, V), "beta": (n,), "w": (n, L, d), "h": (n, L, V)}
    assert all(np.all(np.isfinite(np.asarray(v))) for v in out.values())
    assert not np.allclose(out["alpha"], draws["alpha"])
    kept = rf.refresh(jax.random.key(0), draws, ragged, HYPER, 0)  # no sweep: the globals stay, the locals are drawn
    for k in draws:
        np.testing.assert_array_equal(np.asarray(kept[k]), draws[k])
    again = rf.refresh(jax.random.key(0), draws, ragged, HYPER, 2)
    np.testing.assert_array_equal(np.asarray(out["b"]), np.asarray(again["b"]))
    with pytest.raises(LmprompError, match="sweeps"):
        rf.refresh(jax.random.key(0), draws, ragged, HYPER, -1)
    with pytest.raises(LmprompError, match="missing \\['beta'\\]"):
        rf.refresh(jax.random.key(0), {k: v for k, v in draws.items() if k != "beta"}, ragged, HYPER, 1)
    with pytest.raises(LmprompError, match="single-type"):
        rf.refresh(jax.random.key(0), draws, ragged, HYPER.replace(num_components=2), 1)


def test_shared_design_path_equals_the_general_path():
    """Demonstrations on one design: the eigenbasis conditionals (diagonal plus rank V) rotated back equal
    the per-demonstration ones, a learned beta's rate too, and refresh takes that path."""
    from lmpromp_ppl.basis import design_matrix
    from lmpromp_ppl.data.core import shared_design

    rng = np.random.default_rng(4)
    L, T, J, V = 5, 15, 3, 2
    psi = np.asarray(design_matrix(np.linspace(0.0, 1.0, T), 2, J))
    data = ModelData(jnp.asarray(np.broadcast_to(psi, (L,) + psi.shape)), jnp.asarray(rng.normal(size=(L, 2 * T))),
                     jnp.ones((L, 2 * T)))
    stats = data_statistics(data)
    design = shared_design(data)
    U = np.asarray(design.rotation)
    d = psi.shape[1]
    M, b = jnp.asarray(rng.normal(size=(d, V))), jnp.asarray(rng.normal(size=d))
    alpha, beta = jnp.asarray(2.3), jnp.asarray(5.0)
    cond = rf.rotated_conditionals(design, U.T @ M, alpha, beta, HYPER)

    def covariance(scale, factor):
        return U @ (np.diag(np.asarray(scale) ** 2) + np.asarray(factor) @ np.asarray(factor).T) @ U.T

    general_b, general_chol_b = rf.conditional_b(stats, M, alpha, beta, HYPER)
    general_w, general_chol_w = rf.conditional_locals(stats, b, M, alpha, beta, HYPER)
    np.testing.assert_allclose(U @ cond.mean_b, general_b, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(covariance(cond.scale_b, cond.factor_b),
                               np.linalg.inv(general_chol_b @ general_chol_b.T), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(cond.weights_mean(U.T @ b) @ U.T, general_w, rtol=1e-9, atol=1e-12)
    for i in range(L):
        np.testing.assert_allclose(covariance(cond.scale_w, cond.factor_w),
                                   np.linalg.inv(general_chol_w[i] @ general_chol_w[i].T), rtol=1e-9, atol=1e-12)
    w = jnp.asarray(rng.normal(size=(L, d)))
    np.testing.assert_allclose(rf.conditional_beta(design, w @ U, HYPER), rf.conditional_beta(stats, w, HYPER),
                               rtol=1e-10)
    draws = {"b": rng.normal(size=(2, d)), "M": rng.normal(size=(2, d, V)), "alpha": np.ones(2),
             "lam": np.ones((2, V)), "beta": np.ones(2)}
    hyper = HYPER.replace(learn_beta=True)
    key = jax.random.key(5)
    out = rf.refresh(key, draws, data, hyper, 1)
    theta = {k: jnp.asarray(v[0]) for k, v in draws.items()}
    theta = dict(theta, b=theta["b"] @ U, M=U.T @ theta["M"])
    k_sweeps = jax.random.split(jax.random.split(key, 2)[0])[0]  # the first draw's sweep keys (refresh's layout)
    k_one = jax.random.split(k_sweeps, 1)[0]
    expected = rf.sweep(k_one, theta, design, hyper)
    np.testing.assert_allclose(np.asarray(out["b"][0]), U @ np.asarray(expected["b"]), rtol=1e-10)

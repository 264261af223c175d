"""Approximation-quality metrics, alignment and relabelling on draws with known answers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import norm, ortho_group

from lmpromp_ppl.diagnostics.alignment import (
    Reference,
    align_draws,
    build_reference,
    component_permutations,
    procrustes_reference,
    procrustes_rotations,
    relabel_components,
    relabel_reference,
)
from lmpromp_ppl.diagnostics.metrics import (
    compare_marginals,
    reference_marginals,
    joint_divergences,
    khat_verdict,
    pareto_khat,
    reference_reliability,
    summarise_comparison,
    wasserstein_marginals,
)
from lmpromp_ppl.quantities import active_projector, gram_eigenvalues, sorted_lam

NUM = 20_000
# (reference mean, reference sd, q mean, q sd): identical, shifted, shrunk, inflated, other scale
CASES = np.array(
    [
        [0.0, 1.0, 0.0, 1.0],
        [0.0, 1.0, 0.5, 1.0],
        [0.0, 1.0, 0.0, 0.5],
        [0.0, 1.0, 0.0, 2.0],
        [1.0, 3.0, 2.5, 1.5],
    ]
)


@pytest.fixture(scope="module")
def gaussian_draws():
    rng = np.random.default_rng(0)
    p = CASES[:, 0] + CASES[:, 1] * rng.standard_normal((NUM, len(CASES)))
    q = CASES[:, 2] + CASES[:, 3] * rng.standard_normal((NUM, len(CASES)))
    return q, p


def _w1_to_normal(sample: np.ndarray, mean: float, sd: float) -> float:
    """W1 between an empirical distribution and N(mean, sd^2): the integral of |F_n - F|."""
    grid = np.linspace(mean - 12 * sd, mean + 12 * sd, 400_001)
    ecdf = np.searchsorted(np.sort(sample), grid, side="right") / sample.size
    return float(np.trapezoid(np.abs(ecdf - norm.cdf(grid, mean, sd)), grid))


def _w1_normals(m1, s1, m2, s2) -> float:
    """Exact W1 between two normals: E|mu + (s2 - s1) Z| (quantile coupling), a folded-normal mean."""
    mu, sig = m2 - m1, abs(s2 - s1)
    if sig == 0:
        return abs(mu)
    return sig * np.sqrt(2 / np.pi) * np.exp(-(mu**2) / (2 * sig**2)) + mu * (1 - 2 * norm.cdf(-mu / sig))


def test_smd_and_sd_ratio_match_analytic_values(gaussian_draws):
    q, p = gaussian_draws
    comp = compare_marginals(q, p)
    m_p, s_p, m_q, s_q = CASES.T
    smd_true = (m_q - m_p) / s_p
    ratio_true = s_q / s_p
    # standard errors of the estimators (delta method, independent samples)
    se_smd = np.sqrt(s_q**2 / NUM + s_p**2 / NUM) / s_p + np.abs(smd_true) / np.sqrt(2 * NUM)
    se_ratio = ratio_true * np.sqrt(1 / (2 * NUM) + 1 / (2 * NUM))
    np.testing.assert_array_less(np.abs(comp.smd - smd_true), 4 * se_smd)
    np.testing.assert_array_less(np.abs(comp.sd_ratio - ratio_true), 4 * se_ratio)


def test_wasserstein_matches_analytic_value_within_empirical_error(gaussian_draws):
    """|W1(F_n, G_m) - W1(F, G)| <= W1(F_n, F) + W1(G_m, G) (triangle inequality), computed exactly."""
    q, p = gaussian_draws
    comp = compare_marginals(q, p)
    for e, (m_p, s_p, m_q, s_q) in enumerate(CASES):
        bound = (_w1_to_normal(p[:, e], m_p, s_p) + _w1_to_normal(q[:, e], m_q, s_q)) / s_p
        exact = _w1_normals(m_p, s_p, m_q, s_q) / s_p
        assert abs(comp.wasserstein[e] - exact) <= bound + 1e-6, (e, comp.wasserstein[e], exact, bound)


def test_vectorised_wasserstein_equals_scipy_per_marginal():
    from scipy.stats import wasserstein_distance

    rng = np.random.default_rng(3)
    q = rng.normal(size=(300, 4))
    p = rng.normal(0.3, 2.0, size=(800, 4))
    p[:10, 0] = q[:10, 0]  # shared values
    q[:, 3], p[:, 3] = np.round(q[:, 3]), np.round(p[:, 3])  # heavy ties
    expected = [wasserstein_distance(q[:, e], p[:, e]) for e in range(4)]
    np.testing.assert_allclose(wasserstein_marginals(q, p), expected, rtol=1e-12, atol=1e-14)
    assert wasserstein_marginals(q, q)[0] == 0.0


def test_coverage_of_central_interval(gaussian_draws):
    q, p = gaussian_draws
    comp = compare_marginals(q, p, prob=0.9)
    m_p, s_p, m_q, s_q = CASES.T
    z = norm.ppf(0.95)
    lo, hi = m_q - z * s_q, m_q + z * s_q
    true = norm.cdf(hi, m_p, s_p) - norm.cdf(lo, m_p, s_p)
    # binomial error of the fraction of p's draws plus the error of q's two estimated quantiles
    se = np.sqrt(true * (1 - true) / NUM + 2 * 0.05 * 0.95 / NUM)
    np.testing.assert_array_less(np.abs(comp.coverage - true), 4 * se)
    assert abs(comp.coverage[0] - 0.9) < 4 * se[0]



def test_shared_reference_marginals_change_nothing(gaussian_draws):
    """Comparing with precomputed reference marginals (sorted once for every engine) gives what the
    direct formulas give: counts of p inside q's interval, and the sd-scaled differences."""
    q, p = gaussian_draws
    q = np.round(q, 1)  # ties between q's quantiles and p's draws
    p = np.round(p, 1)
    shared = compare_marginals(q, p, reference=reference_marginals(p))
    alone = compare_marginals(q, p)
    for a, b in zip(shared, alone):
        np.testing.assert_array_equal(a, b)
    lower, upper = np.quantile(q, [0.05, 0.95], axis=0)
    np.testing.assert_array_equal(shared.coverage, np.mean((p >= lower) & (p <= upper), axis=0))
    np.testing.assert_allclose(shared.smd, (q.mean(0) - p.mean(0)) / p.std(0, ddof=1), rtol=1e-12)
    with pytest.raises(ValueError, match="reference marginals"):
        compare_marginals(q, p, reference=reference_marginals(p[:100]))


def test_summary_keys_and_no_nan():
    rng = np.random.default_rng(1)
    p = rng.standard_normal((500, 3))
    p[:, 2] = 1.0  # constant element: no reference scale
    q = rng.standard_normal((400, 3))
    comp = compare_marginals(q, p)
    assert np.isnan(comp.smd[2]) and np.isnan(comp.sd_ratio[2])
    summary = summarise_comparison(comp)
    assert set(summary) == {"smd_max_abs", "sd_ratio_median", "wasserstein_max", "coverage90"}
    assert all(v is not None and np.isfinite(v) for v in summary.values())
    with pytest.raises(ValueError, match="NaN"):
        compare_marginals(np.full((10, 3), np.nan), p)
    with pytest.raises(ValueError, match="same elements"):
        compare_marginals(q[:, :2], p)


def test_joint_divergences_separate_identical_from_shifted():
    rng = np.random.default_rng(2)
    p = {"a": rng.standard_normal((800, 3))}
    same = {"a": rng.standard_normal((800, 3))}
    shifted = {"a": rng.standard_normal((800, 3)) + 1.0}
    d_same = joint_divergences(same, p, num_samples=400)
    d_shift = joint_divergences(shifted, p, num_samples=400)
    # the assignment solution equals arviz-stats' linear program on a small case
    import arviz_stats
    import xarray as xr

    def tree(z):
        return xr.DataTree.from_dict({"posterior": xr.Dataset({"a": (("chain", "draw", "e"), z[None])})})

    small_q, small_p = shifted["a"][:60], p["a"][:60]
    ours = joint_divergences({"a": small_q}, {"a": small_p}, num_samples=60)["wasserstein_joint"]
    mean, sd = small_p.mean(0), small_p.std(0, ddof=1)
    theirs = arviz_stats.wasserstein(tree((small_q - mean) / sd), tree((small_p - mean) / sd), num_samples=60,
                                     round_to="none")
    assert ours == pytest.approx(float(theirs), rel=1e-9)
    assert set(d_same) == {"wasserstein_joint", "kl_p_q"}
    # a shift of one sd in each of 3 dims moves the joint distance by sqrt(3)
    assert d_shift["wasserstein_joint"] > d_same["wasserstein_joint"] + 1.0
    assert d_shift["kl_p_q"] > d_same["kl_p_q"] + 0.5


def _log_ratio(sd_q: float, dim: int, num: int, seed: int) -> np.ndarray:
    """log p - log q for draws from q = N(0, sd_q^2 I), p = N(0, I) (unnormalised p)."""
    x = sd_q * np.random.default_rng(seed).standard_normal((num, dim))
    log_p = -0.5 * np.sum(x**2, axis=1)
    log_q = norm.logpdf(x, 0.0, sd_q).sum(axis=1)
    return log_p - log_q


def test_khat_separates_good_from_too_narrow_proposal():
    """For q = N(0, s^2) and p = N(0, 1) the ratio tail has k = 1 - s^2 when s < 1 and is bounded when s >= 1."""
    k_wide, _ = pareto_khat(_log_ratio(1.2, 3, 4000, 0))
    k_close, _ = pareto_khat(_log_ratio(0.95, 3, 4000, 1))
    k_narrow, _ = pareto_khat(_log_ratio(0.3, 3, 4000, 2))  # true k = 0.91
    assert k_wide < 0.5 and k_close < 0.5
    assert k_narrow > 0.7
    assert khat_verdict(k_wide) == "good" and khat_verdict(k_narrow) == "unreliable"


def test_khat_of_exact_proposal_is_none_with_note():
    khat, note = pareto_khat(np.full(1000, -3.2))
    assert khat is None and "constant" in note
    khat, note = pareto_khat(np.r_[np.full(999, 0.0), np.nan])
    assert khat is None and "NaN" in note


def test_reference_reliability_flags_disagreeing_chains():
    rng = np.random.default_rng(3)
    good = {"x": rng.standard_normal((2, 1000, 2))}
    rel = reference_reliability(good, divergences=0)
    assert rel["rhat_max"] < 1.01 and rel["ess_bulk_min"] > 400 and rel["problems"] == []
    bad = {"x": rng.standard_normal((2, 1000, 2)) + np.array([0.0, 2.0])[:, None, None]}
    rel = reference_reliability(bad, divergences=3)
    assert rel["rhat_max"] > 1.5
    assert any("R-hat" in p for p in rel["problems"]) and any("divergent" in p for p in rel["problems"])


# ------------------------------------------------------------------ alignment
def test_procrustes_rotations_equal_scipy_on_noisy_draws():
    """The batched SVD gives scipy's orthogonal Procrustes solution draw by draw (not only exact rotations)."""
    from scipy.linalg import orthogonal_procrustes

    rng = np.random.default_rng(11)
    ref = rng.standard_normal((8, 3))
    M = ref @ ortho_group.rvs(3, size=6, random_state=12) + 0.3 * rng.standard_normal((6, 8, 3))
    R = procrustes_rotations(M.reshape(2, 3, 8, 3), ref)
    assert R.shape == (2, 3, 3, 3)
    expected = np.stack([orthogonal_procrustes(m, ref)[0] for m in M]).reshape(2, 3, 3, 3)
    np.testing.assert_allclose(R, expected, atol=1e-12)


def test_procrustes_recovers_rotated_and_sign_flipped_M():
    rng = np.random.default_rng(4)
    M = rng.standard_normal((6, 3))
    h = rng.standard_normal((5, 3))
    rots = ortho_group.rvs(3, size=4, random_state=5)
    rots[1] = np.diag([1.0, -1.0, 1.0])  # a pure sign flip
    rots[2][:, 0] *= -1  # a reflection (det = -1)
    M_rot = M @ rots  # (4, 6, 3): M R
    h_rot = h @ rots  # the same latent rotation of the control variables
    R = procrustes_rotations(M_rot, M)
    np.testing.assert_allclose(M_rot @ R, np.broadcast_to(M, M_rot.shape), atol=1e-10)
    np.testing.assert_allclose(h_rot @ R, np.broadcast_to(h, h_rot.shape), atol=1e-10)
    # the reference of rotated copies is one of them up to rotation; every copy aligns onto it exactly
    ref = procrustes_reference(M_rot)
    np.testing.assert_allclose(M_rot @ procrustes_rotations(M_rot, ref), np.broadcast_to(ref, M_rot.shape), atol=1e-10)
    np.testing.assert_allclose(gram_eigenvalues(ref), gram_eigenvalues(M), rtol=1e-10)
    # align_draws with (chain, draw) sample dims rotates M and h consistently
    draws = {"M": M_rot.reshape(2, 2, 6, 3), "h": h_rot.reshape(2, 2, 5, 3)}
    out = align_draws("lmpromp", draws, Reference(None, M))
    np.testing.assert_allclose(out["M"], np.broadcast_to(M, (2, 2, 6, 3)), atol=1e-10)
    np.testing.assert_allclose(out["h"], np.broadcast_to(h, (2, 2, 5, 3)), atol=1e-10)


def test_projector_and_gram_eig_are_rotation_invariant():
    rng = np.random.default_rng(6)
    M = rng.standard_normal((6, 2))
    R = ortho_group.rvs(2, random_state=7)
    np.testing.assert_allclose(active_projector(M @ R, 2), active_projector(M, 2), atol=1e-12)
    P = active_projector(M, 2)
    np.testing.assert_allclose(P @ P, P, atol=1e-12)
    np.testing.assert_allclose(P @ M, M, atol=1e-12)
    np.testing.assert_allclose(gram_eigenvalues(M @ R), gram_eigenvalues(M), rtol=1e-12)
    np.testing.assert_array_equal(sorted_lam(np.array([3.0, 1.0, 2.0])), [1.0, 2.0, 3.0])


def test_relabelling_undoes_permutations_of_components():
    rng = np.random.default_rng(8)
    K, d, V, L, n = 3, 4, 2, 5, 12
    b = 5.0 * rng.standard_normal((K, d))
    M = rng.standard_normal((K, d, V))
    alpha = np.array([1.0, 2.0, 3.0])
    h = rng.standard_normal((L, K, V))
    z = rng.integers(0, K, L)
    perms = np.stack([rng.permutation(K) for _ in range(n)])  # draw s holds true component k at slot inv
    draws = {
        "b": b[perms] + 0.01 * rng.standard_normal((n, K, d)),
        "M": M[perms],
        "alpha": alpha[perms],
        "h": h[:, perms].transpose(1, 0, 2, 3),
        "z": np.argsort(perms, axis=1)[:, z],  # true label z sits at slot argsort(perm)[z]
        "w": rng.standard_normal((n, L, d)),
    }
    found = component_permutations(draws["b"], b)
    np.testing.assert_array_equal(found, np.argsort(perms, axis=1))
    out = relabel_components(draws, found, sample_ndim=1)
    np.testing.assert_allclose(out["b"], np.broadcast_to(b, (n, K, d)), atol=0.1)
    np.testing.assert_array_equal(out["M"], np.broadcast_to(M, (n, K, d, V)))
    np.testing.assert_array_equal(out["alpha"], np.broadcast_to(alpha, (n, K)))
    np.testing.assert_array_equal(out["h"], np.broadcast_to(h, (n, L, K, V)))
    np.testing.assert_array_equal(out["z"], np.broadcast_to(z, (n, L)))
    np.testing.assert_array_equal(out["w"], draws["w"])
    # a reference built from the draws alone recovers b up to one global relabelling
    ref = relabel_reference(draws["b"])
    global_perm = component_permutations(ref[None], b)[0]
    np.testing.assert_allclose(ref[global_perm], b, atol=0.05)
    # build_reference + align_draws with (chain, draw) dims give every draw the reference's labels
    chain_draws = {k: v.reshape((2, n // 2) + v.shape[1:]) for k, v in draws.items()}
    reference = build_reference("mixture", chain_draws)
    aligned = align_draws("mixture", chain_draws, reference)
    first = aligned["alpha"].reshape(n, K)
    np.testing.assert_array_equal(first, np.broadcast_to(first[0], (n, K)))
    eig = gram_eigenvalues(aligned["M"]).reshape(n, K, V)
    np.testing.assert_allclose(eig, np.broadcast_to(eig[0], eig.shape), rtol=1e-10)


def test_cavi_log_density_and_model_log_joint_reproduce_the_elbo():
    """E_q[log p(theta, y) - log q(theta)] is the ELBO: the Monte Carlo mean matches CAVI's closed form."""
    import jax

    import lmpromp_ppl as lp
    from lmpromp_ppl.data import prepare_dataset
    from lmpromp_ppl.diagnostics.metrics import model_log_joint
    from lmpromp_ppl.models.lmpromp import lmpromp_model

    dataset = "synthetic:latent?L=6&D=2&J=3&V=2&T=15&seed=0"
    hyper = lp.preset("proper", latent_dim=2)
    result = lp.fit(dataset, model="lmpromp", engine="cavi", hyper=hyper, num_basis=3)
    data = prepare_dataset(dataset, 3).model_data
    draws = {k: np.asarray(v) for k, v in result.sampler(jax.random.key(0), 4000).items()}
    log_ratio = model_log_joint(lmpromp_model, (data, hyper), draws) - np.asarray(result.log_density(draws))
    se = log_ratio.std(ddof=1) / np.sqrt(log_ratio.size)
    assert abs(log_ratio.mean() - result.summary["elbo"]) < 4 * se

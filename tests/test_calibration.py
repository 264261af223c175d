"""SBC and VSBC statistics, batched CAVI, SBC tasks and the sweep's held-out score.

Monte Carlo tolerances: coverage is a mean of R Bernoulli(0.9) indicators, so it
is checked within 4 standard errors sqrt(0.09 / R); a uniformity p-value of an
exact engine is itself uniform, so ``p > 0.001`` fails with probability 0.001.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from lmpromp_ppl.calibration.sbc import (
    SbcProblem,
    design,
    collect,
    pit_values,
    rank_statistics,
    sbc_task,
    simulate_replicate,
    summarize,
    uniformity_pvalues,
)
from lmpromp_ppl.calibration.sweep import heldout_scores, parse_grid, split_demos
from lmpromp_ppl.calibration.vsbc import numpyro_vsbc, vsbc_probabilities, vsbc_test
from lmpromp_ppl.errors import DataError, LmprompError
from lmpromp_ppl.inference.cavi import fit, fit_cavi_batched, replicate_state
from lmpromp_ppl.models.hyper import preset

R, N, NOBS = 300, 99, 5


def _gaussian_toy(shrink: float, bias: float, seed: int = 0):
    """theta ~ N(0, 1), y_j ~ N(theta, 1), j = 1..NOBS; exact posterior N(sum y / (n+1), 1/(n+1)).

    ``shrink`` multiplies the posterior s.d. and ``bias`` shifts its mean
    (in posterior s.d.): (1, 0) is the exact posterior.  Returns task-like results for :func:`collect`.
    """
    rng = np.random.default_rng(seed)
    records = []
    for i in range(R):
        theta = rng.normal()
        y = theta + rng.normal(size=NOBS)
        sd = 1.0 / np.sqrt(NOBS + 1)
        draws = y.sum() / (NOBS + 1) + bias * sd + shrink * sd * rng.normal(size=(N, 1))
        truth = np.array([theta])
        records.append({"index": i, "ranks": {"theta": rank_statistics(truth, draws, rng).tolist()},
                        "vsbc": {"theta": vsbc_probabilities(truth, draws).tolist()},
                        "truth": {"theta": truth.tolist()}, "post_mean": {"theta": draws.mean(0).tolist()},
                        "post_sd": {"theta": draws.std(0, ddof=1).tolist()}, "seconds": 0.0})
    return [{"model": "toy", "engine": f"shrink{shrink}-bias{bias}", "replicates": records}]


def test_sbc_passes_exact_and_flags_shrunk_posterior():
    results = _gaussian_toy(1.0, 0.0) + _gaussian_toy(0.5, 0.0, seed=1) + _gaussian_toy(1.0, 1.5, seed=2)
    rows = {r["engine"]: r for r in summarize(collect(results), N)}
    se = np.sqrt(0.09 / R)
    exact, shrunk, biased = rows["shrink1.0-bias0.0"], rows["shrink0.5-bias0.0"], rows["shrink1.0-bias1.5"]
    assert exact["pvalue_min"] > 1e-3
    assert abs(exact["coverage90"] - 0.9) < 4 * se
    assert exact["vsbc_pvalue_min"] > 1e-3
    # a posterior half as wide as the exact one: ranks pile up at 0 and N
    assert shrunk["pvalue_min"] < 1e-6
    assert shrunk["coverage90"] < 0.9 - 4 * se
    assert shrunk["sd_ratio"] < 0.75
    # symmetric about the truth: VSBC (point estimates only) does not flag the shrunk posterior,
    # but does flag a biased one
    assert shrunk["vsbc_pvalue_min"] > 1e-3
    assert biased["vsbc_pvalue_min"] < 1e-6
    assert biased["pvalue_min"] < 1e-6


def test_rank_and_pit_properties():
    rng = np.random.default_rng(0)
    draws = np.array([[0.0, 1.0], [1.0, 1.0], [2.0, 1.0]])
    ranks = rank_statistics(np.array([1.5, 1.0]), draws, rng)
    assert ranks[0] == 2 and 0 <= ranks[1] <= 3
    pit = pit_values(np.array([[0], [3]]), 3, rng)
    assert np.all((pit[0] >= 0) & (pit[0] <= 0.25)) and np.all((pit[1] >= 0.75) & (pit[1] <= 1))
    with pytest.raises(LmprompError):
        pit_values(np.array([[4]]), 3, rng)
    with pytest.raises(LmprompError):
        rank_statistics(np.zeros(3), draws, rng)
    with pytest.raises(LmprompError):
        uniformity_pvalues(np.zeros((1, 2)))


@pytest.mark.slow
def test_vsbc_statistic_is_numpyros():
    """numpyro's vsbc_diagnostic on the collapsed LMProMP: our statistic on its probabilities gives its KS values."""
    problem = SbcProblem(num_demos=4, num_basis=3, num_steps=8, latent_dim=1, num_draws=49)
    out = numpyro_vsbc(problem.model, design(problem), problem.hyper(), jax.random.key(0), num_simulations=8,
                       num_svi_steps=100, num_samples=50)
    assert set(out["probabilities"]) >= {"b", "M", "alpha", "lam"}
    for site, probabilities in out["probabilities"].items():
        p = np.asarray(probabilities).reshape(8, -1)
        assert np.all((p >= 0) & (p <= 1))
        ks, pvalues = vsbc_test(p)
        np.testing.assert_allclose(ks, np.ravel(out["ks_stats"][site]), rtol=1e-12)
        np.testing.assert_allclose(pvalues, np.ravel(out["ks_pvalues"][site]), rtol=1e-12)


@pytest.fixture(scope="module")
def problem():
    return SbcProblem(num_demos=6, num_basis=4, num_steps=12, latent_dim=1, num_draws=29)


def test_batched_cavi_matches_one_at_a_time(problem):
    datasets = [simulate_replicate(problem, 3, i)[1] for i in range(3)]
    batched = fit_cavi_batched(datasets, problem.hyper())
    assert batched.converged.all()
    for r, data in enumerate(datasets):
        single = fit(data, problem.hyper(), jax.random.key(0))
        assert single.iterations == batched.iterations[r]
        np.testing.assert_allclose(single.elbo, batched.elbo[r], rtol=1e-10)
        state = replicate_state(batched, r)
        for name in ("b_mean", "M_mean", "alpha_rate", "lam_rate", "h_mean"):
            np.testing.assert_allclose(getattr(state, name), getattr(single.state, name), rtol=1e-8, atol=1e-10)
    short = datasets[0]._replace(y=datasets[0].y[:, :-1], psi=datasets[0].psi[:, :-1], mask=datasets[0].mask[:, :-1])
    with pytest.raises(DataError):
        fit_cavi_batched([datasets[0], short], problem.hyper())
    with pytest.raises(LmprompError):
        fit_cavi_batched(datasets, problem.hyper().replace(num_components=2))


def test_sbc_task_cavi_records(problem):
    result = sbc_task({"problem": problem.to_dict(), "engine": "cavi", "seed": 1, "indices": [0, 1, 2], "options": {}})
    d = problem.num_basis * problem.num_dofs
    sizes = {"alpha": 1, "b": d, "gram_eig": problem.latent_dim, "pred_mean": 3, "pred_sd": 3}
    for record, index in zip(result["replicates"], (0, 1, 2)):
        assert record["index"] == index and record["converged"]
        assert {k: len(v) for k, v in record["ranks"].items()} == sizes
        assert all(0 <= r <= problem.num_draws for v in record["ranks"].values() for r in v)
        truth, _ = simulate_replicate(problem, 1, index)
        np.testing.assert_allclose(record["truth"]["b"], truth["b"])
    with pytest.raises(LmprompError, match="not offered"):
        sbc_task({"problem": {**problem.to_dict(), "model": "promp"}, "engine": "cavi", "seed": 0, "indices": [0]})


def test_problem_validation():
    with pytest.raises(LmprompError):
        SbcProblem(model="mixture")
    with pytest.raises(LmprompError):
        SbcProblem(latent_dim=9, num_basis=2)
    with pytest.raises(LmprompError):
        SbcProblem(phases=(1.5,))
    assert SbcProblem.from_dict(SbcProblem().to_dict()) == SbcProblem()


def test_heldout_scores_predict_the_rest_from_the_first_third():
    """lpd and RMSE score one prediction: the rows after the first third given it, by the Schur complement of
    the rows' joint marginal (w and h integrated out), with the fit's beta when the point holds one."""
    hyper = preset("thesis", latent_dim=1)
    rng = np.random.default_rng(0)
    psi = rng.normal(size=(2, 6, 3))  # D = 2 DoFs, 3 time steps (the second demonstration 2)
    y = rng.normal(size=(2, 6))
    mask = np.ones((2, 6))
    mask[1, 4:] = 0.0
    point = {"b": rng.normal(size=3), "M": rng.normal(size=(3, 1)), "alpha": 2.0}
    from lmpromp_ppl.data.core import ModelData

    data = ModelData(jnp.asarray(psi), jnp.asarray(y), jnp.asarray(mask))

    def expected(beta):
        cov_w = np.eye(3) / 2.0 + point["M"] @ point["M"].T / hyper.gamma
        lpd, sq, n_rest = 0.0, 0.0, 0
        for i, n in ((0, 6), (1, 4)):
            p, yi = psi[i, :n], y[i, :n]
            mean, cov = p @ point["b"], np.eye(n) / beta + p @ cov_w @ p.T
            s, r = slice(0, 2), slice(2, n)  # one observed time step of 2 DoFs in both
            gain = cov[r, s] @ np.linalg.inv(cov[s, s])
            mu = mean[r] + gain @ (yi[s] - mean[s])
            lpd += stats.multivariate_normal(mu, cov[r, r] - gain @ cov[s, r]).logpdf(yi[r])
            sq += np.sum((yi[r] - mu) ** 2)
            n_rest += n - 2
        return lpd / n_rest, np.sqrt(sq / n_rest)

    scores = heldout_scores(point, data, hyper, num_dofs=2)
    lpd, rmse = expected(hyper.beta)
    np.testing.assert_allclose([scores["lpd"], scores["rmse"]], [lpd, rmse], rtol=1e-9)
    learned = heldout_scores({**point, "beta": 7.0}, data, hyper, num_dofs=2)
    np.testing.assert_allclose([learned["lpd"], learned["rmse"]], expected(7.0), rtol=1e-9)
    assert abs(learned["lpd"] - scores["lpd"]) > 1e-3


@pytest.mark.filterwarnings("ignore::lmpromp_ppl.errors.ConvergenceWarning")
def test_sweep_metrics_rank_a_beta_grid_alike():
    """The issue's example: on LASA GShape the two held-out metrics used to rank a beta grid in opposite orders."""
    from lmpromp_ppl.calibration.sweep import sweep_task

    scores = {}
    for beta in (1.0, 10.0, 100.0):
        spec = {"dataset": "lasa:GShape?every=20", "params": {"beta": beta, "latent_dim": 1}, "seed": 0,
                "test_fraction": 0.25, "options": {"num_restarts": 1}}
        scores[beta] = sweep_task(spec)["heldout"]
    by_lpd = sorted(scores, key=lambda b: -scores[b]["lpd"])
    by_rmse = sorted(scores, key=lambda b: scores[b]["rmse"])
    assert by_lpd == by_rmse


def test_grid_and_split_validation():
    assert parse_grid(["beta=50,100", "latent_dim=1,2"]) == {"beta": [50.0, 100.0], "latent_dim": [1, 2]}
    for bad in (["beta"], ["nope=1"], ["latent_dim=1.5"], ["beta=x"], ["beta=1", "beta=2"], []):
        with pytest.raises(LmprompError):
            parse_grid(bad)
    train, test = split_demos(8, 0.25, 0)
    assert len(test) == 2 and sorted(np.concatenate([train, test]).tolist()) == list(range(8))
    with pytest.raises(LmprompError):
        split_demos(2, 0.5, 0)

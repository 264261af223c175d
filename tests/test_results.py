"""The common result layout: DataTree groups, dims, save/load round trip."""

import json

import numpy as np
import pytest

from lmpromp_ppl.data.core import Scaling
from lmpromp_ppl.quantities import gram_eigenvalues, trajectory_moments
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.models.hyper import Hyperparameters
from lmpromp_ppl.results import FitResult, load


def _lmpromp_draws(rng, chains=2, draws=5, L=4, D=2, J=3, V=2, K=None):
    comp = () if K is None else (K,)
    d = D * J
    out = {
        "b": rng.normal(size=(chains, draws) + comp + (d,)),
        "M": rng.normal(size=(chains, draws) + comp + (d, V)),
        "h": rng.normal(size=(chains, draws, L) + comp + (V,)),
        "w": rng.normal(size=(chains, draws, L, d)),
        "alpha": rng.gamma(5.0, size=(chains, draws) + comp),
        "lam": rng.gamma(5.0, size=(chains, draws) + comp + (V,)),
    }
    if K is not None:
        out["pi"] = rng.dirichlet(np.ones(K), size=(chains, draws))
    return out


def _result(rng, **kw):
    K = kw.pop("K", None)
    draws = _lmpromp_draws(rng, K=K)
    return FitResult(
        model="lmpromp" if K is None else "mixture",
        engine="nuts",
        hyper=Hyperparameters(latent_dim=2, num_components=K or 1),
        num_basis=3,
        num_dofs=2,
        scaling=Scaling(np.array([1.0, -2.0]), np.array([2.0, 0.5])),
        dataset="synthetic:test",
        dof_names=("x", "y"),
        draws=draws,
        point={k: v.mean(axis=(0, 1)) for k, v in draws.items()},
        sample_stats={"diverging": np.zeros((2, 5), dtype=bool)},
        optimization={"elbo": np.linspace(-10, -1, 7)},
        summary={"seconds": 1.5, "compile_seconds": 0.5, "elbo": float("nan")},
        **kw,
    )


@pytest.mark.parametrize("K", [None, 3])
def test_datatree_groups_and_contract_dims(K):
    rng = np.random.default_rng(0)
    tree = _result(rng, K=K).to_datatree()
    assert {"posterior", "derived", "sample_stats", "optimization", "point_estimate"} <= set(tree.children)
    post = tree["posterior"]
    comp = ("component",) if K else ()
    assert post["b"].dims == ("chain", "draw") + comp + ("weight",)
    assert post["M"].dims == ("chain", "draw") + comp + ("weight", "latent")
    assert post["h"].dims == ("chain", "draw", "demo") + comp + ("latent",)
    assert post["w"].dims == ("chain", "draw", "demo", "weight")
    assert post["lam"].dims == ("chain", "draw") + comp + ("latent",)
    assert tree["derived"]["gram_eig"].dims == ("chain", "draw") + comp + ("latent",)
    assert tree["derived"]["pred_mean"].dims == ("chain", "draw", "phase", "dof")
    assert tree["optimization"]["elbo"].dims == ("iteration",)


def test_gram_eigenvalues_descending_and_equal_to_dense():
    rng = np.random.default_rng(1)
    M = rng.normal(size=(4, 6, 2))
    eig = gram_eigenvalues(M)
    dense = np.sort(np.linalg.eigvalsh(M @ np.swapaxes(M, -1, -2)), axis=-1)[..., ::-1][..., :2]
    np.testing.assert_allclose(eig, dense, rtol=1e-10, atol=1e-12)
    assert np.all(np.diff(eig, axis=-1) <= 0)


def test_trajectory_moments_match_dense_covariance():
    """pred_sd of the LMProMP equals sqrt(diag(Psi (alpha^-1 I + gamma^-1 M M^T) Psi^T))."""
    from lmpromp_ppl.basis import design_matrix

    rng = np.random.default_rng(2)
    D, J, V, gamma = 2, 4, 2, 3.0
    draws = {"b": rng.normal(size=(D * J,)), "M": rng.normal(size=(D * J, V)), "alpha": np.array(4.0)}
    phase = np.linspace(0, 1, 7)
    mean, sd = trajectory_moments("lmpromp", draws, num_dofs=D, num_basis=J, gamma=gamma, phase=phase)
    psi = np.asarray(design_matrix(phase, D, J))
    cov = np.eye(D * J) / 4.0 + draws["M"] @ draws["M"].T / gamma
    np.testing.assert_allclose(mean.reshape(-1), psi @ draws["b"], rtol=1e-12)
    np.testing.assert_allclose(sd.reshape(-1), np.sqrt(np.diag(psi @ cov @ psi.T)), rtol=1e-12)
    # The ProMP with the same covariance gives the same moments.
    m2, s2 = trajectory_moments("promp", {"mu_w": draws["b"], "Sigma_w": cov}, num_dofs=D, num_basis=J, gamma=gamma, phase=phase)
    np.testing.assert_allclose(m2, mean, rtol=1e-12)
    np.testing.assert_allclose(s2, sd, rtol=1e-12)


def test_mixture_moments_are_moment_matched():
    rng = np.random.default_rng(3)
    D, J, V, K = 1, 3, 1, 2
    draws = {"b": rng.normal(size=(K, J)), "M": rng.normal(size=(K, J, V)), "alpha": np.array([2.0, 5.0]), "pi": np.array([0.3, 0.7])}
    phase = np.linspace(0, 1, 5)
    mean, sd = trajectory_moments("mixture", draws, num_dofs=D, num_basis=J, gamma=1.0, phase=phase)
    parts = [trajectory_moments("lmpromp", {k: draws[k][c] for k in ("b", "M", "alpha")}, num_dofs=D, num_basis=J, gamma=1.0, phase=phase) for c in range(K)]
    m = 0.3 * parts[0][0] + 0.7 * parts[1][0]
    second = 0.3 * (parts[0][1] ** 2 + parts[0][0] ** 2) + 0.7 * (parts[1][1] ** 2 + parts[1][0] ** 2)
    np.testing.assert_allclose(mean, m, rtol=1e-12)
    np.testing.assert_allclose(sd, np.sqrt(second - m**2), rtol=1e-10)


def test_save_load_round_trip_and_refuses_overwrite(tmp_path):
    rng = np.random.default_rng(4)
    res = _result(rng)
    res.save(tmp_path / "fit")
    summary = json.loads((tmp_path / "fit" / "summary.json").read_text())
    assert summary["format_version"] == 1
    assert summary["elbo"] is None  # NaN is written as null
    for key in ("model", "engine", "hyperparameters", "elbo_trace", "iterations", "converged", "seconds", "compile_seconds", "active_latent_dims"):
        assert key in summary
    back = load(tmp_path / "fit")
    assert back.model == res.model and back.engine == res.engine and back.hyper == res.hyper
    for k, v in res.draws.items():
        np.testing.assert_array_equal(back.draws[k], v)
    for k, v in res.point.items():
        np.testing.assert_array_equal(back.point[k], v)
    np.testing.assert_array_equal(back.scaling.mean, res.scaling.mean)
    assert back.dof_names == ("x", "y")
    with pytest.raises(LmprompError, match="refusing to overwrite"):
        res.save(tmp_path / "fit")
    res.save(tmp_path / "fit", force=True)


def test_load_errors_name_the_problem(tmp_path):
    with pytest.raises(LmprompError, match="summary.json is missing|posterior.nc is missing"):
        load(tmp_path)
    (tmp_path / "posterior.nc").write_bytes(b"not netcdf")
    (tmp_path / "summary.json").write_text('{"format_version": 1}')
    with pytest.raises(LmprompError, match="cannot read"):
        load(tmp_path)

"""The engine ``cavi_lr`` in the framework: registry, API, result layout, CLI, prediction, compare, SBC."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

import lmpromp_ppl as lp
from lmpromp_ppl.calibration.sbc import SbcProblem, sbc_task, simulate_replicate
from lmpromp_ppl.cli import main
from lmpromp_ppl.diagnostics.metrics import engine_khat
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference import cavi
from lmpromp_ppl.inference.registry import ENGINES, check_fit, engines_for
from lmpromp_ppl.reports.compare import expand_engines

DATASET = "synthetic:latent?L=8&D=2&J=4&V=2&T=20&seed=3"


@pytest.fixture(scope="module")
def result():
    return lp.fit(DATASET, engine="cavi_lr", num_basis=4, hyper=lp.preset("default", latent_dim=2), seed=1)


def test_registry_offers_cavi_lr_for_the_single_type_only():
    assert "cavi_lr" in ENGINES and "cavi_lr" in engines_for("lmpromp")
    assert "cavi_lr" not in engines_for("mixture") and "cavi_lr" not in engines_for("promp")
    with pytest.raises(LmprompError, match="lmpromp model"):
        check_fit("mixture", "cavi_lr", {})
    with pytest.raises(LmprompError, match="does not take"):
        check_fit("lmpromp", "cavi_lr", {"search": "none"})
    with pytest.raises(LmprompError, match="unknown resample"):
        check_fit("lmpromp", "cavi_lr", {"resample": "always"})
    assert "cavi_lr" in expand_engines("auto", "lmpromp") and "cavi_lr" not in expand_engines("auto", "mixture")


def test_fit_reports_the_linear_response_and_its_importance_diagnostics(result):
    info = result.summary["linear_response"]
    assert info["cg_residual"] < 1e-8
    assert info["psis_khat"] is None or np.isfinite(info["psis_khat"])
    assert info["importance_resampled"] == (info["psis_khat"] is not None and info["psis_khat"] < 0.7)
    assert result.summary["converged"]
    draws = result.posterior_draws(200, jax.random.key(0))  # the sites and dims: tests/test_layout.py
    # the correction widens the offset's marginals relative to the factor q(b)
    q_sd = float(np.sqrt(result.state.state.b_var[0]))
    assert np.median(np.std(np.asarray(draws["b"])[0], axis=0)) > 1.2 * q_sd


def test_draws_end_with_the_exact_conditional_refresh(result, tmp_path):
    """By default every draw takes REFRESH_SWEEPS Gibbs sweeps (lmpromp_ppl.inference.refresh), said in the
    summary; they move alpha off the linear-response Gaussian; a loaded fit refreshes its new draws too."""
    from lmpromp_ppl.inference.refresh import REFRESH_SWEEPS

    assert result.state.refresh == REFRESH_SWEEPS > 0
    assert result.summary["linear_response"]["refresh_sweeps"] == REFRESH_SWEEPS
    key = jax.random.key(6)
    refreshed = result.state.sample(key, 100)
    plain = result.state._replace(refresh=0).sample(key, 100)
    assert not np.allclose(np.asarray(refreshed["alpha"]), np.asarray(plain["alpha"]))
    assert set(refreshed) == set(plain)
    result.save(tmp_path / "fit", key=jax.random.key(2))
    back = lp.load(tmp_path / "fit")
    again = back.sampler(key, 100)
    bare = cavi.sample_lr(jax.random.split(key)[0], back.state.lr, back.state.state, 100, True)
    assert not np.allclose(np.asarray(again["alpha"]), np.asarray(bare["alpha"]))
    with pytest.raises(LmprompError, match="non-negative integer"):
        check_fit("lmpromp", "cavi_lr", {"refresh": -1})


def test_engine_khat_uses_the_collapsed_global_ratios(result):
    model_data = lp.data.prepare_dataset(DATASET, 4).model_data
    out = engine_khat(result, model_data, jax.random.key(3), num_draws=500)
    assert out["psis_khat"] is not None and np.isfinite(out["psis_khat"]), out


def test_saved_fit_round_trips_the_family_and_the_linear_response(result, tmp_path):
    result.save(tmp_path / "fit", key=jax.random.key(2))
    back = lp.load(tmp_path / "fit")
    assert back.engine == "cavi_lr"
    assert back.state.state.wh_cov is not None
    np.testing.assert_array_equal(np.asarray(back.state.state.wh_cov), np.asarray(result.state.state.wh_cov))
    np.testing.assert_array_equal(np.asarray(back.state.lr.cov), np.asarray(result.state.lr.cov))
    draws = back.sampler(jax.random.key(4), 50)
    assert np.shape(draws["M"]) == (50,) + np.shape(result.state.state.M_mean[0])
    assert np.all(np.isfinite(np.asarray(back.log_density(draws))))


def test_cli_fits_and_predicts_with_cavi_lr(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["fit", DATASET, "--engine", "cavi_lr", "--latent-dim", "2", "--num-basis", "4",
                 "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["engine"] == "cavi_lr" and "linear_response" in summary
    assert main(["fit", DATASET, "--engine", "cavi_lr", "--latent-dim", "2", "--num-basis", "4", "--refresh", "0",
                 "--out", str(tmp_path / "bare"), "--quiet"]) == 0
    assert json.loads((tmp_path / "bare" / "summary.json").read_text())["linear_response"]["refresh_sweeps"] == 0
    assert main(["fit", DATASET, "--engine", "cavi_lr", "--refresh", "-1", "--out", str(tmp_path / "bad")]) == 2
    assert not (tmp_path / "bad").exists()
    capsys.readouterr()
    demos = lp.data.load_dataset(DATASET)
    t, y = demos.times[0], demos.positions[0]
    np.savez(tmp_path / "obs.npz", t=(t[:8] - t[0]) / (t[-1] - t[0]), y=y[:8])
    assert main(["predict", str(out), "--observe", str(tmp_path / "obs.npz"), "--out", str(tmp_path / "p"),
                 "--quiet"]) == 0
    assert (tmp_path / "p" / "prediction.npz").is_file()
    assert main(["fit", DATASET, "--engine", "cavi_lr", "--model", "mixture", "--out", str(tmp_path / "m")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("lmpromp: error:") and "\n" not in err.splitlines()[-1]


def test_sbc_replicates_are_vmapped_and_equal_the_single_fit():
    problem = SbcProblem()
    out = sbc_task({"problem": problem.to_dict(), "engine": "cavi_lr", "seed": 0, "indices": [0, 1, 2],
                    "options": {}})
    records = out["replicates"]
    assert len(records) == 3 and all("psis_khat" in r for r in records)
    assert all(r["ranks"]["alpha"][0] <= problem.num_draws for r in records)
    # the vmapped linear response of replicate 1 equals the single-replicate one
    _, data = simulate_replicate(problem, 0, 1)
    hyper = problem.hyper()
    fits = cavi.fit_cavi_batched([simulate_replicate(problem, 0, i)[1] for i in range(3)], hyper,
                                 local="joint", family="rowwise")
    batched, _, _ = cavi.linear_response_batched(fits, hyper)
    single = cavi.linear_response(cavi.replicate_state(fits, 1), cavi.sufficient_statistics(data),
                                  cavi.hyper_arrays(hyper, 0.0))
    np.testing.assert_allclose(np.asarray(batched.cov[1]), np.asarray(single.cov), rtol=1e-8,
                               atol=1e-12 * float(np.max(np.abs(single.cov))))


def test_importance_resampled_draws_follow_the_weights(result):
    """The resampling path: draws of every site, globals from the pool by the PSIS weights, locals exact."""
    forced = result.state._replace(resampled=True, refresh=0)
    draws = forced.sample(jax.random.key(5), 300)
    plain = result.state._replace(refresh=0).sample(jax.random.key(5), 300)
    assert set(draws) == set(plain)
    for name in draws:
        assert np.shape(draws[name]) == np.shape(plain[name]), name
        assert np.all(np.isfinite(np.asarray(draws[name]))), name
    # resampling repeats pool members: fewer distinct alpha values than draws when weights are uneven
    assert len(np.unique(np.asarray(draws["alpha"]))) < 300
    # the locals are drawn given each global draw: w_i sits near b + M h_i for its own draw
    resid = np.asarray(draws["w"]) - np.asarray(draws["b"])[:, None] - np.einsum(
        "ndv,niv->nid", np.asarray(draws["M"]), np.asarray(draws["h"]))
    alpha = np.asarray(draws["alpha"])
    assert abs(np.mean(resid**2 * alpha[:, None, None]) - 1.0) < 0.5

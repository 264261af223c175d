"""`lmpromp bench` at a tiny size: the pieces agree with the engines and the JSON has its layout.

No test asserts a time.
"""

import json
import sys

import jax
import numpy as np
import pytest

from lmpromp_ppl import bench
from lmpromp_ppl.cli import main
from lmpromp_ppl.data import Demonstrations, model_data
from lmpromp_ppl.errors import DataError
from lmpromp_ppl.inference import cavi
from lmpromp_ppl.inference.cavi import fit_cavi_batched

TINY = bench.RowSpec("default", L=6, D=1, J=6, V=2, T=20)
BASELINE = "lasa:GShape?every=50"


def _config(rows, **changes):
    settings = dict(
        rows=rows, max_iter=500, timing_sweeps=10, repeats=1,
        svi=bench.SviSettings(max_steps=200, check_every=100, mc_particles=50, budget_s=5.0),
        nuts=bench.NutsSettings(num_chains=2, num_warmup=50, num_samples=50),
        batch_size=3, batch_row=TINY, baseline_dataset=BASELINE, baseline_num_basis=5,
        matmul_size=100, progress=False,
    )
    settings.update(changes)
    return bench.BenchConfig(**settings)


@pytest.fixture(scope="module")
def result():
    return bench.run_benchmark(_config((TINY,)), gpu_note="not run in the tests")


def test_shared_cavi_data_equals_sufficient_statistics():
    demos = bench.row_demonstrations(bench.RowSpec("x", L=5, D=2, J=4, V=2, T=15, seed=3))
    fast = bench.shared_cavi_data(demos, 4)
    ref = cavi.sufficient_statistics(model_data(demos, 4))
    assert isinstance(ref.gram, cavi.SharedGram)
    for name in ("psi_t_y", "y_sq", "num_obs"):
        np.testing.assert_allclose(getattr(fast, name), getattr(ref, name), rtol=1e-12, atol=1e-12)
    gram = lambda g: np.asarray(g.basis * g.eigvals @ g.basis.T)  # noqa: E731
    np.testing.assert_allclose(gram(fast.gram), gram(ref.gram), atol=1e-10)


def test_shared_cavi_data_refuses_different_time_grids():
    demos = bench.row_demonstrations(bench.RowSpec("x", L=3, D=1, J=4, V=1, T=10))
    shorter = Demonstrations(
        times=(demos.times[0], demos.times[1][:-1]), positions=(demos.positions[0], demos.positions[1][:-1]),
    )
    with pytest.raises(DataError, match="time grid"):
        bench.shared_cavi_data(shorter, 4)


def test_batched_cavi_matches_single_fits():
    """vmap of (pure-JAX thesis initialisation + compiled loop) reaches each dataset's own CAVI optimum."""
    rows = [bench.RowSpec("x", L=6, D=1, J=6, V=2, T=20, seed=s) for s in range(3)]
    demos = [bench.row_demonstrations(r) for r in rows]
    singles = [bench.shared_cavi_data(d, 6) for d in demos]
    stacked = cavi.CaviData(
        np.stack([s.psi_t_y for s in singles]), np.stack([s.y_sq for s in singles]),
        np.stack([s.num_obs for s in singles]), singles[0].gram,
    )
    hyper = bench.row_hyper(rows[0])
    batch = fit_cavi_batched(stacked, hyper, tol=1e-10, max_iter=3000)
    assert batch.converged.all()
    for s, d in enumerate(demos):
        fit = cavi.fit(model_data(d, 6), hyper, jax.random.key(0), tol=1e-10, max_iter=3000)
        assert batch.elbo[s] == pytest.approx(fit.elbo, rel=1e-7)
        # the same optimum up to the sign of the latent directions: compare M M^T and b
        M = np.asarray(batch.state.M_mean[s, 0])
        np.testing.assert_allclose(M @ M.T, np.asarray(fit.state.M_mean[0] @ fit.state.M_mean[0].T), atol=1e-5)
        np.testing.assert_allclose(batch.state.b_mean[s], fit.state.b_mean, atol=1e-6)


def test_json_layout(result):
    text = json.dumps(result, allow_nan=False)  # missing values are null, never NaN
    assert json.loads(text)["format"] == "lmpromp-bench/1"
    for key in ("cpu", "cores", "versions", "matmul_flop_rate"):
        assert key in result["machine"], key
    (row,) = result["rows"]
    for key in ("name", "L", "D", "J", "V", "K"):
        assert key in row, key
    assert (row["name"], row["L"], row["D"], row["J"], row["V"], row["K"]) == ("default", 6, 1, 6, 2, 1)
    for key in ("compile_s", "fit_s", "iterations", "tol", "max_iter", "flops_per_iteration"):
        assert key in row["cavi"], key
    assert row["cavi"]["converged"] and 0 < row["cavi"]["iterations"] <= 500
    # CAVI only ascends from its initialisation
    assert row["cavi"]["elbo"] > row["cavi"]["elbo_init"]
    for engine in ("svi_meanfield", "svi_autonormal", "nuts"):
        assert row[engine] == {"run": False, "reason": row[engine]["reason"]}
    assert row["ratios"]["nuts_over_cavi"] is None and row["ratios"]["svi_over_cavi"] is None
    assert result["batch"]["datasets"] == 3 and result["batch"]["converged_fraction"] == 1.0
    assert result["gpu"] == {"run": False, "reason": "not run in the tests"}
    for goal in result["goals"].values():
        assert set(goal) >= {"target", "measured", "met"}
    assert result["goals"]["default_cavi_under_20ms"]["measured"] == row["cavi"]["fit_s"]
    assert result["goals"]["default_1000x_faster_than_nuts"]["met"] is None
    assert result["goals"]["batch_1000_under_60s"]["met"] is None  # fewer than 1000 datasets
    table = bench.format_table(result)
    assert "| default | 6 | 6 | 2 | 1 |" in table and "GPU: not run" in table


def test_promp_baseline_against_movement_primitives(result, monkeypatch):
    base = result["promp_baseline"]
    assert (base["num_demos"], base["num_steps"], base["num_dofs"], base["num_basis"]) == (7, 21, 2, 5)
    try:
        import movement_primitives  # noqa: F401
    except ImportError:
        assert base["movement_primitives"].startswith("skipped")
    else:
        # both estimate the same mean movement: a few per cent of the data range apart
        assert 0 < base["mean_rmse_over_range"] < 0.1
    monkeypatch.setitem(sys.modules, "movement_primitives.promp", None)  # as if not installed
    skipped = bench.bench_promp_baseline(BASELINE, 5)
    assert skipped["movement_primitives"].startswith("skipped") and skipped["mean_rmse_over_range"] is None


def test_cli_bench_errors(tmp_path, capsys):
    existing = tmp_path / "bench.json"
    existing.write_text("{}")
    assert main(["bench", "--out", str(existing), "--quiet"]) == 2
    assert "--force" in capsys.readouterr().err
    assert main(["bench", "--out", str(tmp_path / "new.json"), "--device", "tpu", "--quiet"]) == 2
    assert "--device" in capsys.readouterr().err
    assert not (tmp_path / "new.json").exists()


@pytest.mark.slow
def test_every_engine_at_a_tiny_size():
    """SVI (both guides), NUTS and the mixture row run end to end; their entries have the issue's fields."""
    tiny = bench.RowSpec("default", L=6, D=1, J=6, V=2, T=20, engines=("svi_meanfield", "svi_autonormal", "nuts"))
    mixture = bench.RowSpec("K3", L=9, D=1, J=6, V=2, K=3, T=20)
    out = bench.run_benchmark(_config((tiny, mixture), batch_size=0, baseline_dataset=""))
    row, mix = out["rows"]
    for engine in ("svi_meanfield", "svi_autonormal"):
        assert set(row[engine]) >= {"fit_s", "steps", "elbo_gap"}
        assert row[engine]["steps"] % 100 == 0 and row[engine]["steps"] <= 200
    assert "Monte Carlo" in row["svi_autonormal"]["elbo_kind"]
    assert set(row["nuts"]) >= {"fit_s", "ess_bulk_min", "s_per_ess"} and row["nuts"]["ess_bulk_min"] > 0
    assert row["ratios"]["nuts_over_cavi"] > 0
    assert mix["cavi"]["engine"] == "cavi_mixture" and mix["cavi"]["elbo"] > mix["cavi"]["elbo_init"]

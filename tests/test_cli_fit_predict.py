"""`lmpromp fit` and `lmpromp predict` end to end, and the fit API's errors."""

import json

import numpy as np
import pytest

import lmpromp_ppl as lp
from lmpromp_ppl.cli import main
from lmpromp_ppl.errors import LmprompError

DATASET = "synthetic:latent?L=8&D=2&J=4&V=2&T=20&seed=3"


@pytest.fixture(scope="module")
def fit_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("fit") / "run"
    code = main(["fit", DATASET, "--latent-dim", "2", "--num-basis", "4", "--out", str(out), "--quiet"])
    assert code == 0
    return out


def test_fit_writes_contract_files(fit_dir):
    summary = json.loads((fit_dir / "summary.json").read_text())
    for key in ("model", "engine", "hyperparameters", "elbo", "elbo_trace", "iterations", "converged",
                "seconds", "compile_seconds", "active_latent_dims"):
        assert key in summary, key
    assert summary["model"] == "lmpromp" and summary["engine"] == "cavi"
    assert summary["hyperparameters"]["latent_dim"] == 2
    assert len(summary["elbo_trace"]) == summary["iterations"]
    assert summary["elbo"] == pytest.approx(summary["elbo_trace"][-1])
    assert np.all(np.diff(summary["elbo_trace"]) >= -1e-8 * abs(summary["elbo"]))
    assert set(summary["active_latent_dims"]) <= {0, 1}


def test_fit_refuses_existing_output_without_force(fit_dir, capsys):
    code = main(["fit", DATASET, "--latent-dim", "2", "--num-basis", "4", "--out", str(fit_dir), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--force" in err


def test_loaded_fit_predicts_through_the_observations(fit_dir, tmp_path):
    fit = lp.load(fit_dir)
    demos = lp.data.load_dataset(DATASET)
    z, y = demos.phases()[0], demos.positions[0]
    head = z <= 0.5
    np.savez(tmp_path / "obs.npz", t=z[head], y=y[head])
    out = tmp_path / "pred"
    assert main(["predict", str(fit_dir), "--observe", str(tmp_path / "obs.npz"), "--out", str(out),
                 "--exact", "--quiet"]) == 0
    with np.load(out / "prediction.npz") as f:
        phase, mean, sd, samples, sd_obs = f["phase"], f["mean"], f["sd"], f["samples"], f["sd_obs"]
    assert mean.shape == sd.shape == sd_obs.shape == (phase.size, 2) and samples.shape[1:] == (phase.size, 2)
    assert np.all(sd_obs > sd)  # the band of a new observation adds the fitted noise
    assert (out / "prediction.png").stat().st_size > 0
    # The exact conditional follows the observed part better than the prior mean does, to
    # within the generator's observation noise (beta = 400: s.d. 0.05).
    fitted = np.stack([np.interp(z[head], phase, mean[:, k]) for k in range(2)], axis=1)
    prior_mean = fit.to_datatree(200)["derived"]["pred_mean"].mean(("chain", "draw")).values
    prior = np.stack([np.interp(z[head], np.linspace(0, 1, prior_mean.shape[0]), prior_mean[:, k]) for k in range(2)], axis=1)
    fitted_rmse = np.sqrt(np.mean((fitted - y[head]) ** 2))
    assert fitted_rmse < np.sqrt(np.mean((prior - y[head]) ** 2))
    assert fitted_rmse < 1.5 * 400**-0.5


@pytest.mark.parametrize(
    "args, message",
    [
        (["predict", "{fit}", "--observe", "{tmp}/missing.npz", "--out", "{tmp}/p"], "no such file"),
        (["predict", "{tmp}", "--observe", "{tmp}/obs.npz", "--out", "{tmp}/p"], "not a saved fit"),
        (["predict", "{fit}", "--observe", "{tmp}/bad.npz", "--out", "{tmp}/p"], "2 DoF"),
        (["predict", "{fit}", "--observe", "{tmp}/obs.npz", "--out", "{tmp}/p", "--duration", "0.05"], "exceed the duration"),
        (["fit", "lasa:NoSuchShape", "--out", "{tmp}/f"], "NoSuchShape"),
        (["fit", DATASET, "--model", "promp", "--out", "{tmp}/f"], "not for promp"),
        (["fit", DATASET, "--latent-dim", "30", "--num-basis", "4", "--out", "{tmp}/f"], "latent dimension"),
        (["fit", DATASET, "--latent-dim", "3", "--num-basis", "4", "--engine", "nuts", "--max-iter", "5", "--out", "{tmp}/f"], "does not take"),
    ],
)
def test_user_errors_exit_2_with_one_line(fit_dir, tmp_path, capsys, args, message):
    np.savez(tmp_path / "obs.npz", t=np.array([0.0, 0.1]), y=np.zeros((2, 2)))
    np.savez(tmp_path / "bad.npz", t=np.array([0.0, 0.1]), y=np.zeros((2, 3)))
    argv = [a.format(fit=fit_dir, tmp=tmp_path) for a in args]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("lmpromp: error:") and "\n" not in err and message in err


def test_fewer_demonstrations_than_latent_dimensions_is_a_clear_error():
    demos = lp.data.load_dataset("synthetic:latent?L=3&D=1&J=5&V=1&T=10")
    with pytest.raises(LmprompError, match="fewer demonstrations"):
        lp.fit(demos, hyper=lp.Hyperparameters(latent_dim=4), num_basis=5)

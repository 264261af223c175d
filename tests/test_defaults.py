"""Default settings on real demonstrations (docs/defaults.md) and the degeneracy warnings.

The full table over every dataset is ``reports/real-data/`` (``make real-data``);
here a small real case and a noisy synthetic case check that the defaults give
movement distributions that follow the demonstrations, and that the thesis's
settings are flagged where they do not.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import lmpromp_ppl as lp
from lmpromp_ppl.basis import DEFAULT_NUM_BASIS, DEFAULT_WIDTH, design_matrix
from lmpromp_ppl.data.core import Demonstrations
from lmpromp_ppl.diagnostics.degeneracy import H_MEAN_LIMIT, WEIGHT_LIMIT, degeneracy_warnings
from lmpromp_ppl.predict.from_fit import population_prediction, predict_from_fit
from lmpromp_ppl.reports.real_data import dataset_row

GSHAPE = "lasa:GShape?every=20"


def _fit(data, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return lp.fit(data, **kw)


def test_presets_default_learns_noise_and_thesis_keeps_its_values():
    default, thesis = lp.preset("default"), lp.preset("thesis")
    assert default == lp.DEFAULT and thesis == lp.Hyperparameters() == lp.THESIS
    assert default.learn_beta and default.lambda0 == 1.0
    assert default == thesis.replace(learn_beta=True)
    assert not thesis.learn_beta and thesis.lambda0 == 1.0 and thesis.beta == 100.0
    # proper: the default's settings with proper Gamma priors and the weak offset prior for sampling
    assert lp.PROPER == default.replace(a0=1e-2, b0=1e-2, lambda0=1e-2)


def test_default_basis_is_well_conditioned_and_the_thesis_basis_is_not():
    phase = np.linspace(0, 1, 100)

    def cond(J, width):
        psi = np.asarray(design_matrix(phase, 1, J, width))
        return np.linalg.cond(psi.T @ psi)

    assert cond(DEFAULT_NUM_BASIS, DEFAULT_WIDTH) < 1e5
    assert cond(10, 2.0) > 1e6  # the thesis's width: near-collinear neighbours


@pytest.fixture(scope="module")
def gshape_default():
    return _fit(GSHAPE, model="lmpromp", engine="cavi", hyper=lp.preset("default", latent_dim=2))


def test_default_fit_of_lasa_follows_the_demonstrations(gshape_default):
    result = gshape_default
    demos = lp.data.load_dataset(GSHAPE)
    pop = population_prediction(result, query=demos.phases()[0], num_samples=1)
    mean = np.mean(np.stack(demos.positions), axis=0)
    scale = np.asarray(result.scaling.scale)
    rmse = np.sqrt(np.mean(((pop.mean - mean) / scale) ** 2))
    assert rmse < 0.25
    assert np.max(np.abs(result.point["w"])) < WEIGHT_LIMIT
    # the mean lives in b, not in M h
    h = np.asarray(result.point["h"])
    assert np.linalg.norm(h.mean(axis=0)) < H_MEAN_LIMIT
    assert result.summary["warnings"] == []
    # the learned noise is that of a smooth recording, far below the thesis's fixed 0.1
    assert "beta" in result.point and float(result.point["beta"]) > 100.0


def test_a_too_coarse_basis_on_lasa_is_flagged_as_degenerate():
    """With J = 6 on GShape the weights reach about 11 and a column of M carries the mean
    movement (docs/defaults.md); the fit says both in plain words."""
    result = _fit(GSHAPE, model="lmpromp", engine="cavi", hyper=lp.preset("default", latent_dim=2), num_basis=6)
    text = " ".join(result.summary["warnings"])
    assert "mean movement carried by M h" in text
    assert "weights far beyond the data's scale" in text
    demos = lp.data.load_dataset(GSHAPE)
    pop = population_prediction(result, query=demos.phases()[0], num_samples=1)
    rmse = np.sqrt(np.mean(((pop.mean - np.mean(np.stack(demos.positions), axis=0)) / result.scaling.scale) ** 2))
    assert rmse > 0.25


def _noisy_sines(noise_sd=0.5, L=10, T=100, seed=0):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, T)
    truth = np.sin(2 * np.pi * t)[:, None]
    y = [truth + noise_sd * rng.standard_normal((T, 1)) for _ in range(L)]
    return Demonstrations(times=[t] * L, positions=y, name="noisy-sines"), t, truth


def test_learned_noise_fits_noisy_recordings():
    demos, t, truth = _noisy_sines()
    result = _fit(demos, model="lmpromp", engine="cavi", hyper=lp.preset("default", latent_dim=2))
    pred = population_prediction(result, query=t, num_samples=1)
    # the noise level is learned: 0.5 in data units, within sampling error of 1000 residuals
    assert abs(pred.noise_sd[0] - 0.5) < 0.05
    assert np.max(np.abs(result.point["w"])) < WEIGHT_LIMIT
    assert np.sqrt(np.mean((pred.mean - truth) ** 2)) < 0.1
    # conditioning on the first third follows the sine, not the noise
    third = t.size // 3
    cond = predict_from_fit(result, t[:third], demos.positions[0][:third], query=t, num_samples=1)
    assert np.sqrt(np.mean((cond.mean - truth) ** 2)) < 0.2
    # the band of a new observation includes the noise
    np.testing.assert_allclose(pred.sd_obs**2, pred.sd**2 + pred.noise_sd**2, rtol=1e-12)


def test_default_predict_is_exact_and_passes_through_precise_observations(gshape_default):
    result = gshape_default
    demos = lp.data.load_dataset(GSHAPE)
    z, y = demos.phases()[0][:15], demos.positions[0][:15]
    exact = predict_from_fit(result, z, y, query=z, num_samples=1)
    thesis = predict_from_fit(result, z, y, query=z, num_samples=1, exact=False)
    scale = np.asarray(result.scaling.scale)
    miss_exact = np.sqrt(np.mean(((exact.mean - y) / scale) ** 2))
    miss_thesis = np.sqrt(np.mean(((thesis.mean - y) / scale) ** 2))
    assert miss_exact < 0.05 and miss_exact < miss_thesis


def test_real_data_row_meets_every_criterion_on_lasa():
    # every fold: single folds' coverage ranges from 0.5 to 0.97 on seven demonstrations
    row = dataset_row(GSHAPE, "cavi", max_folds=7, options={"hyper": lp.preset("default", latent_dim=2)})
    assert row["folds"] == list(range(7))
    assert all(row["passes"].values()), row
    assert 0.0 < row["halfwidth"] < 1.5 and row["max_abs_w"] < WEIGHT_LIMIT


@pytest.mark.slow
def test_nuts_row_on_lasa_follows_the_demonstrations():
    """The NUTS rows of reports/real-data/ (proper preset): the mean in b, weights of order one."""
    options = {"num_chains": 2, "num_warmup": 300, "num_samples": 300}
    row = dataset_row(GSHAPE, "nuts", max_folds=3, options=options)
    assert row["passes"]["pop_rmse"] and row["passes"]["cond_rmse_observed"], row
    assert row["max_abs_w"] < WEIGHT_LIMIT
    assert not any("carried by M h" in w for w in row["warnings"]), row["warnings"]


# ----------------------------------------------------------- degeneracy warnings
def _clean_point(L=6, d=8, V=2, K=None):
    rng = np.random.default_rng(0)
    h = rng.standard_normal((L, V))
    h -= h.mean(axis=0)
    point = {"h": h, "w": rng.uniform(-1, 1, (L, d)), "b": np.zeros(d), "alpha": np.array(5.0), "M": np.ones((d, V))}
    return point


def test_no_warning_for_a_clean_fit():
    assert degeneracy_warnings("lmpromp", point=_clean_point(), summary={"converged": True, "active_latent_dims": [0, 1]}) == []


@pytest.mark.parametrize(
    "change, summary, phrase",
    [
        (lambda p: p.update(h=p["h"] - 1.2), {}, "mean movement carried by M h"),
        (lambda p: p.update(w=p["w"] * 50), {}, "weights far beyond"),
        (lambda p: None, {"active_latent_dims": []}, "every latent dimension is switched off"),
        (lambda p: None, {"converged": False, "iterations": 2000}, "not converged"),
        (lambda p: None, {"divergences": 3}, "3 divergent"),
    ],
)
def test_each_symptom_gives_its_warning(change, summary, phrase):
    point = _clean_point()
    change(point)
    out = degeneracy_warnings("lmpromp", point=point, summary=summary)
    assert len(out) == 1 and phrase in out[0]


def test_h_offset_is_rotation_invariant_over_draws():
    point = _clean_point()
    rng = np.random.default_rng(1)
    draws = []
    for _ in range(20):  # every draw offset by 1.2 in a random direction: the mean over draws is ~0
        angle = rng.uniform(0, 2 * np.pi)
        draws.append(point["h"] + 1.2 * np.array([np.cos(angle), np.sin(angle)]))
    h = np.stack(draws)[None]  # (chain, draw, L, V)
    out = degeneracy_warnings("lmpromp", point=point, draws={"h": h})
    assert any("carried by M h" in x for x in out)


def test_h_offset_that_carries_no_movement_is_not_a_warning():
    # a latent dimension the data do not need (NUTS): h drawn from the prior, a small column of M
    L, J, V = 7, 8, 3
    rng = np.random.default_rng(2)
    h = rng.standard_normal((1, 400, L, V))
    offset = np.linalg.norm(h.mean(axis=2), axis=-1).mean()
    assert offset > H_MEAN_LIMIT  # sqrt(V / L) = 0.65 by chance alone
    point = {"h": h[0].mean(axis=0), "w": np.zeros((L, J))}
    basis = dict(num_dofs=1, num_basis=J, width=1.0)
    small = {"h": h, "M": np.full((1, 400, J, V), 0.01)}
    assert degeneracy_warnings("lmpromp", point=point, draws=small, **basis) == []
    large = {"h": h, "M": np.ones((1, 400, J, V))}
    (out,) = degeneracy_warnings("lmpromp", point=point, draws=large, **basis)
    assert "carried by M h" in out and "moves the mean movement by" in out
    # without the basis the h offset alone decides
    assert degeneracy_warnings("lmpromp", point=point, draws=small) != []


def test_mixture_copy_and_responsibility_weighted_offset():
    d, J = 6, 6
    b = np.zeros((3, d))
    b[2] += 2.0
    point = {"b": b, "alpha": np.full(3, 4.0), "M": np.ones((3, d, 1)), "w": np.zeros((4, d)),
             "h": np.zeros((4, 3, 1))}
    out = degeneracy_warnings("mixture", point=point, num_dofs=1, num_basis=J, resp=np.eye(4, 3), active=[0, 1, 2])
    assert len(out) == 1 and "components 0 and 1 are copies" in out[0]
    # a removed component is not compared
    assert degeneracy_warnings("mixture", point=point, num_dofs=1, num_basis=J, resp=np.eye(4, 3), active=[0, 2]) == []
    # h offset only among the demonstrations a component is responsible for
    point["h"][:2, 0, 0] = 2.0
    resp = np.zeros((4, 3))
    resp[:2, 0] = resp[2:, 2] = 1.0
    out = degeneracy_warnings("mixture", point=point, num_dofs=1, num_basis=J, resp=resp, active=[0, 2])
    assert len(out) == 1 and "of component 0" in out[0]


def test_real_data_command_writes_the_table(tmp_path, capsys):
    from lmpromp_ppl.cli import main

    out = tmp_path / "rd"
    assert main(["real-data", "--datasets", "lasa:Angle?every=20", "--engines", "cavi", "--max-folds", "2",
                 "--mixture-seeds", "0", "--out", str(out), "--quiet"]) == 0
    text = (out / "real-data.md").read_text()
    assert "`lasa:Angle?every=20` | cavi | 7 |" in text and "## Criteria met" in text
    import json

    document = json.loads((out / "real-data.json").read_text())
    (row,) = document["rows"]
    assert row["folds"] == [0, 6] and set(row["passes"]) == set(document["criteria"])
    assert (out / "predictive.png").stat().st_size > 0
    # --merge keeps the rows of pairs not run now and records both commands
    assert main(["real-data", "--datasets", "lasa:Line?every=20", "--engines", "cavi", "--max-folds", "1",
                 "--mixture-seeds", "0", "--out", str(out), "--quiet", "--merge", "--force"]) == 0
    merged = json.loads((out / "real-data.json").read_text())
    assert [r["dataset"] for r in merged["rows"]] == ["lasa:Angle?every=20", "lasa:Line?every=20"]
    assert merged["rows"][0] == row and " && " in merged["command"]
    assert main(["real-data", "--engines", "cavi", "--merge", "--force", "--out", str(tmp_path / "none")]) == 2
    assert "--merge needs an existing" in capsys.readouterr().err and not (tmp_path / "none").exists()
    # a bad engine is one line and status 2, and leaves no output behind
    assert main(["real-data", "--engines", "cavi,gibbs", "--out", str(tmp_path / "bad")]) == 2
    assert "unknown engine" in capsys.readouterr().err and not (tmp_path / "bad").exists()


def test_coverage_standard_error_is_over_folds_and_shown_in_the_table():
    from lmpromp_ppl.reports.real_data import coverage_se, markdown_table

    folds = [0.5, 0.9, 1.0, 0.8]
    row = {"dataset": "x", "engine": "cavi", "num_demos": 4, "pop_rmse": 0.1, "coverage90": float(np.mean(folds)),
           "halfwidth": 0.3, "cond_rmse_observed": 0.01, "cond_rmse_rest": 0.1, "uncond_rmse_rest": 0.2,
           "noise_sd": 0.01, "max_abs_w": 2.0, "per_fold": [{"coverage90": c} for c in folds]}
    from lmpromp_ppl.reports.real_data import passes

    row["passes"] = passes(row)
    se = np.std(folds, ddof=1) / 2.0
    assert coverage_se(row) == pytest.approx(se)
    assert f"0.8 ± {se:.2f}" in markdown_table([row])
    assert coverage_se({**row, "per_fold": row["per_fold"][:1]}) is None


def test_fit_command_says_when_the_fit_is_degenerate(tmp_path, capsys):
    from lmpromp_ppl.cli import main

    args = ["fit", GSHAPE, "--num-basis", "6", "--latent-dim", "2"]
    assert main(args + ["--out", str(tmp_path / "a")]) == 0
    out = capsys.readouterr().out
    assert "warning: mean movement carried by M h" in out
    import json

    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert any("carried by M h" in w for w in summary["warnings"])
    assert main(args + ["--out", str(tmp_path / "b"), "--quiet"]) == 0
    assert capsys.readouterr().out == ""


def test_nuts_datasets_all_is_every_dataset_of_the_table():
    from lmpromp_ppl.cli.real_data import nuts_names

    names = ["lasa:Angle?every=10", "gunpoint:train"]
    assert nuts_names("all", names) == names
    assert nuts_names(" lasa:Line?every=20 , gunpoint:train", names) == ["lasa:Line?every=20", "gunpoint:train"]

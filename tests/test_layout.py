"""One result layout for every engine: same variables and dims, identical after save and load."""

import numpy as np
import pytest
import xarray as xr

import lmpromp_ppl as lp

DATASET = "synthetic:latent?L=6&D=2&J=3&V=2&T=15&seed=1"
OPTIONS = {
    "cavi": {},
    "cavi_lr": {},
    "nuts": {"num_chains": 2, "num_warmup": 150, "num_samples": 150},
    "svi_meanfield": {"num_steps": 400},
    "svi_autonormal": {"num_steps": 400},
    "svi_lowrank": {"num_steps": 400},
}


@pytest.fixture(scope="module")
def results():
    import warnings

    from lmpromp_ppl.errors import ConvergenceWarning

    hyper = lp.preset("proper", latent_dim=2)
    out = {}
    for engine, options in OPTIONS.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)  # tiny step budgets, on purpose
            out[engine] = lp.fit(DATASET, engine=engine, hyper=hyper, num_basis=3, seed=0, **options)
    return out


@pytest.fixture(scope="module")
def trees(results):
    """Each engine's tree with 200 draws, built once for the tests that read it."""
    return {engine: res.to_datatree(200) for engine, res in results.items()}


def _layout(tree):
    return {
        group: {name: tree[group][name].dims for name in tree[group].to_dataset().data_vars}
        for group in ("posterior", "derived", "observed_data", "point_estimate")
    }


def test_every_engine_has_the_same_sites_and_dims(results, trees):
    layouts = {engine: _layout(tree) for engine, tree in trees.items()}
    reference = layouts["cavi"]
    assert set(reference["posterior"]) >= {"b", "M", "h", "w", "alpha", "lam"}
    assert reference["derived"]["gram_eig"] == ("chain", "draw", "latent")
    for engine, layout in layouts.items():
        assert layout == reference, engine
    for engine, tree in trees.items():
        group = "sample_stats" if engine == "nuts" else "optimization"
        assert group in tree.children, engine
        assert tree.attrs["engine"] == engine and "package_versions" in tree.attrs


def test_saved_and_reloaded_trees_are_identical(results, trees, tmp_path):
    for engine, res in results.items():
        tree = trees[engine]
        res.save(tmp_path / engine)
        back = lp.load(tmp_path / engine).to_datatree()
        assert set(back.children) == set(tree.children), engine
        for group in tree.children:
            xr.testing.assert_identical(back[group].to_dataset(), tree[group].to_dataset())
        assert back.attrs == tree.attrs


def test_posterior_predictive_replicates_the_demonstrations(results):
    """y_rep = Psi w + noise: its mean over draws sits on the data within the posterior spread."""
    res = results["cavi"]
    rep = res.to_datatree(300, posterior_predictive=True)["posterior_predictive"]["y"]
    assert rep.dims == ("chain", "draw", "demo", "sample", "dof")
    y = res.observed["y"]
    mean, sd = rep.mean(("chain", "draw")).values, rep.std(("chain", "draw")).values
    z = (y - mean) / sd
    assert np.all(np.isfinite(z))
    # Standardised residuals of a calibrated replicate have unit scale; far fewer than
    # 1 % beyond 4 sd for a Gaussian, so 1 % is a loose but failing-capable bound.
    assert np.mean(np.abs(z) > 4) < 0.01
    assert 0.2 < np.std(z) < 2.0

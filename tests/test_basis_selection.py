"""``num_basis="auto"``: the number of basis functions chosen by the evidence lower bound.

Synthetic sets are generated with a smooth basis (J = 8 or 10, width 2), LASA
shapes need a finer one; the bound has to tell them apart, and the mixture on
``synthetic:clusters`` has to find the four clusters at the J it chooses
(docs/defaults.md, *Choosing J by the bound*).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import lmpromp_ppl as lp
import lmpromp_ppl.api as api
from lmpromp_ppl.cli import main

GRID = (6, 10, 20, 30)


@pytest.fixture(scope="module")
def clusters():
    return lp.data.load_dataset("synthetic:clusters")


@pytest.fixture
def small_grid(monkeypatch):
    monkeypatch.setattr(api, "AUTO_NUM_BASIS", GRID)


@pytest.fixture
def mixture_grid(monkeypatch):
    """The mixture's selection over (6, 10, 20): a basis twice as fine as the generator's stays a choice
    that the bound has to turn down; J = 30 would add the costliest fit and test nothing new."""
    monkeypatch.setattr(api, "AUTO_NUM_BASIS", GRID[:3])


def test_the_bound_picks_a_coarse_basis_for_smooth_data_and_a_fine_one_for_lasa(clusters):
    smooth = lp.select_num_basis(clusters, grid=GRID)
    shape = lp.select_num_basis("lasa:GShape?every=20", grid=GRID)
    for choice in (smooth, shape):
        assert choice["grid"] == list(GRID) and len(choice["elbo"]) == len(GRID)
        assert choice["num_basis"] == GRID[int(np.argmax(choice["elbo"]))]
        assert choice["result"].num_basis == choice["num_basis"]
        assert choice["result"].summary["elbo"] == pytest.approx(max(choice["elbo"]))
    # generated from J = 8 (width 2): the bound falls as the basis grows beyond it
    assert smooth["num_basis"] <= 10
    assert np.all(np.diff(smooth["elbo"][GRID.index(10):]) < 0)
    # the G needs more than ten basis functions per DoF
    assert shape["num_basis"] >= 20


def test_the_choice_does_not_depend_on_the_seed(clusters):
    """The selection's CAVI fits start deterministically (no restarts), so the
    real-data report may choose J once per dataset for all its seeds."""
    first = lp.select_num_basis(clusters, grid=(6, 10), seed=0)
    other = lp.select_num_basis(clusters, grid=(6, 10), seed=7)
    assert first["elbo"] == other["elbo"] and first["num_basis"] == other["num_basis"]


def test_the_grid_stops_at_the_shortest_demonstration(clusters):
    short = lp.data.load_dataset("synthetic:clusters?T=12")
    choice = lp.select_num_basis(short, grid=GRID)
    assert choice["grid"] == [6, 10]
    with pytest.raises(lp.errors.LmprompError, match="no basis size"):
        lp.select_num_basis(short, grid=(20, 30))


def test_fit_auto_is_the_fit_at_the_chosen_basis(clusters, small_grid):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        auto = lp.fit(clusters, num_basis="auto", seed=3)
        table = auto.summary["num_basis_selection"]
        direct = lp.fit(clusters, num_basis=table["num_basis"], seed=3)
    assert auto.num_basis == table["num_basis"] == GRID[int(np.argmax(table["elbo"]))]
    assert auto.summary["elbo"] == pytest.approx(direct.summary["elbo"], rel=1e-12)
    np.testing.assert_allclose(auto.point["w"], direct.point["w"], rtol=1e-10, atol=1e-12)
    with pytest.raises(lp.errors.LmprompError, match="'auto'"):
        lp.fit(clusters, num_basis="many")


def test_the_mixture_finds_the_four_clusters_at_the_chosen_basis(clusters, mixture_grid):
    hyper = lp.preset("default", num_components=6, latent_dim=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = lp.fit(clusters, model="mixture", hyper=hyper, num_basis="auto", seed=0)
    assert result.summary["num_basis_selection"]["grid"] == list(GRID[:3])
    assert result.summary["num_basis_selection"]["num_basis"] <= 10
    assert len(result.summary["active_components"]) == 4
    assert result.summary["ari"] >= 0.95


def test_cli_fit_auto_says_which_basis_and_saves_the_comparison(tmp_path, capsys, small_grid):
    out = tmp_path / "fit"
    assert main(["fit", "synthetic:clusters", "--num-basis", "auto", "--seed", "3", "--out", str(out)]) == 0
    line = capsys.readouterr().out
    saved = lp.load(out)
    J = saved.summary["num_basis_selection"]["num_basis"]
    assert saved.num_basis == J and f"J = {J} (by the bound)" in line
    assert saved.summary["num_basis_selection"]["grid"] == list(GRID)

"""The mixture's split-and-merge search (lmpromp_ppl.inference.cavi.search) and its reporting.

* the acceptance rule keeps a move only when the bound rises, and the best bound
  over a search never decreases;
* merge and split moves produce valid states (responsibilities sum to one,
  removed components get none);
* through ``lmpromp_ppl.fit``: the search recovers synthetic clusters and the
  shapes of a pooled LASA set (ARI against the labels in ``summary["ari"]``), and
  its bound is never below plain CAVI's from the same start.
"""

import jax
import numpy as np
import pytest

import lmpromp_ppl
from lmpromp_ppl.basis import DEFAULT_NUM_BASIS, DEFAULT_WIDTH
from lmpromp_ppl.data import Demonstrations, load_dataset, model_data, standardise
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference import cavi
from lmpromp_ppl.inference.cavi import init_mixture_state
from lmpromp_ppl.inference.cavi import search as ms
from lmpromp_ppl.models.hyper import Hyperparameters
from lmpromp_ppl.reports.real_data import POOLED_LASA

cm = cavi


def test_acceptance_rule_needs_a_higher_bound():
    assert ms.accept(-100.0 + 1e-3, -100.0)
    assert not ms.accept(-100.0, -100.0)
    assert not ms.accept(-100.0 - 1.0, -100.0)
    assert not ms.accept(-100.0 + 1e-12, -100.0)  # round-off is not an improvement
    assert not ms.accept(float("nan"), -100.0)
    assert not ms.accept(0.0, float("nan"))


@pytest.fixture(scope="module")
def clusters_state():
    """The data and hyperparameters of ``test_search_recovers_synthetic_clusters`` (shared compiled code)."""
    demos, _ = standardise(load_dataset("synthetic:clusters"))
    data = cavi.sufficient_statistics(model_data(demos, 10))
    hyper = Hyperparameters(latent_dim=2, num_components=6)
    return data, hyper, cm.hyper_arrays(hyper), init_mixture_state(data, hyper, jax.random.key(3))


def test_merge_and_split_moves_give_valid_states(clusters_state):
    data, _, hyper_arr, state = clusters_state
    pairs = ms.merge_candidates(state, data)
    assert len(pairs) == 15 and len(set(pairs)) == 15
    k, l = pairs[0]
    merged = ms.merge_state(state, hyper_arr, k, l)
    resp = cm.responsibilities(merged)
    np.testing.assert_allclose(resp.sum(axis=1), 1.0, rtol=1e-12)
    assert not bool(merged.active[l]) and np.all(resp[:, l] == 0.0)
    np.testing.assert_allclose(resp[:, k], cm.responsibilities(state)[:, [k, l]].sum(axis=1), rtol=1e-12)
    assert np.isfinite(float(cm.elbo(merged, data, hyper_arr)))
    split = ms.split_state(merged, data, hyper_arr, k, l, seed=0)
    assert split is not None and bool(split.active[l])
    resp = cm.responsibilities(split)
    np.testing.assert_allclose(resp.sum(axis=1), 1.0, rtol=1e-12)
    assert resp[:, k].sum() > 0 and resp[:, l].sum() > 0
    assert np.isfinite(float(cm.elbo(split, data, hyper_arr)))
    assert ms.split_candidates(split, hyper_arr)  # components with >= 2 demonstrations
    with pytest.raises(LmprompError, match="cannot merge"):
        ms.merge_state(merged, hyper_arr, k, l)


def test_search_best_bound_never_decreases_and_beats_plain_cavi(clusters_state):
    data, _, hyper_arr, state = clusters_state
    found = ms.search(state, data, hyper_arr, seed=0)
    assert np.all(np.diff(found.best_elbos) >= 0.0)
    assert len(found.best_elbos) == len(found.moves) + 2 or len(found.moves) == 12
    plain = cavi.run(state, data, hyper_arr, 1e-8, 300).elbo_trace[-1]
    assert found.elbo >= plain
    assert found.elbo == pytest.approx(float(cm.elbo(found.state, data, hyper_arr)), rel=1e-10)


def test_pooled_lasa_string_loads_with_shape_labels():
    demos = load_dataset("lasa:GShape+angle+Sshape?every=20")
    assert demos.name == "lasa:GShape+Angle+Sshape?every=20"
    assert demos.num_demos == 21 and demos.num_dofs == 2
    assert demos.labels.tolist() == ["GShape"] * 7 + ["Angle"] * 7 + ["Sshape"] * 7
    assert set(demos.lengths) == {51}
    single = load_dataset("lasa:Angle?every=20")
    np.testing.assert_array_equal(demos.positions[7], single.positions[0])
    with pytest.raises(Exception, match="more than once"):
        load_dataset("lasa:Angle+angle")
    with pytest.raises(Exception, match="empty shape"):
        load_dataset("lasa:Angle+")


def _ari(spec, hyper, seed, **options):
    # the basis and width the search was measured with (benchmarks/mixture_search.py --num-basis 10)
    options = {"num_basis": 10, "width": 2.0, **options}
    res = lmpromp_ppl.fit(spec, model="mixture", hyper=hyper, seed=seed, **options)
    return res.summary


@pytest.mark.filterwarnings("ignore::lmpromp_ppl.errors.ConvergenceWarning")
@pytest.mark.parametrize("seed", [0, 1])
def test_search_recovers_synthetic_clusters(seed):
    """Four clusters 2.1 apart in a plane, K = 6: ARI >= 0.95 against the cluster labels."""
    hyper = Hyperparameters(latent_dim=2, num_components=6)
    summary = _ari("synthetic:clusters", hyper, seed)
    assert summary["ari"] >= 0.95, summary["active_components"]
    assert len(summary["active_components"]) == 4


@pytest.mark.filterwarnings("ignore::lmpromp_ppl.errors.ConvergenceWarning")
def test_search_recovers_pooled_lasa_shapes():
    """Three LASA shapes pooled (21 demonstrations), default settings, K = 6, V = 2: the three shapes.

    With the thesis-era ``lambda0 = 0.01`` the bound preferred one component
    shared by two shapes (docs/defaults.md); with the default ``lambda0 = 1`` the
    shapes' partition has the highest bound and the search finds it.
    """
    hyper = lmpromp_ppl.preset("default", num_components=6, latent_dim=2)
    summary = _ari("lasa:GShape+Angle+Sshape?every=20", hyper, 0, num_basis=DEFAULT_NUM_BASIS, width=DEFAULT_WIDTH)
    assert summary["ari"] >= 0.9
    assert len(summary["active_components"]) == 3


_MERGED_BY_THE_BOUND = pytest.mark.xfail(
    strict=True,
    reason="the bound of two shapes on one component exceeds the bound started from the four shapes "
           "(7073.0 > 7064.5 at J = 20, the bound's choice with V = 2; 7212.1 > 7189.6 at J = 25; docs/defaults.md): "
           "a model limitation, not the search's",
)


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::lmpromp_ppl.errors.ConvergenceWarning")
@pytest.mark.parametrize("dataset", [
    pytest.param(d, marks=_MERGED_BY_THE_BOUND) if d.startswith("lasa:Khamesh") else d
    for d in POOLED_LASA
])
def test_mixture_finds_pooled_lasa_shapes_in_nine_of_ten_seeds(dataset):
    """The issue's criterion on each pooled LASA set of reports/real-data/: K = 6 keeps the shapes, ARI >= 0.9."""
    from lmpromp_ppl.reports.real_data import mixture_rows

    rows = mixture_rows([dataset], seeds=range(10))
    ok = sum(r["active_components"] == r["num_types"] and r["ari"] >= 0.9 for r in rows)
    assert ok >= 9, [(r["active_components"], r["ari"]) for r in rows]


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::lmpromp_ppl.errors.ConvergenceWarning")
def test_mixture_finds_synthetic_clusters_in_nine_of_ten_seeds():
    """The issue's criterion on synthetic:clusters with the mixture's default basis (chosen by the bound)."""
    from lmpromp_ppl.reports.real_data import mixture_rows

    rows = mixture_rows(["synthetic:clusters"], seeds=range(10))
    ok = sum(r["active_components"] == 4 and r["ari"] >= 0.95 for r in rows)
    assert ok >= 9, [(r["num_basis"], r["active_components"], r["ari"]) for r in rows]


@pytest.mark.filterwarnings("ignore::lmpromp_ppl.errors.ConvergenceWarning")
def test_search_option_and_unlabelled_data():
    hyper = Hyperparameters(latent_dim=2, num_components=3)
    with pytest.raises(LmprompError, match="unknown search"):
        lmpromp_ppl.fit("synthetic:clusters?L=12", model="mixture", hyper=hyper, search="greedy")
    with pytest.raises(LmprompError, match="mixture model only"):
        lmpromp_ppl.fit("synthetic:clusters?L=12", model="lmpromp", search="none")
    demos = load_dataset("synthetic:clusters")
    unlabelled = Demonstrations(demos.times, demos.positions)
    res = lmpromp_ppl.fit(unlabelled, model="mixture", hyper=hyper.replace(num_components=6), search="none",
                          num_basis=8)  # a fixed basis: the choice of J is tested in test_basis_selection
    assert "ari" not in res.summary and "active_components" in res.summary

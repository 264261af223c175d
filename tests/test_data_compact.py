"""The compact model inputs (PhaseData) against the dense design matrices they replace.

``model_data`` keeps each demonstration's single-DoF basis at its phases
instead of one dense (T D, D J) design matrix per demonstration.  These tests
check that nothing downstream can tell: the dense view equals the design
matrices built the former way, every NumPyro declaration gives the same log
density on both forms, and CAVI's statistics agree on the shared and the
per-demonstration paths.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpyro import handlers
from numpyro.infer.util import log_density

from lmpromp_ppl.basis import design_matrix
from lmpromp_ppl.data.core import (
    DemoStatistics,
    Demonstrations,
    ModelData,
    PhaseData,
    SharedDesign,
    demo_statistics,
    model_data,
    shared_design,
)
from lmpromp_ppl.errors import DataError, LmprompError
from lmpromp_ppl.inference import cavi
from lmpromp_ppl.models import Hyperparameters
from lmpromp_ppl.models.registry import model_function, model_inputs

NUM_BASIS = 3
HYPER = Hyperparameters(beta=4.0, lambda0=0.7, gamma=1.3, a0=2.5, b0=0.6, c0=1.7, d0=0.9, latent_dim=2,
                        num_components=2, learn_beta=True, beta_a0=3.0, beta_b0=0.5)


def _demos(lengths, seed, shared=False):
    rng = np.random.default_rng(seed)
    if shared:
        grid = np.linspace(0.0, 2.0, lengths[0])
        times = [grid for _ in lengths]
    else:
        times = [np.sort(rng.uniform(0, 1, n)) + np.arange(n) for n in lengths]
    return Demonstrations(times, [rng.normal(size=(n, 2)) for n in lengths])


def dense_the_former_way(demos, num_basis):
    """The padded (L, S, d) inputs as ``model_data`` built them before the compact form."""
    phases = demos.phases()
    size = max(p.shape[0] for p in phases) * demos.num_dofs
    d = demos.num_dofs * num_basis
    psi = np.zeros((demos.num_demos, size, d))
    y = np.zeros((demos.num_demos, size))
    mask = np.zeros((demos.num_demos, size))
    for i, (z, pos) in enumerate(zip(phases, demos.positions)):
        n = z.shape[0] * demos.num_dofs
        psi[i, :n] = np.asarray(design_matrix(z, demos.num_dofs, num_basis))
        y[i, :n] = pos.reshape(-1)
        mask[i, :n] = 1.0
    return ModelData(jnp.asarray(psi), jnp.asarray(y), jnp.asarray(mask))


CASES = {"ragged": dict(lengths=(6, 4, 5), seed=0), "shared": dict(lengths=(5, 5, 5, 5), seed=1, shared=True)}


@pytest.fixture(scope="module", params=sorted(CASES))
def pair(request):
    demos = _demos(**CASES[request.param])
    return request.param, model_data(demos, NUM_BASIS), dense_the_former_way(demos, NUM_BASIS)


def test_dense_view_equals_the_former_design_matrices(pair):
    case, compact, dense = pair
    assert isinstance(compact, PhaseData)
    # one basis matrix for demonstrations that share their phases
    assert compact.phi.shape[0] == (1 if case == "shared" else compact.num_demos)
    assert compact.shares_psi() == dense.shares_psi() == (case == "shared")
    view = compact.dense()
    for got, want in zip(view, dense):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    assert (compact.num_demos, compact.num_weights) == (dense.num_demos, dense.num_weights)


MODELS = [("lmpromp", "none"), ("lmpromp", "w"), ("lmpromp", "wh"), ("lmpromp", "whb"), ("mixture", "wh"),
          ("mixture", "none"), ("mixture", "w"), ("promp", "none"), ("promp", "w")]


@pytest.mark.parametrize("name, collapsed", MODELS)
def test_every_declaration_has_the_same_log_density_on_both_forms(pair, name, collapsed):
    """At parameters drawn from the prior (random inputs), the compact and the dense inputs
    give the same log joint density."""
    _, compact, dense = pair
    model = model_function(name, collapsed)
    for seed in range(1):
        trace = handlers.trace(handlers.seed(model, jax.random.key(seed))).get_trace(dense, HYPER)
        params = {k: v["value"] for k, v in trace.items() if v["type"] == "sample" and not v["is_observed"]}
        density = jax.jit(lambda inputs, p: log_density(model, (inputs, HYPER), {}, p)[0])  # one program per form
        want = float(density(dense, params))
        got = float(density(compact, params))
        assert np.isfinite(want)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)
        # the form the engines evaluate (shared-design statistics where the design is shared)
        fastest = model_inputs(name, collapsed, compact)
        np.testing.assert_allclose(float(density(fastest, params)), want, rtol=1e-12, atol=1e-9)


def _assert_same_density_and_gradient(model, dense, forms, *, seed, rtol, grad_rtol):
    """At parameters drawn from the prior, each of ``forms`` gives the dense inputs' log density and gradient."""
    trace = handlers.trace(handlers.seed(model, jax.random.key(seed))).get_trace(dense, HYPER)
    params = {k: v["value"] for k, v in trace.items() if v["type"] == "sample" and not v["is_observed"]}

    @jax.jit
    def value_and_grad(inputs):
        return jax.value_and_grad(lambda p: log_density(model, (inputs, HYPER), {}, p)[0])(params)

    want, want_grad = value_and_grad(dense)
    for inputs in forms:
        got, got_grad = value_and_grad(inputs)
        np.testing.assert_allclose(float(got), float(want), rtol=rtol)
        for site in want_grad:
            np.testing.assert_allclose(np.asarray(got_grad[site]), np.asarray(want_grad[site]),
                                       rtol=grad_rtol, atol=1e-9 * float(np.max(np.abs(want_grad[site]))))


SHARED_MODELS = [("lmpromp", "none"), ("lmpromp", "w"), ("lmpromp", "wh"), ("mixture", "w"), ("mixture", "wh")]


@pytest.mark.parametrize("name, collapsed", SHARED_MODELS)
def test_shared_design_statistics_give_the_dense_density_and_gradient(name, collapsed):
    """Where every demonstration shares one design, the declarations evaluate sufficient
    statistics in its eigenbasis (O(L d V)); value and gradient equal the dense form's, with
    the statistics built from PhaseData or from the dense ModelData."""
    demos = _demos(**CASES["shared"])
    compact = model_data(demos, NUM_BASIS)
    dense = dense_the_former_way(demos, NUM_BASIS)
    stats = model_inputs(name, collapsed, compact)
    assert isinstance(stats, SharedDesign)
    from_dense = shared_design(dense)
    np.testing.assert_allclose(np.sort(from_dense.eig), np.sort(stats.eig), atol=1e-12)
    _assert_same_density_and_gradient(model_function(name, collapsed), dense, (stats, from_dense), seed=3,
                                      rtol=1e-12, grad_rtol=1e-9)


STATISTICS_MODELS = [("lmpromp", "none"), ("lmpromp", "w"), ("lmpromp", "wh"), ("lmpromp", "whb"),
                     ("mixture", "w"), ("mixture", "wh"), ("promp", "w")]


@pytest.mark.parametrize("name, collapsed", STATISTICS_MODELS)
def test_per_demonstration_statistics_give_the_dense_density_and_gradient(name, collapsed):
    """Demonstrations of different lengths with a missing value: the declarations evaluate
    per-demonstration statistics (built from PhaseData without the dense design, or from the
    dense ModelData whose masked entry holds NaN); value and gradient equal the dense form's."""
    compact = model_data(_demos((6, 4, 5), seed=4), NUM_BASIS)
    observed = np.asarray(compact.observed).copy()
    observed[2, 1, 0] = 0.0
    compact = compact._replace(observed=jnp.asarray(observed))
    dense = compact.dense()
    with_nan = dense._replace(y=dense.y.at[2, 1 * 2 + 0].set(jnp.nan))
    stats = model_inputs(name, collapsed, compact)
    assert isinstance(stats, DemoStatistics)
    from_dense = demo_statistics(with_nan)
    for got, want in zip(stats, from_dense):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-13)
    _assert_same_density_and_gradient(model_function(name, collapsed), dense, (stats, from_dense), seed=5,
                                      rtol=1e-11, grad_rtol=1e-8)


def test_shared_design_only_where_every_demonstration_has_the_same_observed_design():
    ragged = model_data(_demos(**CASES["ragged"]), NUM_BASIS)
    assert shared_design(ragged) is None
    # designs that differ: per-demonstration statistics, except where the observation sites need the design
    assert isinstance(model_inputs("lmpromp", "wh", ragged), DemoStatistics)
    assert isinstance(model_inputs("mixture", "none", ragged), ModelData)
    assert isinstance(model_inputs("promp", "none", ragged), ModelData)
    shared = model_data(_demos(**CASES["shared"]), NUM_BASIS)
    observed = np.asarray(shared.observed).copy()
    observed[0, 1, 0] = 0.0  # one missing value breaks the shared design
    assert shared_design(shared._replace(observed=jnp.asarray(observed))) is None
    # the ProMP and the offset-collapsed LMProMP take the per-demonstration statistics
    assert isinstance(model_inputs("promp", "w", shared), DemoStatistics)
    assert isinstance(model_inputs("lmpromp", "whb", shared), DemoStatistics)
    with pytest.raises(LmprompError, match="needs their design"):
        handlers.seed(model_function("promp", "w"), 0)(model_inputs("promp", "w", ragged), HYPER, observed=False)
    # statistics cannot simulate demonstrations
    model = model_function("lmpromp", "wh")
    with pytest.raises(LmprompError, match="needs their design"):
        handlers.seed(model, 0)(shared_design(shared), HYPER, observed=False)


def test_phases_equal_up_to_rounding_share_one_basis():
    """Recordings whose clocks differ give phases that agree only to rounding (LASA: 2e-16);
    they share one basis matrix, and so the eigenbasis paths."""
    times = [np.arange(7) * step for step in (0.09389994, 0.11384475, 0.0731)]  # LASA's sample steps
    rng = np.random.default_rng(0)
    demos = Demonstrations(times, [rng.normal(size=(7, 2)) for _ in times])
    assert not all(np.array_equal(p, demos.phases()[0]) for p in demos.phases())
    compact = model_data(demos, NUM_BASIS)
    assert compact.phi.shape[0] == 1 and compact.shares_psi()
    assert isinstance(model_inputs("lmpromp", "wh", compact), SharedDesign)


def test_cavi_statistics_are_the_same_on_both_forms(pair):
    case, compact, dense = pair
    for shared in ([True, False] if case == "shared" else [False]):
        got = cavi.sufficient_statistics(compact, shared_psi=shared)
        want = cavi.sufficient_statistics(dense, shared_psi=shared)
        for name in ("psi_t_y", "y_sq", "num_obs"):
            np.testing.assert_allclose(getattr(got, name), getattr(want, name), rtol=1e-13, atol=1e-13)
        if shared:  # the eigenvectors may differ within repeated eigenvalues; the Gram matrix may not
            gram = [g.basis @ (g.eigvals[:, None] * g.basis.T) for g in (got.gram, want.gram)]
            np.testing.assert_allclose(gram[0], gram[1], atol=1e-12)
            np.testing.assert_allclose(got.gram.basis.T @ got.gram.basis, np.eye(compact.num_weights), atol=1e-12)
        else:
            np.testing.assert_allclose(got.gram.matrices, want.gram.matrices, atol=1e-13)


def test_a_missing_value_is_masked_alike_on_both_forms():
    demos = _demos((6, 4, 5), seed=2)
    compact = model_data(demos, NUM_BASIS)
    observed = np.asarray(compact.observed).copy()
    observed[1, 2, 1] = 0.0  # demonstration 1, time 2, DoF 1
    compact = compact._replace(observed=jnp.asarray(observed))
    dense = compact.dense()
    assert float(dense.mask[1, 2 * 2 + 1]) == 0.0
    got, want = cavi.sufficient_statistics(compact), cavi.sufficient_statistics(dense)
    np.testing.assert_allclose(got.num_obs, want.num_obs)
    np.testing.assert_allclose(got.psi_t_y, want.psi_t_y, atol=1e-13)
    np.testing.assert_allclose(got.gram.matrices, want.gram.matrices, atol=1e-13)


def test_compact_inputs_grow_as_L_T_D_not_as_the_dense_design():
    """L = 300 demonstrations of 120 samples, D = 7, J = 60: the dense design would take
    300 x 840 x 420 x 8 bytes = 847 MB; the compact inputs take what the data take."""
    L, T, D, J = 300, 120, 7, 60
    rng = np.random.default_rng(0)
    grid = np.linspace(0.0, 1.0, T)
    demos = Demonstrations([grid] * L, list(rng.normal(size=(L, T, D))))
    compact = model_data(demos, J)
    size = sum(np.asarray(a).nbytes for a in compact)
    assert size <= 2 * L * T * D * 8 + T * J * 8
    assert size < (L * T * D * D * J * 8) / 100
    assert compact.shares_psi()


def test_inconsistent_compact_inputs_are_refused():
    compact = model_data(_demos((6, 4, 5), seed=0), NUM_BASIS)
    with pytest.raises(DataError, match="inconsistent PhaseData"):
        cavi.sufficient_statistics(compact._replace(values=compact.values[:, :-1]))
    with pytest.raises(DataError, match="only 0 and 1"):
        cavi.sufficient_statistics(compact._replace(observed=compact.observed * 0.5))
    bad = np.asarray(compact.values).copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(DataError, match="NaN or inf"):
        cavi.sufficient_statistics(compact._replace(values=jnp.asarray(bad)))


@pytest.mark.filterwarnings("ignore::lmpromp_ppl.errors.ConvergenceWarning")  # a few steps, on purpose
def test_nuts_and_svi_never_build_the_dense_design_of_compact_inputs(monkeypatch):
    """On demonstrations of different lengths, NUTS (collapsed over w and h) and SVI (the autonormal
    and meanfield guides) run, draw and evaluate their k-hat ratios on the compact inputs and their
    statistics: a concrete dense design is never built (abstract traces may build an abstract one)."""
    from lmpromp_ppl.inference.nuts import fit_nuts
    from lmpromp_ppl.inference.svi import fit_svi

    compact = model_data(_demos((6, 4, 5), seed=6), NUM_BASIS)
    hyper = HYPER.replace(num_components=1, learn_beta=False)
    dense_view = PhaseData.dense

    def concrete_dense_refused(self):
        if not isinstance(self.phi, jax.core.Tracer):
            raise AssertionError("a concrete dense design was built")
        return dense_view(self)

    monkeypatch.setattr(PhaseData, "dense", concrete_dense_refused)
    with pytest.raises(AssertionError, match="concrete dense"):
        compact.dense()
    res = fit_nuts("lmpromp", compact, hyper, jax.random.key(0), num_chains=1, num_warmup=30, num_samples=20,
                   init="uniform")
    assert res.samples["w"].shape == (1, 20, 3, 2 * NUM_BASIS) and np.all(np.isfinite(res.samples["w"]))
    for guide in ("autonormal", "meanfield"):
        fit = fit_svi("lmpromp", compact, hyper, jax.random.key(1), guide=guide, num_steps=200, window=100,
                      stop_tol=0.0, prepare_draws=0)
        draws = fit.sample(jax.random.key(2), 5)
        assert draws["w"].shape == (5, 3, 2 * NUM_BASIS) and np.all(np.isfinite(draws["w"]))
        log_ratio, _ = fit.importance_log_ratios(jax.random.key(3), 50)
        assert np.all(np.isfinite(log_ratio))


@pytest.mark.filterwarnings("ignore::lmpromp_ppl.errors.ConvergenceWarning")
def test_svi_on_compact_inputs_follows_the_dense_fit():
    """The same SVI steps on the compact ragged inputs (statistics) and on their dense view: the
    loss of every step agrees to rounding (the two forms of the density are equal)."""
    from lmpromp_ppl.inference.svi import fit_svi

    compact = model_data(_demos((6, 4, 5), seed=7), NUM_BASIS)
    hyper = HYPER.replace(num_components=1)
    fits = [fit_svi("lmpromp", data, hyper, jax.random.key(4), guide="autonormal", num_steps=100, window=50,
                    stop_tol=0.0, prepare_draws=0) for data in (compact, compact.dense())]
    np.testing.assert_allclose(fits[0].loss_trace, fits[1].loss_trace, rtol=1e-8)

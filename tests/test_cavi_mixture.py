"""Proofs for the CAVI extensions (issue 5; docs/derivation.md, "Extensions").

For every combination of model (single type, mixture) x family of q(M)
(column-wise, row-wise) x beta (fixed, learned):

* monotone: the ELBO never decreases after any single factor update;
* stationary: after each update the autodiff gradient of the closed-form ELBO
  with respect to that factor's own parameters vanishes (responsibilities
  through logits, q(pi) through its concentration);
* same model as NumPyro: the closed-form ELBO equals a Monte Carlo estimate of
  E_q[log p - log q] with log p from the declared models (the mixture with
  explicit assignments z drawn from q(z), one component removed);

and further: the families agree at V = 1, the row-wise family's M update and
converged bound are never below the column-wise ones, the K = 1 engine equals
the single-type engine, the thesis's forms of four mixture updates are not
stationary, the mixture recovers and prunes synthetic clusters, and a learned
beta recovers the true noise precision.
"""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import numpyro.distributions as dist
import pytest
from numpyro.infer.util import log_density
from sklearn.metrics import adjusted_rand_score

from lmpromp_ppl.data import ModelData, load_dataset, model_data, standardise
from lmpromp_ppl.data.synthetic import GENERATOR_WIDTH, latent_manifold
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference import cavi
from lmpromp_ppl.inference import cavi as cm
from lmpromp_ppl.inference.cavi import init_mixture_state, init_state
from lmpromp_ppl.inference.cavi.posterior import _gamma_draws
from lmpromp_ppl.models.hyper import SIMULATION, Hyperparameters
from lmpromp_ppl.models.lmpromp import lmpromp_model
from lmpromp_ppl.models.mixture import mixture_model

L, V, K = 12, 2, 3
COMBOS = list(itertools.product(["single", "mixture"], ["columnwise", "rowwise"], [False, True]))
IDS = [f"{m}-{f}-{'learned' if b else 'fixed'}-beta" for m, f, b in COMBOS]


def _hyper(model: str, learn_beta: bool, base: Hyperparameters = Hyperparameters()) -> Hyperparameters:
    return base.replace(
        beta=100.0, latent_dim=V, num_components=K if model == "mixture" else 1, learn_beta=learn_beta
    )


@pytest.fixture(scope="module")
def small():
    """Four small clusters (L=12, d=6) with missing entries: the general (per-demonstration Gram) path."""
    demos, _ = standardise(load_dataset(f"synthetic:clusters?L={L}&T=12&radius=0.2&seed=3"))
    data = model_data(demos, 6, width=0.5)
    rng = np.random.default_rng(0)
    mask = (rng.uniform(size=data.mask.shape) > 0.15).astype(float)
    mask[0, 6:] = 0.0
    data = ModelData(data.psi, jnp.where(mask > 0, data.y, jnp.nan), jnp.asarray(mask))
    return data, cavi.sufficient_statistics(data)


def _start(model, family, learn_beta, cdata, hyper, key):
    if model == "mixture":
        return init_mixture_state(cdata, hyper, key, family=family)
    return init_state(cdata, hyper, key=key, family=family)  # q(beta) when hyper.learn_beta


def _perturb(state: cm.CaviState, seed: int) -> cm.CaviState:
    """An arbitrary valid state at which no factor is optimal."""
    rng = np.random.default_rng(seed)
    shift = lambda a, scale: a + scale * rng.standard_normal(a.shape)  # noqa: E731
    changes = dict(
        w_mean=shift(state.w_mean, 0.1),
        w_cov=cavi.FullCovariance(1.7 * state.w_cov.matrices),
        h_mean=shift(state.h_mean, 0.3),
        h_cov=0.6 * state.h_cov,
        b_mean=shift(state.b_mean, 0.1),
        b_var=3.0 * state.b_var,
        M_mean=shift(state.M_mean, 0.1),
        M_var=2.0 * state.M_var,
        alpha_shape=0.5 * state.alpha_shape,
        alpha_rate=0.7 * state.alpha_rate,
        lam_shape=1.3 * state.lam_shape,
        lam_rate=1.5 * state.lam_rate,
    )
    if state.M_var.ndim == 3:  # a full (non-diagonal) row covariance
        changes["M_var"] = 2.0 * state.M_var + 0.3 * jnp.sqrt(
            jnp.einsum("kuu,kvv->kuv", state.M_var, state.M_var)
        ) * (1.0 - jnp.eye(V))
    if state.resp is not None:
        logits = jnp.log(0.7 * state.resp + 0.1) + 0.5 * rng.standard_normal(state.resp.shape)
        changes["resp"] = jax.nn.softmax(logits, axis=1)
        changes["pi_conc"] = 1.3 * state.pi_conc + 0.5
    if bool(state.beta_learned):
        changes["beta_shape"] = 0.7 * state.beta_shape
        changes["beta_rate"] = 1.2 * state.beta_rate
    return state._replace(**changes)


@pytest.fixture(scope="module")
def starts(small):
    """The perturbed start of every combination (general path)."""
    _, cdata = small
    out = {}
    for model, family, learn_beta in COMBOS:
        hyper = _hyper(model, learn_beta)
        state = _start(model, family, learn_beta, cdata, hyper, jax.random.key(1))
        out[model, family, learn_beta] = _perturb(state, seed=2)
    return out


# --------------------------------------------------------------------------- compiled checks
FACTOR_FIELDS = {
    "w": ("w_mean", "w_cov"),
    "b": ("b_mean", "b_var"),
    "M": ("M_mean", "M_var"),
    "h": ("h_mean", "h_cov"),
    "lam": ("lam_shape", "lam_rate"),
    "alpha": ("alpha_shape", "alpha_rate"),
    "beta": ("beta_shape", "beta_rate"),
    "z": ("resp",),
    "pi": ("pi_conc",),
}


def _factor_norms(state, data, hyper):
    """ELBO and the norm of its gradient with respect to each factor of ``updates_for(state)``.

    The responsibilities enter through logits (``resp = softmax(logits)``), q(pi) through its concentration.
    """
    names = list(cm.updates_for(state))
    fields = [f for name in names for f in FACTOR_FIELDS[name]]
    params = {f: getattr(state, f) for f in fields}
    if "resp" in params:
        params["resp"] = jnp.log(params["resp"])

    def objective(p):
        p = dict(p)
        if "resp" in p:
            p["resp"] = jax.nn.softmax(p["resp"], axis=1)
        return cm.elbo(state._replace(**p), data, hyper)

    value, grad = jax.value_and_grad(objective)(params)
    norms = [
        jnp.sqrt(sum(jnp.sum(g**2) for f in FACTOR_FIELDS[name] for g in jax.tree.leaves(grad[f])))
        for name in names
    ]
    return value, jnp.stack(norms)


@jax.jit
def _sweep_check(state, data, hyper):
    """One sweep, one factor at a time: ELBOs (n+1,), gradient norms of factor j before/after its update."""
    updates = list(cm.updates_for(state).values())
    branches = [lambda s, u=u: u(s, data, hyper) for u in updates]
    value, norms = _factor_norms(state, data, hyper)

    def one(carry, index):
        state, norms = carry
        state = jax.lax.switch(index, branches, state)
        value, new_norms = _factor_norms(state, data, hyper)
        return (state, new_norms), (value, norms[index], new_norms[index])

    (state, _), (values, before, after) = jax.lax.scan(one, (state, norms), jnp.arange(len(updates)))
    return state, jnp.concatenate([value[None], values]), before, after


@pytest.fixture(scope="module")
def sweeps(small, starts):
    """Six sweeps of single-factor updates from every perturbed start."""
    _, cdata = small
    out = {}
    for combo, state in starts.items():
        hyper = cm.hyper_arrays(_hyper(combo[0], combo[2]))
        records = []
        for _ in range(6):
            state, values, before, after = _sweep_check(state, cdata, hyper)
            records.append(tuple(np.asarray(x) for x in (values, before, after)))
        out[combo] = (list(cm.updates_for(state)), records)
    return out


def test_fixed_and_learned_beta_share_compiled_code(starts):
    """Whether beta is learned is an array, not pytree structure: one compiled sweep serves both."""
    for model, family in itertools.product(["single", "mixture"], cm.FAMILIES):
        fixed, learned = starts[model, family, False], starts[model, family, True]
        assert jax.tree.structure(fixed) == jax.tree.structure(learned)
        assert [x.shape for x in jax.tree.leaves(fixed)] == [x.shape for x in jax.tree.leaves(learned)]


@pytest.mark.parametrize("combo", COMBOS, ids=IDS)
def test_elbo_never_decreases_after_any_factor_update(sweeps, combo):
    names, records = sweeps[combo]
    assert ("z" in names) == ("pi" in names) == (combo[0] == "mixture")
    for values, _, _ in records:
        assert np.all(np.isfinite(values))
        change = np.diff(values)
        assert np.all(change >= -1e-10 * np.abs(values[:-1])), (combo, dict(zip(names, change)))
    assert records[0][0][-1] > records[0][0][0]  # not vacuous: the bound moved


@pytest.mark.parametrize("combo", COMBOS, ids=IDS)
def test_each_update_is_stationary_by_autodiff(sweeps, combo):
    names, records = sweeps[combo]
    for sweep, (values, before, after) in enumerate(records):
        for j, name in enumerate(names):
            tol = 1e-6 * before[j] + 1e-9 * (1.0 + abs(values[j + 1]))
            assert after[j] <= tol, (combo, sweep, name, before[j], after[j])
    # not vacuous: in the first sweep every factor was far from stationary before its update
    # (with a fixed beta the beta "update" is a no-op and the bound does not depend on q(beta))
    checked = [j for j, name in enumerate(names) if name != "beta" or combo[2]]
    assert np.all(records[0][1][checked] > 1e-3), dict(zip(names, records[0][1]))
    if not combo[2]:
        assert records[0][1][names.index("beta")] == 0.0


# --------------------------------------------------------------------------- same model as NumPyro
NUM_DRAWS = 10000


def _mask_last_component(state: cm.CaviState, hyper: Hyperparameters) -> cm.CaviState:
    """Remove component K-1 as :func:`cm.prune` would (responsibilities renormalised, q(pi) updated)."""
    active = jnp.arange(K) < K - 1
    resp = jnp.where(active[None], state.resp, 0.0)
    resp = resp / resp.sum(axis=1, keepdims=True)
    return state._replace(active=active, resp=resp, pi_conc=hyper.kappa0 + resp.sum(axis=0))


@jax.jit
def _log_q(state: cm.CaviState, draws: dict) -> jax.Array:
    """log q of each draw (the library's :func:`cm.log_q`, used for k-hat; checked here by the bound)."""
    return cm.log_q(state, draws)


def _prior_draws(key, hyper):
    """Prior draws of every component's parameters and their log prior.

    The Gamma draws reuse the compiled sampler of ``sample_q`` for the mixture
    (K + K V + 1 + K shapes; the last K + 1 are padding).
    """
    k_g, key = jax.random.split(key)
    shapes = jnp.concatenate([jnp.full(K * V, hyper.c0), jnp.full(K, hyper.a0), jnp.ones(K + 1)])
    return _prior_rest(key, _gamma_draws(k_g, shapes, NUM_DRAWS), hyper)


@jax.jit
def _prior_rest(key, gammas, hyper):
    n, d = NUM_DRAWS, 6
    k_M, k_b, k_h = jax.random.split(key, 3)
    lam = gammas[:, : K * V].reshape(n, K, V) / hyper.d0
    alpha = gammas[:, K * V : K * V + K] / hyper.b0
    M = jax.random.normal(k_M, (n, K, d, V)) / jnp.sqrt(lam)[:, :, None, :]
    b = jax.random.normal(k_b, (n, K, d)) / jnp.sqrt(hyper.lambda0)
    h = jax.random.normal(k_h, (n, L, K, V)) / jnp.sqrt(hyper.gamma)
    log_prior = (
        dist.Gamma(hyper.c0, hyper.d0).log_prob(lam).sum(-1)
        + dist.Normal(0.0, 1.0 / jnp.sqrt(lam)[:, :, None, :]).log_prob(M).sum((-2, -1))
        + dist.Normal(0.0, hyper.lambda0**-0.5).log_prob(b).sum(-1)
        + dist.Gamma(hyper.a0, hyper.b0).log_prob(alpha)
        + dist.Normal(0.0, hyper.gamma**-0.5).log_prob(h).sum((1, 3))
    )
    return {"lam": lam, "M": M, "b": b, "alpha": alpha, "h": h}, log_prior


def _prior_draws_of_removed(key, draws, state, hyper):
    """Replace the removed components' draws by prior draws; return them with their log prior."""
    prior, log_prior = _prior_draws(key, hyper)
    removed = ~state.active
    draws = dict(draws)
    for name in ("lam", "M", "b", "alpha"):
        draws[name] = jnp.where(removed.reshape((K,) + (1,) * (prior[name].ndim - 2)), prior[name], draws[name])
    draws["h"] = jnp.where(removed[:, None], prior["h"], draws["h"])
    return draws, jnp.where(removed, log_prior, 0.0).sum(-1)


def _c2_dropped_terms(state: cm.CaviState, hyper: cm.CaviHyper) -> float:
    """What App. C.1 / C.2 drop: the factor (d - 1) on Sigma_M in E log p(w) and (d/2) sum E log lam."""
    st = cm.expected_stats(state, hyper, logs=True)
    d = state.w_mean.shape[1]
    M_cov = state.M_var if state.M_var.ndim == 3 else jax.vmap(jnp.diag)(state.M_var)
    sigma_terms = jnp.einsum("ik,k,kuv,ikvu->", st.resp, st.alpha_mean, M_cov, st.hhT)
    log_lam = jnp.sum(jnp.where(state.active[:, None], st.log_lam_mean, 0.0))
    return float(-0.5 * (d - 1) * sigma_terms + 0.5 * d * log_lam)


_LOG_P = {}


def _log_p(model: str, hyper: Hyperparameters, data: ModelData, draws: dict) -> np.ndarray:
    """Log joint of the declared NumPyro model at each draw (compiled once per model variant)."""
    key = (model, hyper.learn_beta)
    if key not in _LOG_P:
        if model == "mixture":
            fn = lambda p, data: log_density(mixture_model, (data, hyper, False), {}, p)[0]  # noqa: E731
        else:
            fn = lambda p, data: log_density(lmpromp_model, (data, hyper), {}, p)[0]  # noqa: E731
        _LOG_P[key] = jax.jit(jax.vmap(fn, in_axes=(0, None)))
    return np.asarray(_LOG_P[key](draws, data))


@pytest.mark.parametrize("combo", COMBOS, ids=IDS)
def test_closed_form_elbo_matches_numpyro_monte_carlo(small, combo):
    """At a perturbed state (mixture: component K-1 removed) the bound equals E_q[log p - log q]."""
    model, family, learn_beta = combo
    data, cdata = small
    hyper = _hyper(model, learn_beta, SIMULATION)  # proper priors: prior draws of removed components stay finite
    state = _perturb(_start(model, family, learn_beta, cdata, hyper, jax.random.key(4)), seed=5)
    if model == "mixture":
        state = _mask_last_component(state, hyper)
    closed = float(cm.elbo(state, cdata, cm.hyper_arrays(hyper)))
    k_q, k_pi, k_removed = jax.random.split(jax.random.key(6), 3)
    draws = cm.sample_q(k_q, state, NUM_DRAWS)
    extra = 0.0
    if model == "mixture":
        assert draws["z"].shape == (NUM_DRAWS, L) and int(draws["z"].max()) < K - 1  # z from q(z)
        draws["pi"] = dist.Dirichlet(state.pi_conc).sample(k_pi, (NUM_DRAWS,))  # q(pi) over all K
        draws, extra = _prior_draws_of_removed(k_removed, draws, state, cm.hyper_arrays(hyper))
    values = _log_p(model, hyper, data, draws) - np.asarray(_log_q(state, draws) + extra)
    mean, standard_error = values.mean(), values.std(ddof=1) / np.sqrt(NUM_DRAWS)
    assert abs(closed - mean) <= 4.0 * standard_error, (closed, mean, standard_error)
    # the test has the resolution to see an error of the thesis's bound: for the single type the
    # non-constant terms C.1 drops; for the mixture C.2's sign slip on E log q(z) (2 H[q(z)])
    if model == "single":
        assert 4.0 * standard_error < abs(_c2_dropped_terms(state, cm.hyper_arrays(hyper)))
    else:
        entropy_z = -float(jnp.sum(jnp.where(state.resp > 0, state.resp * jnp.log(state.resp), 0.0)))
        assert 4.0 * standard_error < 2.0 * entropy_z


# --------------------------------------------------------------------------- families
def test_rowwise_M_update_never_below_columnwise(small, starts):
    """The row-wise family contains the column-wise one: its optimal q(M) gives at least the same bound."""
    _, cdata = small
    for (model, family, learn_beta), state in starts.items():
        if family != "rowwise":
            continue
        hyper = cm.hyper_arrays(_hyper(model, learn_beta))
        diagonal = state._replace(M_var=jnp.diagonal(state.M_var, axis1=-2, axis2=-1))
        row = float(cm.elbo(cm.update_M(state, cdata, hyper), cdata, hyper))
        col = float(cm.elbo(cm.update_M(diagonal, cdata, hyper), cdata, hyper))
        assert row >= col - 1e-10 * abs(col), (model, learn_beta, row, col)
        assert row > col + 1e-6  # strictly better here: the optimal row covariance is not diagonal


def test_families_coincide_at_V_equal_1(small):
    """At V = 1 a (1 x 1) row covariance is a column variance: same q(M) update, same bound."""
    _, cdata = small
    hyper = Hyperparameters(beta=100.0, latent_dim=1)
    hyper_arr = cm.hyper_arrays(hyper)
    column = _perturb(init_state(cdata, hyper, key=jax.random.key(7)), seed=8)
    row = column._replace(M_var=column.M_var[..., None])
    assert float(cm.elbo(row, cdata, hyper_arr)) == pytest.approx(float(cm.elbo(column, cdata, hyper_arr)), rel=1e-12)
    column, row = cm.update_M(column, cdata, hyper_arr), cm.update_M(row, cdata, hyper_arr)
    np.testing.assert_allclose(row.M_mean, column.M_mean, rtol=1e-12)
    np.testing.assert_allclose(row.M_var[..., 0], column.M_var, rtol=1e-12)
    assert float(cm.elbo(row, cdata, hyper_arr)) == pytest.approx(float(cm.elbo(column, cdata, hyper_arr)), rel=1e-12)


def test_diagonal_row_covariance_is_the_columnwise_distribution(starts, small):
    """The column-wise family is the row-wise one with a diagonal covariance: equal bounds."""
    _, cdata = small
    for (model, family, learn_beta), column in starts.items():
        if family != "columnwise":
            continue
        hyper = cm.hyper_arrays(_hyper(model, learn_beta))
        row = column._replace(M_var=jax.vmap(jnp.diag)(column.M_var))
        assert float(cm.elbo(row, cdata, hyper)) == pytest.approx(float(cm.elbo(column, cdata, hyper)), rel=1e-12)


@pytest.fixture(scope="module")
def clusters():
    demos = load_dataset("synthetic:clusters")
    labels = np.asarray(demos.labels).astype(int)
    demos, _ = standardise(demos)
    return model_data(demos, 8, width=GENERATOR_WIDTH), labels  # the generator's basis


@pytest.fixture(scope="module")
def cluster_fits(clusters):
    """K = 6 on the four clusters, both families from the same start (same k-means key)."""
    data, _ = clusters
    hyper = Hyperparameters(latent_dim=2, num_components=6)
    return {
        family: cavi.fit(data, hyper, jax.random.key(0), mixture=True, family=family, tol=1e-10)
        for family in cm.FAMILIES
    }


def test_rowwise_converged_bound_not_below_columnwise(cluster_fits):
    """Same data, same start: the larger family converges to a bound at least as high.

    Both runs stop when the relative change per sweep is below 1e-10; the comparison
    allows 1e-8 relative for the distance still left to each fixed point.  (Not a
    theorem for local optima; the exact per-update statement is
    ``test_rowwise_M_update_never_below_columnwise``.)
    """
    fits = cluster_fits
    assert all(fit.converged for fit in fits.values())
    assert fits["rowwise"].elbo >= fits["columnwise"].elbo - 1e-8 * abs(fits["columnwise"].elbo)


# --------------------------------------------------------------------------- engines agree
def test_one_component_mixture_equals_single_type(small):
    """A mixture state with K = 1 (q(z) and q(pi) present) has the single type's bound and sweeps.

    With one component the terms in z and pi vanish (E log pi = 0, r log r = 0, the Dirichlet
    terms cancel), so the mixture's updates of z and pi change nothing the bound sees.
    """
    data, cdata = small
    hyper = Hyperparameters(beta=100.0, latent_dim=V)
    single = init_state(cdata, hyper, key=jax.random.key(8))
    as_mixture = single._replace(resp=jnp.ones((L, 1)), pi_conc=jnp.asarray([hyper.kappa0 + L]))
    hyper_arr = cm.hyper_arrays(hyper)
    assert list(cm.updates_for(as_mixture)) == list(cm.updates_for(single)) + ["z", "pi"]
    assert float(cm.elbo(as_mixture, cdata, hyper_arr)) == pytest.approx(
        float(cm.elbo(single, cdata, hyper_arr)), rel=1e-12
    )
    for _ in range(10):
        single, info_single = cm.step(single, cdata, hyper_arr)
        as_mixture, info_mixture = cm.step(as_mixture, cdata, hyper_arr)
        assert float(info_mixture.elbo) == pytest.approx(float(info_single.elbo), rel=1e-10)


# --------------------------------------------------------------------------- thesis errata (Sec. 4.2.1, B.2)
def _thesis_h(state, data, hyper):
    """Sec. 4.2.1 / B.2: the update of every h_ik sums over all components."""
    st = cm.expected_stats(state, hyper)
    weights = st.resp * st.alpha_mean[None]  # (L, K)
    precision = jnp.einsum("ik,kuv->iuv", weights, st.MtM) + hyper.gamma * jnp.eye(V)
    offset = state.w_mean[:, None, :] - state.b_mean[None]
    linear = jnp.einsum("ik,kdv,ikd->iv", weights, state.M_mean, offset)
    cov = jnp.linalg.inv(precision)
    mean = jnp.einsum("iuv,iv->iu", cov, linear)
    return state._replace(
        h_mean=jnp.broadcast_to(mean[:, None], state.h_mean.shape),
        h_cov=jnp.broadcast_to(cov[:, None], state.h_cov.shape),
    )


def _thesis_alpha(state, data, hyper):
    """Final b_bar_k of Sec. 4.2.1 / B.2: the residuals are summed without the responsibilities."""
    st = cm.expected_stats(state, hyper)
    updated = cm.update_alpha(state, data, hyper)
    return updated._replace(alpha_rate=hyper.b0 + 0.5 * jnp.sum(st.residual_sq, axis=0))


def _thesis_z(state, data, hyper):
    """rho_k of Sec. 4.2.1: a_bar_k / 2 in place of alpha_bar_k / 2."""
    d = state.w_mean.shape[1]
    st = cm.expected_stats(state, hyper, logs=True)
    logits = st.log_pi_mean + 0.5 * d * st.log_alpha_mean - 0.5 * state.alpha_shape * st.residual_sq
    return state._replace(resp=jax.nn.softmax(logits, axis=1))


def _thesis_Q(state, data, hyper):
    """b_bar_k with Sec. 4.2.1's Q = (M^T d M + Sigma_M) Sigma_h (the factor d misplaced)."""
    d = state.w_mean.shape[1]
    st = cm.expected_stats(state, hyper)
    M_cov = jax.vmap(jnp.diag)(state.M_var)
    thesis_MtM = d * jnp.einsum("kdu,kdv->kuv", state.M_mean, state.M_mean) + M_cov
    correction = jnp.einsum("kuv,ikvu->ik", thesis_MtM - st.MtM, state.h_cov)
    updated = cm.update_alpha(state, data, hyper)
    return updated._replace(alpha_rate=updated.alpha_rate + 0.5 * jnp.sum(st.resp * correction, axis=0))


_norms_jit = jax.jit(_factor_norms)


@pytest.mark.parametrize(
    "factor, thesis_update",
    [("h", _thesis_h), ("alpha", _thesis_alpha), ("z", _thesis_z), ("alpha", _thesis_Q)],
    ids=["h-sum-over-k", "alpha-without-r", "z-a-bar-over-2", "alpha-Q-misplaced-d"],
)
def test_thesis_mixture_updates_are_not_stationary(small, starts, factor, thesis_update):
    _, cdata = small
    state = starts["mixture", "columnwise", False]
    hyper = cm.hyper_arrays(_hyper("mixture", False))
    index = list(cm.updates_for(state)).index(factor)
    _, before = _norms_jit(state, cdata, hyper)
    value, after = _norms_jit(thesis_update(state, cdata, hyper), cdata, hyper)
    tolerance = 1e-6 * float(before[index]) + 1e-9 * (1 + abs(float(value)))
    assert float(after[index]) > 10.0 * tolerance, (float(before[index]), float(after[index]))
    # the corrected update passes the same test from the same state
    _, corrected = _norms_jit(cm.updates_for(state)[factor](state, cdata, hyper), cdata, hyper)
    assert float(corrected[index]) <= tolerance


# --------------------------------------------------------------------------- recovery
def test_mixture_recovers_and_prunes_clusters(clusters, cluster_fits):
    """Started with K = 6 on four well-separated clusters: four components survive, ARI >= 0.9.

    The cluster centres are 2.1 apart in the plane against a within-cluster spread of
    0.3 (7 standard deviations), so a correct fit misassigns no demonstration; the
    bound 0.9 allows one or two.
    """
    data, labels = clusters
    fit = cluster_fits["columnwise"]
    assert fit.converged
    active = cavi.active_components(fit.state)
    assert len(active) == 4, active
    resp = cm.responsibilities(fit.state)
    assert adjusted_rand_score(labels, resp.argmax(axis=1)) >= 0.9
    dims = cavi.active_latent_dims(fit.state)
    # removed components report no latent dimension; within these clusters ARD switches
    # the columns off (E[lam] ~ 1200, E[m] ~ 0: the spread is absorbed by 1/alpha), and the
    # ARD rule says so rather than reporting each component's largest column
    assert len(dims) == 6 and all(not dims[k] for k in range(6) if k not in active)
    point = cavi.point_estimate(fit.state)
    np.testing.assert_allclose(float(point["pi"].sum()), 1.0, rtol=1e-12)
    assert np.all(np.asarray(point["pi"])[[k for k in range(6) if k not in active]] == 0.0)
    draws = cavi.sample_q(jax.random.key(1), fit.state, 5)
    d = data.psi.shape[2]
    shapes = {"pi": (5, 6), "b": (5, 6, d), "M": (5, 6, d, 2), "lam": (5, 6, 2), "alpha": (5, 6),
              "h": (5, 40, 6, 2), "w": (5, 40, d), "z": (5, 40)}
    assert {k: v.shape for k, v in draws.items()} == shapes
    assert set(np.unique(np.asarray(draws["z"]))) <= set(active)


def test_learned_beta_recovers_noise_precision():
    """L=20 demonstrations of 2 x 50 observations (n = 2000) with beta = 400.

    About n - L d = 1600 residual degrees of freedom give the precision a relative
    standard deviation sqrt(2 / 1600) = 3.5 %; we allow 4 of them (14 %).
    """
    demos = latent_manifold(L=20, D=2, J=10, V=2, T=50, beta=400.0, seed=0)
    data = model_data(demos, 10)  # not standardised: the noise keeps precision 400
    hyper = Hyperparameters(beta=100.0, latent_dim=2, learn_beta=True)
    # the noise split between alpha and beta converges slowly; 1e-6 moves beta by far less than 1 %
    fit = cavi.fit(data, hyper, jax.random.key(0), family="rowwise", tol=1e-6)
    assert isinstance(fit.state, cm.CaviState) and fit.converged
    beta = float(cavi.point_estimate(fit.state)["beta"])
    assert abs(beta / 400.0 - 1.0) < 0.14, beta
    draws = cavi.sample_q(jax.random.key(0), fit.state, 3)
    assert {k: v.shape for k, v in draws.items()} == {
        "b": (3, 20), "M": (3, 20, 2), "h": (3, 20, 2), "w": (3, 20, 20),
        "alpha": (3,), "lam": (3, 2), "beta": (3,),
    }
    assert isinstance(cavi.active_latent_dims(fit.state)[0], int)


# --------------------------------------------------------------------------- engineering
def test_invalid_options_are_refused(small):
    data, _ = small
    with pytest.raises(LmprompError, match="family"):
        cavi.fit(data, Hyperparameters(latent_dim=V), jax.random.key(0), family="diagonal")
    with pytest.raises(LmprompError, match="more mixture components"):
        cavi.fit(data, Hyperparameters(latent_dim=V, num_components=L + 1), jax.random.key(0), mixture=True)
    with pytest.raises(LmprompError, match="prune_threshold"):
        cavi.fit(data, _hyper("mixture", False), jax.random.key(0), mixture=True, prune_threshold=-1.0)

r"""Simulation-based calibration (SBC) of the inference engines.

Talts et al. (2018), Algorithm 1: draw :math:`\tilde\theta \sim p(\theta)`,
simulate :math:`\tilde y \sim p(y \mid \tilde\theta)`, fit, draw
:math:`\theta_1, \dots, \theta_N` from the (approximate) posterior and record
the rank :math:`r = \#\{n : f(\theta_n) < f(\tilde\theta)\}` of each scalar
:math:`f`.  For an exact posterior, :math:`r` is uniform on
:math:`\{0, \dots, N\}` whatever :math:`f` (the data-averaged posterior equals
the prior), so the jittered PIT value :math:`u = (r + U)/(N + 1)`,
:math:`U \sim \mathcal U(0, 1)`, is uniform on (0, 1).

The scalars are identifiable quantities (thesis Sec. 4.1: M and h are
determined only up to a rotation of the latent space, eq. 4.1):

* LMProMP: ``alpha``, the components of ``b``, the eigenvalues ``gram_eig`` of
  :math:`M M^T` (descending) and the mean ``pred_mean`` and s.d. ``pred_sd``
  of the movement distribution of a new demonstration at fixed phases
  (:func:`lmpromp_ppl.quantities.trajectory_moments`);
* ProMP: the components of ``mu_w``, ``pred_mean`` and ``pred_sd``.

Datasets are simulated from the model with the SIMULATION hyperparameters
(:data:`lmpromp_ppl.models.hyper.SIMULATION`; the PROPER and THESIS Gamma
priors are not simulable, :func:`lmpromp_ppl.models.prior.check_simulable`),
and every engine is fitted with the same hyperparameters, so that an exact
engine is calibrated in theory.  Replicate ``i`` is simulated from
``fold_in(key(seed), i)``: every engine sees the same datasets, and a
replicate can be recomputed on its own (a task of :mod:`.runner`).

Uniformity of the PIT values of each (engine, quantity, component) is tested
with arviz-stats' ``uniformity_test`` (the ``pot_c`` test behind
arviz-plots' ``plot_ecdf_pit``); :func:`summarize` also reports the coverage
of central 50 % and 90 % posterior intervals and the VSBC symmetry test
(:mod:`.vsbc`).

References
----------
Talts, S., Betancourt, M., Simpson, D., Vehtari, A. and Gelman, A. (2018).
Validating Bayesian inference algorithms with simulation-based calibration.
arXiv:1804.06788.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from lmpromp_ppl.basis import design_matrix
from lmpromp_ppl.calibration.vsbc import vsbc_probabilities, vsbc_test
from lmpromp_ppl.data.core import ModelData
from lmpromp_ppl.quantities import gram_eigenvalues, trajectory_moments
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference import registry
from lmpromp_ppl.models.hyper import Hyperparameters, preset

__all__ = [
    "ENGINES",
    "MODEL_ENGINES",
    "DEFAULT_ENGINES",
    "SbcProblem",
    "design",
    "simulate_replicate",
    "sbc_quantities",
    "rank_statistics",
    "pit_values",
    "uniformity_pvalues",
    "fit_draws",
    "sbc_task",
    "sbc_tasks",
    "collect",
    "summarize",
]

#: The engines SBC runs (every engine of :mod:`lmpromp_ppl.inference.registry`).
ENGINES = registry.ENGINES
#: The simulated problems' models and the engines offered for each (the registry's pairs).
MODEL_ENGINES = {model: registry.engines_for(model) for model in ("lmpromp", "promp")}
#: Fixed per-engine stream numbers of the replicates' keys (independent of the order of ENGINES).
_KEY_STREAM = {"cavi": 0, "nuts": 1, "svi_meanfield": 2, "svi_autonormal": 3, "svi_lowrank": 4, "cavi_lr": 5}
#: The engines whose replicates are fitted together in one vmapped program.
BATCHED_ENGINES = ("cavi", "cavi_lr")

DEFAULT_ENGINES = {
    "lmpromp": ("cavi", "cavi_lr", "nuts", "svi_meanfield"),
    "promp": ("nuts", "svi_autonormal"),
}


@dataclass(frozen=True)
class SbcProblem:
    """The simulated problem: a fixed design, the SIMULATION prior, and the SBC sizes.

    Attributes
    ----------
    model : ``"lmpromp"`` or ``"promp"``
    num_demos : L demonstrations per dataset
    num_dofs : D degrees of freedom
    num_basis : J basis functions per DoF (d = D J weights)
    num_steps : T equally spaced phases in [0, 1] per demonstration
    latent_dim : V
    beta : observation precision (fixed, known to every engine)
    phases : phases at which ``pred_mean`` and ``pred_sd`` are ranked
    num_draws : N posterior draws per replicate (ranks lie in 0..N)
    """

    model: str = "lmpromp"
    num_demos: int = 8
    num_dofs: int = 1
    num_basis: int = 5
    num_steps: int = 20
    latent_dim: int = 2
    beta: float = 100.0
    phases: tuple[float, ...] = (0.25, 0.5, 0.75)
    num_draws: int = 99

    def __post_init__(self):
        if self.model not in MODEL_ENGINES:
            raise LmprompError(f"SBC supports models {sorted(MODEL_ENGINES)}, got {self.model!r}")
        for name in ("num_demos", "num_dofs", "num_basis", "num_steps", "latent_dim", "num_draws"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value < 1:
                raise LmprompError(f"{name} must be a positive integer, got {value!r}")
        if self.num_basis < 2:
            raise LmprompError(f"num_basis must be at least 2, got {self.num_basis}")
        phases = tuple(float(p) for p in self.phases)
        if not phases or not all(0.0 <= p <= 1.0 for p in phases):
            raise LmprompError(f"phases must be a non-empty list of values in [0, 1], got {self.phases!r}")
        object.__setattr__(self, "phases", phases)
        self.hyper()  # validates beta and V against d and L

    def hyper(self) -> Hyperparameters:
        """SIMULATION hyperparameters with this problem's V and beta."""
        hyper = preset("simulation", latent_dim=self.latent_dim, beta=self.beta)
        return hyper.validate_for(self.num_dofs * self.num_basis, self.num_demos)

    def to_dict(self) -> dict:
        return {**dataclasses.asdict(self), "phases": list(self.phases)}

    @classmethod
    def from_dict(cls, d: Mapping) -> "SbcProblem":
        return cls(**{**d, "phases": tuple(d.get("phases", cls.phases))})


def design(problem: SbcProblem) -> ModelData:
    """The shared design: every demonstration observed at ``num_steps`` equally spaced phases; y = 0."""
    psi = np.asarray(design_matrix(np.linspace(0.0, 1.0, problem.num_steps), problem.num_dofs, problem.num_basis))
    L, S = problem.num_demos, psi.shape[0]
    return ModelData(jnp.asarray(np.broadcast_to(psi, (L,) + psi.shape)), jnp.zeros((L, S)), jnp.ones((L, S)))


def simulate_replicate(problem: SbcProblem, seed: int, index: int) -> tuple[dict[str, np.ndarray], ModelData]:
    """Prior draw and simulated dataset of replicate ``index`` (:func:`lmpromp_ppl.models.prior.sample_prior_predictive`).

    Returns
    -------
    truth : site name -> value of the prior draw (no leading axis)
    data : the design with ``y`` replaced by the simulated observations
    """
    from lmpromp_ppl.models.prior import sample_prior_predictive

    key = jax.random.fold_in(jax.random.key(int(seed)), int(index))
    empty = design(problem)
    draws = sample_prior_predictive(problem.model, key, empty, problem.hyper(), 1)
    truth = {name: np.asarray(value[0]) for name, value in draws.items() if name != "y"}
    return truth, empty._replace(y=draws["y"][0])


def sbc_quantities(problem: SbcProblem, draws: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Identifiable scalars of draws with leading sample dims: name -> (..., k).

    ``alpha`` (k = 1), ``b`` (d), ``gram_eig`` (V) for the LMProMP, ``mu_w`` (d)
    for the ProMP, and ``pred_mean``, ``pred_sd`` (phases x DoFs, phase-major)
    for both, in standardised units (module docstring).
    """
    moments = trajectory_moments(
        problem.model, dict(draws), num_dofs=problem.num_dofs, num_basis=problem.num_basis,
        gamma=problem.hyper().gamma, phase=np.asarray(problem.phases),
    )
    lead = moments[0].shape[:-2]
    out: dict[str, np.ndarray] = {}
    if problem.model == "lmpromp":
        out["alpha"] = np.asarray(draws["alpha"], dtype=float).reshape(lead + (1,))
        out["b"] = np.asarray(draws["b"], dtype=float)
        out["gram_eig"] = gram_eigenvalues(draws["M"])
    else:
        out["mu_w"] = np.asarray(draws["mu_w"], dtype=float)
    out["pred_mean"] = moments[0].reshape(lead + (-1,))
    out["pred_sd"] = moments[1].reshape(lead + (-1,))
    return out


def rank_statistics(truth: np.ndarray, draws: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Rank of ``truth`` (k,) among ``draws`` (N, k): #draws below it, ties broken uniformly at random."""
    truth, draws = np.asarray(truth, dtype=float), np.asarray(draws, dtype=float)
    if draws.ndim != 2 or truth.shape != draws.shape[1:]:
        raise LmprompError(f"draws must be (N, k) and truth (k,), got {draws.shape} and {truth.shape}")
    below = np.sum(draws < truth, axis=0)
    ties = np.sum(draws == truth, axis=0)
    return below + rng.integers(0, ties + 1)


def pit_values(ranks: np.ndarray, num_draws: int, rng: np.random.Generator) -> np.ndarray:
    """Jittered PIT values :math:`(r + U)/(N + 1)`, uniform on (0, 1) for an exact posterior."""
    ranks = np.asarray(ranks, dtype=float)
    if np.any(ranks < 0) or np.any(ranks > num_draws):
        raise LmprompError(f"ranks must lie in 0..{num_draws}")
    return (ranks + rng.uniform(size=ranks.shape)) / (num_draws + 1)


def uniformity_pvalues(pit: np.ndarray) -> np.ndarray:
    """arviz-stats ``uniformity_test`` (``pot_c``) p-value of each column of ``pit`` (R, k) -> (k,)."""
    from arviz_stats.base import array_stats

    pit = np.asarray(pit, dtype=float)
    if pit.ndim != 2 or pit.shape[0] < 2:
        raise LmprompError(f"pit must be (replicates >= 2, k), got {pit.shape}")
    p_value, _, _ = array_stats.uniformity_test(pit.T, axis=-1, method="pot_c")
    return np.atleast_1d(np.asarray(p_value, dtype=float))


# --------------------------------------------------------------------------- fitting one replicate
def _thin(samples: Mapping[str, np.ndarray], num_draws: int) -> dict[str, np.ndarray]:
    """Flatten (chain, draw) and keep ``num_draws`` evenly spaced draws (less autocorrelation)."""
    flat = {k: np.asarray(v).reshape((-1,) + np.shape(v)[2:]) for k, v in samples.items()}
    total = next(iter(flat.values())).shape[0]
    if total < num_draws:
        raise LmprompError(f"NUTS kept {total} draws, fewer than num_draws={num_draws}")
    keep = np.linspace(0, total - 1, num_draws).round().astype(int)
    return {k: v[keep] for k, v in flat.items()}


def fit_draws(
    engine: str, problem: SbcProblem, data: ModelData, key: jax.Array, options: Mapping[str, Any] | None = None
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Fit one dataset with one engine and return ``num_draws`` posterior draws and diagnostics.

    Parameters
    ----------
    engine : ``"nuts"`` or an SVI engine (``svi_meanfield``, ``svi_autonormal``,
        ``svi_lowrank``); CAVI runs batched in :func:`sbc_task`
    problem, data : the problem and one simulated dataset
    key : PRNG key of the fit and of the draws
    options : engine options passed to :func:`~lmpromp_ppl.inference.nuts.fit_nuts`
        or :func:`~lmpromp_ppl.inference.svi.fit_svi`

    Returns
    -------
    draws : site -> (num_draws, ...)
    info : ``seconds``, ``converged`` and engine diagnostics (NUTS divergences)
    """
    from lmpromp_ppl.errors import ConvergenceWarning

    options = dict(options or {})
    hyper = problem.hyper()
    fit_key, draw_key = jax.random.split(key)
    start = time.perf_counter()
    if engine == "nuts":
        options = {"num_chains": 2, "num_warmup": 300, "num_samples": 300, **options}
        result = registry.run_engine(engine, problem.model, data, hyper, fit_key, **options)
        draws = _thin(result.samples, problem.num_draws)
        info = {"divergences": int(np.sum(result.sample_stats["diverging"])), "converged": True}
    elif engine in registry.SVI_ENGINES:
        options = {"num_steps": 10000, "learning_rate": 0.01, **options}
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", ConvergenceWarning)
            result = registry.run_engine(engine, problem.model, data, hyper, fit_key, **options)
        draws = result.sample(draw_key, problem.num_draws)
        info = {"converged": bool(result.converged), "steps": int(result.num_steps_run),
                "warnings": [str(w.message) for w in caught if not issubclass(w.category, ConvergenceWarning)]}
    else:
        raise LmprompError(f"fit_draws runs nuts and svi_* engines, got {engine!r} (cavi runs batched)")
    info["seconds"] = time.perf_counter() - start
    return draws, info


def _replicate_record(problem: SbcProblem, index: int, truth: Mapping, draws: Mapping,
                      rng: np.random.Generator, info: Mapping) -> dict[str, Any]:
    """JSON-able ranks, VSBC probabilities and moments of one replicate."""
    true_q = sbc_quantities(problem, truth)
    post_q = sbc_quantities(problem, draws)
    record: dict[str, Any] = {"index": int(index), "ranks": {}, "vsbc": {}, "truth": {},
                              "post_mean": {}, "post_sd": {}}
    for name, value in true_q.items():
        record["ranks"][name] = rank_statistics(value, post_q[name], rng).tolist()
        record["vsbc"][name] = vsbc_probabilities(value, post_q[name]).tolist()
        record["truth"][name] = value.tolist()
        record["post_mean"][name] = post_q[name].mean(axis=0).tolist()
        record["post_sd"][name] = post_q[name].std(axis=0, ddof=1).tolist()
    record.update({k: v for k, v in info.items()})
    return record


def sbc_task(spec: Mapping[str, Any]) -> dict[str, Any]:
    """Run SBC replicates of one engine: the unit of work of :func:`lmpromp_ppl.calibration.runner.run_tasks`.

    Parameters
    ----------
    spec : ``{"problem": SbcProblem.to_dict(), "engine": str, "seed": int,
        "indices": [int, ...], "options": {...}}``; CAVI fits all ``indices``
        in one :func:`lmpromp_ppl.inference.cavi.fit_cavi_batched` call, the
        other engines fit them one after another (one index per task by default)

    Returns
    -------
    ``{"engine", "replicates": [record, ...]}``; each record has the ranks,
    VSBC probabilities, true values, posterior means and s.d. of every
    quantity of :func:`sbc_quantities`, and the fit's diagnostics.
    """
    problem = SbcProblem.from_dict(spec["problem"])
    engine, seed = spec["engine"], int(spec["seed"])
    if engine not in MODEL_ENGINES[problem.model]:
        raise LmprompError(
            f"engine {engine!r} is not offered for model {problem.model!r}; choose from {MODEL_ENGINES[problem.model]}"
        )
    indices = [int(i) for i in spec["indices"]]
    options = dict(spec.get("options") or {})
    engine_id = _KEY_STREAM[engine]
    simulated = [simulate_replicate(problem, seed, i) for i in indices]
    records = []
    if engine == "cavi":
        from lmpromp_ppl.inference.cavi import fit_cavi_batched, sample_q_batched

        options = {"tol": 1e-8, "max_iter": 2000, **options}
        fit = fit_cavi_batched([data for _, data in simulated], problem.hyper(), **options)
        key = jax.random.fold_in(jax.random.fold_in(jax.random.key(seed), indices[0]), 1000 + engine_id)
        draws = sample_q_batched(key, fit, problem.num_draws)
        for r, (index, (truth, _)) in enumerate(zip(indices, simulated)):
            info = {"converged": bool(fit.converged[r]), "iterations": int(fit.iterations[r]),
                    "seconds": fit.seconds / len(indices)}
            rng = np.random.default_rng([seed, index, engine_id])
            records.append(_replicate_record(problem, index, truth, {k: v[r] for k, v in draws.items()}, rng, info))
    elif engine == "cavi_lr":
        records = _cavi_lr_records(problem, seed, indices, simulated, options, engine_id)
    else:
        for index, (truth, data) in zip(indices, simulated):
            key = jax.random.fold_in(jax.random.fold_in(jax.random.key(seed), index), 1000 + engine_id)
            draws, info = fit_draws(engine, problem, data, key, options)
            rng = np.random.default_rng([seed, index, engine_id])
            records.append(_replicate_record(problem, index, truth, draws, rng, info))
    return {"engine": engine, "model": problem.model, "replicates": records}


def _cavi_lr_records(problem, seed, indices, simulated, options, engine_id) -> list[dict]:
    """``cavi_lr`` replicates: one vmapped joint-family fit and linear response, then per replicate the
    importance ratios on the collapsed model and (k-hat < 0.7, ``resample="auto"``) resampled draws, then
    ``refresh`` exact-conditional sweeps from each draw (:mod:`lmpromp_ppl.inference.refresh`, default
    :data:`~lmpromp_ppl.inference.refresh.REFRESH_SWEEPS`; their time counts in the replicate's seconds)."""
    from lmpromp_ppl.inference.cavi import fit_cavi_batched, linear_response_batched
    from lmpromp_ppl.inference.cavi.importance import POOL, global_draws, global_log_ratios, resample_pool, resamples
    from lmpromp_ppl.inference.psis import psis
    from lmpromp_ppl.inference.refresh import REFRESH_SWEEPS, refresh
    from lmpromp_ppl.models.registry import model_inputs

    options = {"tol": 1e-8, "max_iter": 2000, "family": "rowwise", "resample": "auto", "refresh": REFRESH_SWEEPS,
               **options}
    resample, sweeps = options.pop("resample"), options.pop("refresh")
    hyper = problem.hyper()
    fit = fit_cavi_batched([data for _, data in simulated], hyper, local="joint", **options)
    lr, lr_seconds, _ = linear_response_batched(fit, hyper)
    d, V = problem.num_dofs * problem.num_basis, problem.latent_dim
    records = []
    for r, (index, (truth, data)) in enumerate(zip(indices, simulated)):
        key = jax.random.fold_in(jax.random.fold_in(jax.random.key(seed), index), 1000 + engine_id)
        k_ratio, k_pick = jax.random.split(key)
        one = jax.tree.map(lambda leaf: leaf[r], lr)
        pool, ratios = global_log_ratios(k_ratio, one, model_inputs("lmpromp", "wh", data), hyper, POOL, False)
        log_weights, khat, _ = psis(ratios)
        resampled = resamples(resample, khat)
        if resampled:
            draws = {k: np.asarray(v) for k, v in resample_pool(k_pick, pool, log_weights, problem.num_draws).items()}
        else:
            draws = {k: np.asarray(v) for k, v in global_draws(k_pick, one, problem.num_draws, False, d, V).items()}
        refresh_seconds = 0.0
        if sweeps:
            start = time.perf_counter()
            draws = {k: np.asarray(v) for k, v in refresh(jax.random.fold_in(key, 7), draws, data, hyper, sweeps).items()}
            refresh_seconds = time.perf_counter() - start
        info = {"converged": bool(fit.converged[r]), "iterations": int(fit.iterations[r]),
                "seconds": (fit.seconds + lr_seconds) / len(indices) + refresh_seconds, "psis_khat": khat,
                "refresh_sweeps": int(sweeps), "refresh_seconds": refresh_seconds,
                "importance_resampled": bool(resampled)}
        rng = np.random.default_rng([seed, index, engine_id])
        records.append(_replicate_record(problem, index, truth, draws, rng, info))
    return records


def sbc_tasks(
    problem: SbcProblem,
    engines: Sequence[str],
    num_replicates: int,
    *,
    seed: int = 0,
    cavi_batch: int = 50,
    options: Mapping[str, Mapping[str, Any]] | None = None,
) -> dict[str, dict[str, Any]]:
    """Task specifications (task id -> spec) for :func:`sbc_task` through the runner.

    CAVI replicates are grouped ``cavi_batch`` at a time into one vmapped fit;
    NUTS and SVI replicates are one task each.
    """
    if isinstance(num_replicates, bool) or int(num_replicates) != num_replicates or num_replicates < 2:
        raise LmprompError(f"num_replicates must be an integer >= 2, got {num_replicates!r}")
    options = dict(options or {})
    tasks: dict[str, dict[str, Any]] = {}
    for engine in engines:
        if engine not in MODEL_ENGINES[problem.model]:
            raise LmprompError(
                f"engine {engine!r} is not offered for model {problem.model!r}; "
                f"choose from {list(MODEL_ENGINES[problem.model])}"
            )
        size = max(1, int(cavi_batch)) if engine in BATCHED_ENGINES else 1
        for start in range(0, int(num_replicates), size):
            indices = list(range(start, min(start + size, int(num_replicates))))
            task_id = f"sbc-{problem.model}-{engine}-{indices[0]:04d}"
            if size > 1:
                task_id += f"-{indices[-1]:04d}"
            tasks[task_id] = {"kind": "sbc", "problem": problem.to_dict(), "engine": engine, "seed": int(seed),
                              "indices": indices, "options": dict(options.get(engine, {}))}
    return tasks


# --------------------------------------------------------------------------- summaries
@dataclass
class _Collected:
    ranks: dict[str, list] = field(default_factory=dict)
    vsbc: dict[str, list] = field(default_factory=dict)
    truth: dict[str, list] = field(default_factory=dict)
    post_mean: dict[str, list] = field(default_factory=dict)
    post_sd: dict[str, list] = field(default_factory=dict)
    indices: list[int] = field(default_factory=list)
    seconds: float = 0.0
    not_converged: int = 0
    divergences: int = 0
    psis_khat: list = field(default_factory=list)
    resampled: int = 0


def collect(results: Iterable[Mapping[str, Any]]) -> dict[tuple[str, str], dict[str, Any]]:
    """Gather task results into ``(model, engine) -> {"ranks": {q: (R, k)}, "vsbc": ..., ...}``, sorted by replicate."""
    groups: dict[tuple[str, str], _Collected] = {}
    for result in results:
        group = groups.setdefault((result["model"], result["engine"]), _Collected())
        for record in result["replicates"]:
            group.indices.append(record["index"])
            for what in ("ranks", "vsbc", "truth", "post_mean", "post_sd"):
                for name, value in record[what].items():
                    getattr(group, what).setdefault(name, []).append(value)
            group.seconds += float(record.get("seconds", 0.0))
            group.not_converged += int(not record.get("converged", True))
            group.divergences += int(record.get("divergences", 0))
            if "psis_khat" in record:  # cavi_lr: the importance diagnostics of each replicate
                group.psis_khat.append(np.nan if record["psis_khat"] is None else float(record["psis_khat"]))
                group.resampled += int(bool(record.get("importance_resampled")))
    out = {}
    for key, group in groups.items():
        order = np.argsort(group.indices)
        entry: dict[str, Any] = {"indices": np.asarray(group.indices)[order], "seconds": group.seconds,
                                 "not_converged": group.not_converged, "divergences": group.divergences}
        if group.psis_khat:
            khat = np.asarray(group.psis_khat)
            entry["importance"] = {"psis_khat_median": float(np.nanmedian(khat)),
                                   "below_0.7": int(np.sum(khat < 0.7)), "resampled": group.resampled}
        for what in ("ranks", "vsbc", "truth", "post_mean", "post_sd"):
            entry[what] = {name: np.asarray(v, dtype=float)[order] for name, v in getattr(group, what).items()}
        out[key] = entry
    return out


def summarize(collected: Mapping[tuple[str, str], Mapping[str, Any]], num_draws: int,
              seed: int = 0) -> list[dict[str, Any]]:
    """One row per (model, engine, quantity): uniformity, interval coverage and VSBC.

    Columns: ``model``, ``engine``, ``quantity``, ``components`` (k),
    ``replicates`` (R), ``pvalue_min`` (smallest arviz-stats ``pot_c`` p-value
    over the components), ``pvalue_bonferroni`` (``min(1, k * pvalue_min)``),
    ``pvalues`` (per component), ``coverage50`` and ``coverage90`` (fraction of
    replicates whose true value lies in the central 50 % / 90 % posterior
    interval, i.e. PIT in [0.25, 0.75] / [0.05, 0.95], averaged over
    components; nominal 0.5 and 0.9), ``sd_ratio`` (median over components of
    the mean posterior s.d. divided by the root mean squared error of the
    posterior mean: about 1 when calibrated, below 1 when the posterior is too
    narrow), ``vsbc_pvalue_min`` (smallest VSBC KS p-value, :func:`.vsbc.vsbc_test`).
    """
    rows = []
    for (model, engine), entry in sorted(collected.items()):
        for name, ranks in entry["ranks"].items():
            rng = np.random.default_rng([seed, len(rows)])
            pit = pit_values(ranks, num_draws, rng)
            pvalues = uniformity_pvalues(pit)
            k = pit.shape[1]
            rmse = np.sqrt(np.mean((entry["post_mean"][name] - entry["truth"][name]) ** 2, axis=0))
            sd = np.mean(entry["post_sd"][name], axis=0)
            _, vsbc_p = vsbc_test(entry["vsbc"][name])
            rows.append({
                "model": model, "engine": engine, "quantity": name, "components": int(k),
                "replicates": int(pit.shape[0]),
                "pvalue_min": float(pvalues.min()),
                "pvalue_bonferroni": float(min(1.0, k * pvalues.min())),
                "pvalues": [float(p) for p in pvalues],
                "coverage50": float(np.mean((pit >= 0.25) & (pit <= 0.75))),
                "coverage90": float(np.mean((pit >= 0.05) & (pit <= 0.95))),
                "sd_ratio": float(np.median(sd / np.where(rmse > 0, rmse, np.nan))),
                "vsbc_pvalue_min": float(np.min(vsbc_p)),
            })
    return rows

r"""Benchmarks: speed and scale of every engine, side by side in one process.

``lmpromp bench --out FILE.json`` (:mod:`lmpromp_ppl.cli.bench`) calls
:func:`run_benchmark`, which fits the same model to the same data with every
engine and writes one JSON document (layout in ``benchmarks/README.md``):

* **CAVI** (:mod:`lmpromp_ppl.inference.cavi`, the mixture engine of
  :mod:`lmpromp_ppl.inference.cavi_mixture` when K > 1): compilation time and
  time to convergence separately, iterations, and the cost of one sweep
  measured over a fixed number of sweeps, its floating-point operations
  (XLA's compiled cost analysis) and the achieved rate;
* **SVI** with the ``svi_meanfield`` and ``svi_autonormal`` guides of
  :mod:`lmpromp_ppl.inference.svi`: time and steps until the ELBO gap to the
  CAVI optimum falls below 1 % of :math:`\mathcal L_\text{CAVI} - \mathcal L_\text{init}`
  (:math:`\mathcal L_\text{init}` is the ELBO of CAVI's starting point, the
  thesis initialisation of Sec. 4.1.1, so that both guides chase the same
  absolute target), or the best gap within a stated budget.  The meanfield
  guide is in CAVI's family (thesis eq. 4.3): its parameters are mapped to a
  CAVI state and the closed-form bound is evaluated exactly.  The autonormal
  guide is not (it lives on the model collapsed over ``w``): its ELBO is a
  Monte Carlo estimate, ``-loss`` averaged over many particles, which bounds
  the same evidence :math:`\log p(\mathbf y)` and may therefore exceed the
  CAVI optimum (a negative gap);
* **NUTS** (:func:`lmpromp_ppl.inference.nuts.run_nuts`, its reliable default
  parametrisation: collapsed over ``w``, non-centred ``M``): wall time, the
  smallest bulk ESS over the identifiable quantities (``b``, ``alpha``, sorted
  ``lam`` and the eigenvalues of :math:`MM^T`) and the time per effective draw;
* **batch fitting**: CAVI vectorised over many datasets with ``jax.vmap``
  (:func:`lmpromp_ppl.inference.batch.fit_cavi_batched`, initialisation included);
* **ProMP baseline**: the classical ProMP estimate
  (:func:`lmpromp_ppl.models.promp.classical_promp`) against
  ``movement_primitives``' ``ProMP.imitate`` on LASA (optional ``bench`` extra);
* **goals** (the issue's targets) with the measured figure and whether each is met.

Every engine runs on the same data (standardised synthetic latent-manifold
demonstrations, thesis eq. 4.1) and the same model with the ``proper``
hyperparameter preset (NUTS cannot explore the nearly improper thesis preset).
No number produced here is asserted by a test.
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import os
import platform
import sys
import time
import warnings
from dataclasses import dataclass
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from lmpromp_ppl.basis import DEFAULT_WIDTH, design_matrix
from lmpromp_ppl.data.core import Demonstrations, ModelData, model_data, standardize
from lmpromp_ppl.data.synthetic import latent_manifold
from lmpromp_ppl.errors import ConvergenceWarning, DataError, LmprompError
from lmpromp_ppl.inference import cavi
from lmpromp_ppl.inference.batch import fit_cavi_batched
from lmpromp_ppl.models.hyper import Hyperparameters, preset
from lmpromp_ppl.results import package_version, to_json_value

__all__ = [
    "RowSpec",
    "SviSettings",
    "NutsSettings",
    "BenchConfig",
    "DEFAULT_ROW",
    "SCALING_ROWS",
    "GOAL_ROW_NAME",
    "row_demonstrations",
    "shared_cavi_data",
    "matmul_rate",
    "machine_info",
    "bench_cavi",
    "bench_svi",
    "bench_nuts",
    "bench_batch",
    "bench_promp_baseline",
    "evaluate_goals",
    "run_benchmark",
    "format_table",
]

GOAL_ROW_NAME = "L1000_d420_V10"


# --------------------------------------------------------------------------- settings
@dataclass(frozen=True)
class RowSpec:
    """One problem of the benchmark table.

    Attributes
    ----------
    name : row name (``default`` for the default problem)
    L, D, J, V, K : demonstrations, DoF, basis functions per DoF, latent dimension, components
    T : samples per demonstration
    seed : seed of the synthetic data
    engines : engines run besides CAVI (a subset of ``svi_meanfield``,
        ``svi_autonormal``, ``nuts``); the others are reported as not run
    """

    name: str
    L: int
    D: int
    J: int
    V: int
    K: int = 1
    T: int = 50
    seed: int = 0
    engines: tuple[str, ...] = ()

    @property
    def d(self) -> int:
        """Weight dimension D * J."""
        return self.D * self.J


@dataclass(frozen=True)
class SviSettings:
    """Budget and settings of the SVI rows.

    Attributes
    ----------
    learning_rate : Adam step size (``run_svi``'s default)
    check_every : steps between two ELBO evaluations (the resolution of ``steps``)
    max_steps : step budget
    budget_s : optimisation-time budget in seconds (ELBO evaluations not counted)
    mc_particles : particles of the Monte Carlo ELBO of the autonormal guide
    relative_gap : the target, a fraction of ELBO_CAVI - ELBO_init
    """

    learning_rate: float = 0.01
    check_every: int = 100
    max_steps: int = 20000
    budget_s: float = 20.0
    mc_particles: int = 1000
    relative_gap: float = 0.01


@dataclass(frozen=True)
class NutsSettings:
    """Chains, warm-up and draws of the NUTS rows (``run_nuts``'s defaults)."""

    num_chains: int = 2
    num_warmup: int = 500
    num_samples: int = 500


@dataclass(frozen=True)
class BenchConfig:
    """Everything :func:`run_benchmark` needs.

    Attributes
    ----------
    rows : problems to run
    tol, max_iter : CAVI stopping rule (relative ELBO change) and sweep limit
    timing_sweeps : sweeps of the fixed-length run that measures the cost of one sweep
    cavi_budget_s : when ``max_iter`` sweeps would take longer than this, the CAVI fit
        runs in chunks and stops at this time (reported as ``stopped: "time budget"``)
    repeats : repetitions of each timed CAVI run (the minimum is reported)
    svi, nuts : engine settings
    batch_size : datasets of the batch row (0 skips it)
    batch_row : problem of the batch row
    baseline_dataset : dataset of the ProMP baseline ("" skips it)
    baseline_num_basis : basis functions per DoF of both ProMP fits
    matmul_size : size n of the n x n float64 matrix product that measures the machine's rate
    seed : seed of every PRNG key
    progress : print one line per finished engine to stderr
    """

    rows: tuple[RowSpec, ...]
    tol: float = 1e-8
    max_iter: int = 2000
    timing_sweeps: int = 50
    repeats: int = 3
    cavi_budget_s: float = 60.0
    svi: SviSettings = SviSettings()
    nuts: NutsSettings = NutsSettings()
    batch_size: int = 1000
    batch_row: RowSpec | None = None
    baseline_dataset: str = "lasa:GShape"
    baseline_num_basis: int = 10
    matmul_size: int = 2000
    seed: int = 0
    progress: bool = True


_ALL = ("svi_meanfield", "svi_autonormal", "nuts")
_SVI_ONLY = ("svi_meanfield", "svi_autonormal")

#: The default problem of the issue: every engine.
DEFAULT_ROW = RowSpec("default", L=20, D=2, J=10, V=3, engines=_ALL)

#: Scaling rows: L in {10, 100, 1000, 10000}, d = D*J in {120, 420}, V in {2, 10}, K = 3,
#: and the goal problem L = 1000, d = 420, V = 10.  NUTS runs on the default row only
#: (it needs minutes there); SVI on the default row and L = 100, each guide within
#: its budget (:class:`SviSettings`).
SCALING_ROWS = (
    RowSpec("L10", L=10, D=2, J=10, V=3),
    RowSpec("L100", L=100, D=2, J=10, V=3, engines=_SVI_ONLY),
    RowSpec("L1000", L=1000, D=2, J=10, V=3),
    RowSpec("L10000", L=10000, D=2, J=10, V=3),
    RowSpec("d120", L=20, D=6, J=20, V=3),
    RowSpec("d420", L=20, D=7, J=60, V=3, T=120),
    RowSpec("V2", L=20, D=2, J=10, V=2),
    RowSpec("V10", L=20, D=2, J=10, V=10),
    RowSpec("K3", L=21, D=2, J=10, V=3, K=3),
    RowSpec(GOAL_ROW_NAME, L=1000, D=7, J=60, V=10, T=120),
)


def _hyper(row: RowSpec) -> Hyperparameters:
    # fixed beta: the batched CAVI and the committed figures use the thesis's fixed noise
    return preset("proper", latent_dim=row.V, num_components=row.K, learn_beta=False)


def _log(config: BenchConfig, message: str) -> None:
    if config.progress:
        print(f"bench: {message}", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- data
def row_demonstrations(row: RowSpec) -> Demonstrations:
    """Standardised synthetic latent-manifold demonstrations for a row (thesis eq. 4.1).

    For K > 1 the demonstrations of K latent-manifold models (seeds
    ``seed, seed + 1, ...``, each with its own offset and projection) are
    concatenated, about L / K each, so that the mixture has K true types.
    """
    if row.K == 1:
        demos = latent_manifold(L=row.L, D=row.D, J=row.J, V=row.V, T=row.T, seed=row.seed)
    else:
        sizes = [row.L // row.K + (k < row.L % row.K) for k in range(row.K)]
        parts = [
            latent_manifold(L=n, D=row.D, J=row.J, V=row.V, T=row.T, seed=row.seed + k)
            for k, n in enumerate(sizes)
        ]
        demos = Demonstrations(
            times=tuple(t for p in parts for t in p.times),
            positions=tuple(y for p in parts for y in p.positions),
            name=f"synthetic:latent mixture of {row.K} (seeds {row.seed}..{row.seed + row.K - 1})",
        )
    return standardize(demos)[0]


def shared_cavi_data(demos: Demonstrations, num_basis: int, width: float = DEFAULT_WIDTH) -> cavi.CaviData:
    """CAVI statistics of demonstrations that share one time grid, without padded arrays.

    Equal to ``cavi.prepare_cavi_data(model_data(demos, num_basis, width))`` on
    the shared-design fast path, but it never builds the (L, S, d) design
    array (2.8 GB for L = 1000, S = 840, d = 420): :math:`\\Psi^T y_i` is one
    (L, S) x (S, d) product.

    Raises
    ------
    DataError
        when the demonstrations do not share one time grid
    """
    phases = demos.phases()
    first = phases[0]
    if any(p.shape != first.shape or not np.array_equal(p, first) for p in phases):
        raise DataError("shared_cavi_data needs demonstrations that share one time grid")
    psi = np.asarray(design_matrix(first, demos.num_dofs, num_basis, width))
    y = np.stack([np.asarray(p, np.float64).reshape(-1) for p in demos.positions])
    if not np.all(np.isfinite(y)):
        raise DataError("shared_cavi_data needs complete demonstrations (no NaN)")
    eigvals, basis = np.linalg.eigh(psi.T @ psi)
    return cavi.CaviData(
        psi_t_y=jnp.asarray(y @ psi),
        y_sq=jnp.asarray(np.sum(y**2, axis=1)),
        num_obs=jnp.full((y.shape[0],), float(y.shape[1])),
        gram=cavi.SharedGram(jnp.asarray(basis), jnp.asarray(np.maximum(eigvals, 0.0))),
    )


# --------------------------------------------------------------------------- machine
def matmul_rate(n: int = 2000, repeats: int = 5) -> float:
    """Measured float64 rate (FLOP/s) of an n x n matrix product (2 n^3 operations), best of ``repeats``."""
    keys = jax.random.split(jax.random.key(0))
    a = jax.random.normal(keys[0], (n, n), jnp.float64)
    b = jax.random.normal(keys[1], (n, n), jnp.float64)
    product = jax.jit(jnp.matmul)
    jax.block_until_ready(product(a, b))
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(product(a, b))
        best = min(best, time.perf_counter() - start)
    return 2.0 * n**3 / best


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict[str, Any]:
    """CPU, cores, load, jax devices and package versions."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {
        "cpu": _cpu_model(),
        "cores": cores,
        "platform": platform.platform(),
        "load_average_at_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "jax_backend": jax.default_backend(),
        "jax_devices": [str(d) for d in jax.devices()],
        "xla_flags": os.environ.get("XLA_FLAGS"),
        "versions": {
            "python": platform.python_version(),
            **{name: package_version(name) for name in
               ("lmpromp-ppl", "jax", "jaxlib", "numpyro", "numpy", "scikit-learn", "movement_primitives")},
        },
    }


# --------------------------------------------------------------------------- CAVI
def _cavi_parts(row: RowSpec, data: cavi.CaviData, key: Array):
    """(initial state, hyper arrays, sweep function or None) of the engine for this row."""
    from lmpromp_ppl.inference import cavi_mixture
    from lmpromp_ppl.inference.init import init_mixture_state, init_state

    hyper = _hyper(row)
    if row.K == 1:
        return init_state(data, hyper), cavi.hyper_arrays(hyper), None
    state = init_mixture_state(data, hyper, key)
    return state, cavi_mixture.mixture_hyper_arrays(hyper), cavi_mixture.step


def _flops(step_fn: Callable, state, data, hyper_arr) -> float | None:
    """Floating-point operations of one sweep from XLA's compiled cost analysis (None if unavailable)."""
    analysis = jax.jit(step_fn).lower(state, data, hyper_arr).compile().cost_analysis()
    if isinstance(analysis, (list, tuple)):
        analysis = analysis[0] if analysis else None
    if not analysis or "flops" not in analysis:
        return None
    return float(analysis["flops"])


def bench_cavi(row: RowSpec, data: cavi.CaviData, config: BenchConfig, peak_rate: float) -> tuple[dict, Any]:
    """Time CAVI on one row: a full fit (best of ``repeats``) and a fixed number of sweeps.

    Returns
    -------
    (the row's ``cavi`` object, the converged state)
    """
    key = jax.random.key(config.seed)
    start = time.perf_counter()
    state0, hyper_arr, step_fn = _cavi_parts(row, data, key)
    jax.block_until_ready(state0)
    init_s = time.perf_counter() - start
    # cost of one sweep: a fixed number of sweeps (tol = -1 never stops early); a probe
    # of 5 sweeps first, so that a slow problem is not run for the whole count
    sweeps = int(config.timing_sweeps)
    tol_off = jnp.asarray(-1.0)
    fixed_args = lambda n: (state0, data, hyper_arr, tol_off, jnp.asarray(n, jnp.int32),  # noqa: E731
                            jnp.asarray(-jnp.inf))
    run_fixed, compile_s = cavi._compiled_iterate(fixed_args(sweeps), sweeps, step_fn)
    start = time.perf_counter()
    probe = min(5, sweeps)
    jax.block_until_ready(run_fixed(*fixed_args(probe)))
    sweep_s = (time.perf_counter() - start) / probe
    if sweep_s * sweeps < 1.0:
        sweep_s = math.inf
        for _ in range(config.repeats):
            start = time.perf_counter()
            out = jax.block_until_ready(run_fixed(*fixed_args(sweeps)))
            sweep_s = min(sweep_s, (time.perf_counter() - start) / max(int(out.iterations), 1))
    if sweep_s * config.max_iter <= config.cavi_budget_s:
        # the fit as fit_cavi runs it: one compiled while_loop, best of `repeats`
        best = None
        for _ in range(config.repeats):
            result, trace, seconds, compiled = cavi._run_one(
                state0, data, hyper_arr, config.tol, config.max_iter, False, "", step_fn=step_fn
            )
            compile_s += compiled
            if best is None or seconds < best[2]:
                best = (result, trace, seconds)
            if seconds > 1.0:  # long fits are timed once
                break
        result, trace, fit_s = best
        stopped = "converged" if bool(result.converged) else "max_iter"
        how = "one compiled while_loop as in fit_cavi"
    else:
        # too slow for max_iter sweeps within the budget: chunks of `sweeps`, stopped by time
        state, done, fit_s, traces, previous = state0, 0, 0.0, [], jnp.asarray(-jnp.inf)
        tol_arr = jnp.asarray(config.tol, jnp.float64)
        while True:
            limit = min(sweeps, config.max_iter - done)
            start = time.perf_counter()
            result = jax.block_until_ready(
                run_fixed(state, data, hyper_arr, tol_arr, jnp.asarray(limit, jnp.int32), previous))
            fit_s += time.perf_counter() - start
            n = int(result.iterations)
            traces.append(np.asarray(result.elbo_trace[:n]))
            done += n
            state, previous = result.state, result.elbo_trace[max(n - 1, 0)]
            if bool(result.converged) or done >= config.max_iter or n == 0 or fit_s >= config.cavi_budget_s:
                break
        trace = np.concatenate(traces)
        result = result._replace(iterations=jnp.asarray(done, jnp.int32))
        stopped = ("converged" if bool(result.converged) else
                   "max_iter" if done >= config.max_iter else "time budget")
        how = f"chunks of {sweeps} sweeps within a time budget of {config.cavi_budget_s:g} s"
    flops = _flops(cavi.step if step_fn is None else step_fn, state0, data, hyper_arr)
    rate = None if flops is None else flops / sweep_s
    engine = "cavi" if row.K == 1 else "cavi_mixture"
    return {
        "engine": engine,
        "compile_s": compile_s,
        "fit_s": fit_s,
        "init_s": init_s,
        "iterations": int(result.iterations),
        "converged": bool(result.converged),
        "stopped": stopped,
        "elbo": float(trace[-1]),
        "elbo_init": float(_elbo_fn(step_fn)(state0, data, hyper_arr)),
        "tol": config.tol,
        "max_iter": config.max_iter,
        "s_per_iteration": sweep_s,
        "flops_per_iteration": flops,
        "flop_rate": rate,
        "flop_rate_over_matmul": None if rate is None else rate / peak_rate,
        "timing": f"fit_s ({how}): best of {config.repeats} fits from the same start (one when a fit "
                  f"takes > 1 s), excluding compilation and initialisation; s_per_iteration: best of "
                  f"{config.repeats} runs of {sweeps} sweeps (5 sweeps when {sweeps} would take > 1 s)",
        "budget_s": config.cavi_budget_s,
    }, result.state


def _elbo_fn(step_fn: Callable | None) -> Callable:
    if step_fn is None:
        return cavi.elbo
    from lmpromp_ppl.inference import cavi_mixture

    return cavi_mixture.elbo


# --------------------------------------------------------------------------- SVI
def bench_svi(
    guide_name: str,
    md: ModelData,
    hyper: Hyperparameters,
    key: Array,
    elbo_cavi: float,
    elbo_init: float,
    settings: SviSettings,
) -> dict:
    """Steps and optimisation time of SVI until the ELBO gap to CAVI falls below the target.

    The model and guide are those of :func:`lmpromp_ppl.inference.svi.run_svi`
    (``make_guide``; the meanfield guide starts at ``meanfield_init``, the
    autonormal guide at numpyro's default), optimised by Adam with single-particle
    gradients in compiled chunks of ``check_every`` steps; after each chunk the
    ELBO is evaluated (not timed): exactly for the meanfield guide (its
    parameters as a CAVI state, :func:`lmpromp_ppl.inference.cavi.elbo`),
    by a ``mc_particles``-particle Monte Carlo average for the autonormal guide.
    The run stops at the target gap or at the step or time budget.
    """
    from numpyro.infer import SVI, Trace_ELBO
    from numpyro.optim import Adam

    from lmpromp_ppl.inference import svi as svi_engine

    guide_kind = guide_name.removeprefix("svi_")
    data = ModelData(*(jnp.asarray(a, jnp.float64) for a in md))
    model, guide = svi_engine.make_guide(guide_kind, "lmpromp", data, hyper, collapsed="w")
    fixed: dict = {}
    optimiser = SVI(model, guide, Adam(settings.learning_rate), Trace_ELBO())
    key_init, key_mc = jax.random.split(key)
    start = time.perf_counter()
    if guide_kind == "meanfield":
        init = {k: jnp.asarray(v) for k, v in svi_engine.meanfield_init(data, hyper).items()}
        state = optimiser.init(key_init, data, fixed, init_params=init)
        full = cavi.prepare_cavi_data(data, shared_psi=False)
        hyper_arr = cavi.hyper_arrays(hyper)

        def elbo_of(params, _key):
            return cavi.elbo(svi_engine.cavi_state_from_meanfield(params), full, hyper_arr)

        elbo_kind = "closed form (the CAVI bound at the guide's parameters)"
    else:
        state = optimiser.init(key_init, data, fixed)
        mc = Trace_ELBO(num_particles=settings.mc_particles)
        mc_loss = jax.jit(lambda k, params: mc.loss(k, params, model, guide, data, fixed))

        def elbo_of(params, k):
            return -mc_loss(k, params)

        elbo_kind = (f"Monte Carlo: -loss averaged over {settings.mc_particles} particles, "
                     "on the model collapsed over w")

    def chunk(s, d):
        return jax.lax.scan(lambda c, _: optimiser.stable_update(c, d, fixed), s, None,
                            length=settings.check_every)

    chunk = jax.jit(chunk).lower(state, data).compile()
    params = optimiser.get_params(state)
    elbo_start = float(elbo_of(params, key_mc))
    compile_s = time.perf_counter() - start
    target = settings.relative_gap * (elbo_cavi - elbo_init)
    steps, fit_s, best_gap, reached = 0, 0.0, elbo_cavi - elbo_start, False
    while steps < settings.max_steps and fit_s < settings.budget_s:
        tic = time.perf_counter()
        state, losses = chunk(state, data)
        jax.block_until_ready(losses)
        fit_s += time.perf_counter() - tic
        steps += settings.check_every
        key_mc, sub = jax.random.split(key_mc)
        gap = elbo_cavi - float(elbo_of(optimiser.get_params(state), sub))
        if math.isfinite(gap):
            best_gap = min(best_gap, gap)
        if gap <= target:
            reached = True
            break
    return {
        "fit_s": fit_s,
        "compile_s": compile_s,
        "steps": steps,
        "elbo_gap": best_gap,
        "reached": reached,
        "gap_target": target,
        "elbo_start": elbo_start,
        "elbo_kind": elbo_kind,
        "budget": {"max_steps": settings.max_steps, "budget_s": settings.budget_s,
                   "check_every": settings.check_every},
        "learning_rate": settings.learning_rate,
        "note": "fit_s and steps are to the first check at which the gap is below gap_target; "
                "when not reached, the whole budget and elbo_gap is the best gap seen",
    }


# --------------------------------------------------------------------------- NUTS
def bench_nuts(md: ModelData, hyper: Hyperparameters, key: Array, settings: NutsSettings) -> dict:
    """Wall time and time per effective draw of NUTS (smallest bulk ESS over the identifiable quantities)."""
    from lmpromp_ppl.inference import nuts

    result = nuts.run_nuts(
        "lmpromp", md, hyper, key, num_chains=settings.num_chains,
        num_warmup=settings.num_warmup, num_samples=settings.num_samples,
    )
    quality = nuts.reliability(nuts.identifiable_quantities(result.samples))
    ess = min(q["ess_bulk_min"] for q in quality.values())
    return {
        "fit_s": result.seconds,
        "compile_s": result.compile_seconds,
        "ess_bulk_min": ess,
        "s_per_ess": result.seconds / ess,
        "rhat_max": max(q["rhat_max"] for q in quality.values()),
        "divergences": int(np.sum(result.sample_stats["diverging"])),
        "mean_leapfrog_steps": float(np.mean(result.sample_stats["num_steps"])),
        "settings": result.options,
        "quantities": "b, alpha, lam (sorted), eigenvalues of M M^T",
    }


# --------------------------------------------------------------------------- batch
def bench_batch(row: RowSpec, size: int, config: BenchConfig) -> dict:
    """Fit ``size`` datasets of the row's size (seeds ``seed .. seed + size - 1``) in one batch.

    The datasets share one time grid, so they go to
    :func:`lmpromp_ppl.inference.batch.fit_cavi_batched` as one stacked
    :class:`~lmpromp_ppl.inference.cavi.CaviData`: the pure-JAX thesis
    initialisation and the sweeps run in one vmapped program.
    """
    datasets = [
        shared_cavi_data(row_demonstrations(dataclasses.replace(row, seed=row.seed + s)), row.J)
        for s in range(size)
    ]
    data = cavi.CaviData(
        psi_t_y=jnp.stack([x.psi_t_y for x in datasets]),
        y_sq=jnp.stack([x.y_sq for x in datasets]),
        num_obs=jnp.stack([x.num_obs for x in datasets]),
        gram=datasets[0].gram,
    )
    fit = fit_cavi_batched(data, _hyper(row), tol=config.tol, max_iter=config.max_iter)
    return {
        "datasets": size,
        "L": row.L, "D": row.D, "J": row.J, "V": row.V, "K": row.K,
        "compile_s": fit.compile_seconds,
        "fit_s": fit.seconds,
        "datasets_per_s": size / fit.seconds,
        "iterations_max": int(fit.iterations.max()),
        "iterations_mean": float(fit.iterations.mean()),
        "converged_fraction": float(fit.converged.mean()),
        "tol": config.tol,
        "max_iter": config.max_iter,
        "method": "jax.vmap over datasets of a pure-JAX thesis initialisation and the CAVI "
                  "while_loop (inference.batch.fit_cavi_batched); fit_s includes initialisation",
    }


# --------------------------------------------------------------------------- ProMP baseline
def bench_promp_baseline(dataset: str, num_basis: int) -> dict:
    """Classical ProMP (this package) against ``movement_primitives``' ``ProMP.imitate``.

    Both fit the raw (unstandardised) positions on phases in [0, 1]; the row
    reports both times and the RMSE between the two mean trajectories over the
    data's time grid, relative to the data range (max - min over all DoF).
    """
    from lmpromp_ppl.data import load_dataset
    from lmpromp_ppl.models.promp import classical_promp

    demos = load_dataset(dataset)
    phases = demos.phases()
    phase = phases[0]
    classical_promp(demos, num_basis=num_basis)  # warm-up: compiles the jax basis functions
    ours_s = math.inf
    for _ in range(3):
        start = time.perf_counter()
        mu_w, _, _ = classical_promp(demos, num_basis=num_basis)
        ours_s = min(ours_s, time.perf_counter() - start)
    ours_mean = (np.asarray(design_matrix(phase, demos.num_dofs, num_basis)) @ mu_w).reshape(-1, demos.num_dofs)
    stacked = np.concatenate(demos.positions)
    data_range = float(stacked.max() - stacked.min())
    out = {
        "dataset": dataset,
        "num_demos": demos.num_demos,
        "num_steps": int(phase.shape[0]),
        "num_dofs": demos.num_dofs,
        "num_basis": num_basis,
        "lmpromp_ppl": {
            "fit_s": ours_s,
            "timing": "best of 3 after a warm-up call (the first call compiles the jax basis)",
            "settings": "classical_promp: per-demonstration least squares (ridge 1e-6) on normalised "
                        "RBFs of width 2 (variance 2 / (J - 1)^2 in phase), Ledoit-Wolf covariance",
        },
    }
    try:
        from movement_primitives.promp import ProMP
    except ImportError:
        out["movement_primitives"] = "skipped: movement_primitives is not installed (pip install '.[bench]')"
        out["mean_rmse_over_range"] = None
        return out
    ts = np.stack(phases)
    ys = np.stack(demos.positions)
    promp = ProMP(n_dims=demos.num_dofs, n_weights_per_dim=num_basis)
    start = time.perf_counter()
    promp.imitate(ts, ys)
    theirs_s = time.perf_counter() - start
    theirs_mean = promp.mean_trajectory(phase)
    out["movement_primitives"] = {
        "fit_s": theirs_s,
        "timing": "one call (pure numpy, nothing to compile)",
        "version": package_version("movement_primitives"),
        "settings": "ProMP.imitate: EM of Lazaric & Ghavamzadeh (2010) with defaults n_iter=1000, "
                    "min_delta=1e-5, temporally differenced noise (gamma 0.7), normalised RBFs "
                    "with overlap 0.7",
    }
    out["mean_rmse_over_range"] = float(np.sqrt(np.mean((ours_mean - theirs_mean) ** 2)) / data_range)
    out["speed_ratio_movement_primitives_over_ours"] = theirs_s / ours_s
    return out


# --------------------------------------------------------------------------- goals
def _goal(target: str, measured: float | None, met: bool | None, note: str = "") -> dict:
    out = {"target": target, "measured": measured, "met": met}
    if note:
        out["note"] = note
    return out


def evaluate_goals(rows: list[dict], batch: dict | None) -> dict:
    """The issue's goals with their measured figures (``met`` is null when not measured)."""
    by_name = {r["name"]: r for r in rows}
    default = by_name.get("default")
    goals: dict[str, dict] = {}
    if default is not None:
        fit = default["cavi"]["fit_s"]
        goals["default_cavi_under_20ms"] = _goal("CAVI fit_s < 0.020 s on the default problem", fit, fit < 0.020)
        ratio = default["ratios"]["nuts_over_cavi"]
        goals["default_1000x_faster_than_nuts"] = _goal(
            "NUTS fit_s / CAVI fit_s >= 1000", ratio, None if ratio is None else ratio >= 1000)
        ratio = default["ratios"]["svi_over_cavi"]
        svi = default.get("svi_meanfield", {})
        lower = isinstance(svi, dict) and not svi.get("reached", True)
        goals["default_100x_faster_than_svi"] = _goal(
            "svi_meanfield time to the CAVI ELBO (gap < 1 %) / CAVI fit_s >= 100", ratio,
            None if ratio is None else ratio >= 100,
            "SVI did not reach the target within its budget: the ratio is a lower bound" if lower else "")
    goal_row = by_name.get(GOAL_ROW_NAME)
    if goal_row is not None:
        fit = goal_row["cavi"]["fit_s"]
        goals["L1000_d420_V10_under_5s"] = _goal(
            f"CAVI fit_s < 5 s for L = 1000, d = 420, V = 10 on {goal_row['cores']} cores", fit, fit < 5.0)
    if batch is not None:
        goals["batch_1000_under_60s"] = _goal(
            f"{batch['datasets']} batched default datasets in < 60 s (initialisation included)",
            batch["fit_s"], batch["fit_s"] < 60.0 if batch["datasets"] >= 1000 else None,
            "" if batch["datasets"] >= 1000 else "fewer than 1000 datasets were run")
    return goals


# --------------------------------------------------------------------------- driver
def _not_run(reason: str) -> dict:
    return {"run": False, "reason": reason}


def _bench_row(row: RowSpec, config: BenchConfig, peak_rate: float) -> dict:
    hyper = _hyper(row)
    demos = row_demonstrations(row)
    data = shared_cavi_data(demos, row.J)
    out: dict[str, Any] = {
        "name": row.name, "L": row.L, "D": row.D, "J": row.J, "d": row.d, "V": row.V, "K": row.K,
        "T": row.T, "seed": row.seed, "cores": machine_info()["cores"],
        "data": demos.name, "hyperparameters": "preset proper: " + str(hyper.to_dict()),
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        out["cavi"], _ = bench_cavi(row, data, config, peak_rate)
    _log(config, f"{row.name}: cavi {out['cavi']['fit_s'] * 1e3:.2f} ms, {out['cavi']['iterations']} iterations")
    md = model_data(demos, row.J) if row.engines else None
    key = jax.random.key(config.seed)
    for engine in ("svi_meanfield", "svi_autonormal"):
        if engine not in row.engines:
            out[engine] = _not_run("not run on this row: outside the stated SVI budget")
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            out[engine] = bench_svi(engine, md, hyper, key, out["cavi"]["elbo"], out["cavi"]["elbo_init"],
                                    config.svi)
        _log(config, f"{row.name}: {engine} {out[engine]['fit_s']:.2f} s, {out[engine]['steps']} steps, "
                     f"gap {out[engine]['elbo_gap']:.3g} (target {out[engine]['gap_target']:.3g})")
    if "nuts" in row.engines:
        out["nuts"] = bench_nuts(md, hyper, key, config.nuts)
        _log(config, f"{row.name}: nuts {out['nuts']['fit_s']:.1f} s, min bulk ESS {out['nuts']['ess_bulk_min']:.0f}")
    else:
        out["nuts"] = _not_run("not run on this row: NUTS needs minutes per problem; it runs on the default row only")
    fit = out["cavi"]["fit_s"]
    ratio = lambda e: out[e]["fit_s"] / fit if out[e].get("run", True) else None  # noqa: E731
    out["ratios"] = {
        "nuts_over_cavi": ratio("nuts"),
        "svi_over_cavi": ratio("svi_meanfield"),
        "svi_autonormal_over_cavi": ratio("svi_autonormal"),
        "note": "wall time excluding compilation over CAVI's fit_s; svi_over_cavi is svi_meanfield "
                "(CAVI's family, the same ELBO); an SVI ratio is a lower bound when it did not reach the target",
    }
    return out


def _scaling_exponent(rows: list[dict]) -> dict | None:
    """Least-squares slope of log(seconds per sweep) on log L over the rows that vary only L."""
    series = sorted((r for r in rows if r["K"] == 1 and r["D"] == 2 and r["J"] == 10 and r["V"] == 3),
                    key=lambda r: r["L"])
    if len({r["L"] for r in series}) < 2:
        return None
    L = np.array([r["L"] for r in series], float)
    per_iter = np.array([r["cavi"]["s_per_iteration"] for r in series])
    slope_all = float(np.polyfit(np.log(L), np.log(per_iter), 1)[0])
    large = L >= 100
    slope_large = float(np.polyfit(np.log(L[large]), np.log(per_iter[large]), 1)[0]) if large.sum() >= 2 else None
    flops = [r["cavi"]["flops_per_iteration"] for r in series]
    flop_slope = (float(np.polyfit(np.log(L), np.log(np.asarray(flops, float)), 1)[0])
                  if all(f is not None for f in flops) else None)
    return {
        "L": L.tolist(),
        "s_per_iteration": per_iter.tolist(),
        "flops_per_iteration": flops,
        "flops_exponent": flop_slope,
        "exponent": slope_all,
        "exponent_L_ge_100": slope_large,
        "goal": "linear (exponent 1); at small L the fixed cost of a sweep dominates; "
                "flops_exponent is the same fit to XLA's operation count (free of timing noise)",
    }


def run_benchmark(config: BenchConfig, device: str = "cpu", gpu_note: str = "",
                  on_update: Callable[[dict], None] | None = None) -> dict:
    """Run every row, the batch row and the ProMP baseline; return the JSON document.

    Parameters
    ----------
    config : rows and settings
    device : ``"cpu"`` or ``"gpu"`` (jax's default backend must match)
    gpu_note : on a CPU run, why no GPU run accompanies it (the ``gpu`` entry's ``reason``)
    on_update : called with the document so far (``"complete": false``) after every row,
        so that a caller can save partial results of a long run
    """
    if device not in ("cpu", "gpu"):
        raise LmprompError(f"device must be 'cpu' or 'gpu', got {device!r}")
    if jax.default_backend() != device:
        raise LmprompError(
            f"--device {device} asked for, but jax's default backend is {jax.default_backend()!r}"
        )
    started = datetime.datetime.now(datetime.timezone.utc)
    machine = machine_info()
    peak = matmul_rate(config.matmul_size)
    machine["matmul_flop_rate"] = peak
    machine["matmul"] = f"float64 {config.matmul_size} x {config.matmul_size} matrix product, best of 5"
    _log(config, f"matmul rate {peak / 1e9:.1f} GFLOP/s")
    gpu = ({"run": True, "device": machine["jax_devices"]} if device == "gpu" else
           _not_run(gpu_note or "this is a CPU run; run `lmpromp bench --device gpu` on a GPU machine"))
    rows: list[dict] = []
    batch = None
    baseline: dict = _not_run("not reached yet")

    def document(complete: bool) -> dict:
        machine["load_average_now"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
        return to_json_value({
            "format": "lmpromp-bench/1",
            "complete": complete,
            "created": started.isoformat(timespec="seconds"),
            "device": device,
            "machine": machine,
            "settings": {
                "model": "lmpromp (mixture of K LMProMPs when K > 1), hyperparameter preset 'proper'",
                "data": "standardised synthetic:latent (thesis eq. 4.1), one time grid per row",
                "cavi": {"tol": config.tol, "max_iter": config.max_iter, "timing_sweeps": config.timing_sweeps,
                         "repeats": config.repeats, "budget_s": config.cavi_budget_s},
                "svi": dataclasses.asdict(config.svi),
                "nuts": dataclasses.asdict(config.nuts),
                "seed": config.seed,
            },
            "rows": rows,
            "scaling": _scaling_exponent(rows),
            "batch": batch,
            "promp_baseline": baseline,
            "gpu": gpu,
            "goals": evaluate_goals(rows, batch),
        })

    for row in config.rows:
        rows.append(_bench_row(row, config, peak))
        if on_update is not None:
            on_update(document(False))
    if config.batch_size > 0:
        batch = bench_batch(config.batch_row or DEFAULT_ROW, config.batch_size, config)
        _log(config, f"batch: {batch['datasets']} datasets in {batch['fit_s']:.2f} s")
        if on_update is not None:
            on_update(document(False))
    baseline = (bench_promp_baseline(config.baseline_dataset, config.baseline_num_basis)
                if config.baseline_dataset else _not_run("not requested"))
    return document(True)


# --------------------------------------------------------------------------- table
def _fmt(value: Any, spec: str) -> str:
    if value is None:
        return "-"
    return format(value, spec)


def _engine_cell(row: dict, engine: str) -> str:
    entry = row[engine]
    if not entry.get("run", True):
        return "not run"
    if engine == "nuts":
        return f"{entry['fit_s']:.1f} s, {entry['s_per_ess'] * 1e3:.0f} ms/ESS"
    mark = "" if entry["reached"] else " (budget, not reached)"
    return f"{entry['fit_s']:.2f} s, {entry['steps']} steps{mark}"


def format_table(result: dict) -> str:
    """A Markdown table of the rows, then the batch, baseline and goals."""
    lines = [
        "| row | L | d | V | K | CAVI compile s | CAVI fit ms | iters | ms/iter | GFLOP/s | "
        "svi_meanfield | svi_autonormal | NUTS | NUTS/CAVI | SVI/CAVI |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|---|---:|---:|",
    ]
    for r in result["rows"]:
        c = r["cavi"]
        rate = None if c["flop_rate"] is None else c["flop_rate"] / 1e9
        lines.append(
            f"| {r['name']} | {r['L']} | {r['d']} | {r['V']} | {r['K']} | {c['compile_s']:.2f} | "
            f"{c['fit_s'] * 1e3:.2f} | {c['iterations']}{'' if c['converged'] else ' (' + c['stopped'] + ')'} | {c['s_per_iteration'] * 1e3:.3f} | "
            f"{_fmt(rate, '.2f')} | {_engine_cell(r, 'svi_meanfield')} | {_engine_cell(r, 'svi_autonormal')} | "
            f"{_engine_cell(r, 'nuts')} | {_fmt(r['ratios']['nuts_over_cavi'], '.3g')} | "
            f"{_fmt(r['ratios']['svi_over_cavi'], '.3g')} |"
        )
    out = "\n".join(lines)
    machine = result["machine"]
    out += f"\n\nMatrix-product rate: {machine['matmul_flop_rate'] / 1e9:.1f} GFLOP/s ({machine['matmul']})."
    scaling = result.get("scaling")
    if scaling:
        out += (f"\nCAVI cost per sweep ~ L^{scaling['exponent']:.2f} over L = "
                f"{', '.join(str(int(v)) for v in scaling['L'])}"
                + ("" if scaling["exponent_L_ge_100"] is None else
                   f" (L^{scaling['exponent_L_ge_100']:.2f} for L >= 100)")
                + ("" if scaling.get("flops_exponent") is None else
                   f"; operations per sweep ~ L^{scaling['flops_exponent']:.2f}") + ".")
    batch = result.get("batch")
    if batch:
        out += (f"\nBatch: {batch['datasets']} default datasets in {batch['fit_s']:.2f} s "
                f"({batch['datasets_per_s']:.0f} datasets/s, compile {batch['compile_s']:.1f} s, "
                f"{batch['converged_fraction']:.1%} converged).")
    base = result.get("promp_baseline", {})
    if base.get("run", True) and "lmpromp_ppl" in base:
        theirs = base["movement_primitives"]
        theirs_text = theirs if isinstance(theirs, str) else (
            f"movement_primitives {theirs['fit_s'] * 1e3:.1f} ms, mean RMSE / range "
            f"{base['mean_rmse_over_range']:.2e}")
        out += (f"\nProMP baseline on {base['dataset']} ({base['num_demos']} x {base['num_steps']} x "
                f"{base['num_dofs']}, J = {base['num_basis']}): lmpromp_ppl "
                f"{base['lmpromp_ppl']['fit_s'] * 1e3:.1f} ms; {theirs_text}.")
    gpu = result["gpu"]
    if not gpu["run"]:
        out += f"\nGPU: not run ({gpu['reason']})."
    out += "\n\n| goal | target | measured | met |\n|---|---|---:|---|"
    for name, g in result["goals"].items():
        out += f"\n| {name} | {g['target']} | {_fmt(g['measured'], '.4g')} | {g['met']} |"
    return out

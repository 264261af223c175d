r"""Stochastic variational inference on the NumPyro declarations of :mod:`lmpromp_ppl.models`.

:func:`fit_svi` maximises the ELBO :math:`\mathbb E_q[\log p(\mathbf y, Z) - \log q(Z)]`
(thesis eq. 3.5) by Adam on reparametrised Monte Carlo gradients
(``numpyro.infer.Trace_ELBO``) with one of three guides (:func:`make_guide`):

``meanfield`` (engine ``svi_meanfield``)
    A hand-written guide in CAVI's family, eq. 4.3, on the **full** single-type
    LMProMP (:func:`lmpromp_ppl.models.lmpromp.lmpromp_model`):
    :math:`q(\mathbf w_i) = \mathcal N(\boldsymbol\mu_{w_i}, \boldsymbol\Sigma_{w_i})`
    and :math:`q(\mathbf h_i) = \mathcal N(\boldsymbol\mu_{h_i}, \boldsymbol\Sigma_{h_i})`
    with full covariances (Cholesky factors), :math:`q(\mathbf b) =
    \mathcal N(\boldsymbol\mu_b, \sigma_b \mathbf I)` and :math:`q(\mathbf m_v) =
    \mathcal N(\boldsymbol\mu_{m_v}, \sigma_{m_v} \mathbf I)` isotropic
    (:math:`\sigma` are variances, as in the thesis), :math:`q(\alpha) =
    \Gamma(\bar a, \bar b)`, :math:`q(\lambda_v) = \Gamma(\bar c_v, \bar d_v)`
    (and :math:`q(\beta) = \Gamma` when ``learn_beta``).  SVI and CAVI then
    optimise the same objective over the same family: ``-loss`` estimates the
    closed-form CAVI ELBO at the same variational parameters.  Only for
    ``model_name="lmpromp"``.
``autonormal`` (``svi_autonormal``)
    ``numpyro.infer.autoguide.AutoNormal`` (fully factorised Gaussian on the
    unconstrained scale).
``lowrank`` (``svi_lowrank``)
    ``AutoLowRankMultivariateNormal``: a Gaussian with covariance
    :math:`\mathbf W \mathbf W^T + \mathrm{diag}(\mathbf s^2)` of rank ``rank``
    (numpyro's default :math:`\lceil\sqrt{n}\rceil` for ``n`` unconstrained
    dimensions when ``rank`` is None).

The automatic guides run, by default, on the model **collapsed over w**
(``collapsed="w"``, :mod:`lmpromp_ppl.models.collapsed`), the same model that
NUTS samples: a guide then approximates only :math:`p(\theta, \mathbf h | \mathbf y)`
and ``w`` is drawn from the exact conditional :math:`p(\mathbf w | \theta,
\mathbf y)` for every draw from q (see :meth:`SviResult.sample`).
``collapsed="none"`` puts them on the full model.

Step size, plateaus and stopping rule
-------------------------------------
Adam's step size lives in the optimiser state (``_adam``), so it can change
between compiled chunks.  Steps run in chunks of ``window`` steps, each chunk one
compiled ``lax.scan``.  After each chunk the mean loss of the chunk (a moving
average over ``window`` steps, which smooths the Monte Carlo noise of
single-step losses) is compared with that of the previous chunk.  A **plateau**
is a change below ``stop_tol`` relative to the loss or below twice its Monte
Carlo standard error (``sqrt(var_prev / n + var_cur / n)`` from the
single-step losses of the two chunks: no progress is detectable through the
noise).  With a constant step size Adam's iterates do not converge but
fluctuate about the optimum, at a distance that grows with the step size (on
LASA GShape, L = 7, d = 20, V = 2, step 0.01 leaves the iterates of
``svi_meanfield`` about 40 nats below CAVI's bound); so on each of the first
``plateau_reductions`` plateaus the step size is multiplied by
``plateau_factor`` and the run goes on, and the next plateau stops it,
``converged=True``.  Otherwise the run ends at ``num_steps`` (rounded up to a
whole number of chunks, with a ``ConvergenceWarning``).  ``stop_tol=0``
disables the rule and the reductions (every step is run at the scheduled step
size).  ``learning_rate_decay`` additionally shrinks the step size
geometrically per step.

The returned parameters are the **average of the iterates over the last
chunk** (Polyak-Ruppert averaging, on the unconstrained scale), which removes
most of the remaining fluctuation.  Measured on the test problem of
``tests/test_svi.py`` (L = 4, d = 6, V = 2), from CAVI's initialisation,
``svi_meanfield`` ends within 0.1 % of CAVI's gain of CAVI's ELBO; on LASA
GShape with the default options it stops after 7000-12000 steps 4-7 nats
below CAVI's ELBO of 612 (the plain constant-step run stopped 139 nats below).
Lower-variance estimators do not help here: ``TraceMeanField_ELBO`` (analytic
KL for ``b``, ``M``, ``alpha``, ``lam``), and an analytic KL for ``w`` too,
gave no faster progress, since for ``w`` the Monte Carlo log-density ratio
cancels much of the likelihood's noise.  Steps whose loss or gradient is
not finite are skipped (``SVI.stable_update``).

Timing: ``compile_seconds`` covers ``SVI.init`` and the ahead-of-time compilation
of the chunk (cached per static configuration); ``seconds`` the optimisation.
"""

from __future__ import annotations

import time
import warnings
from functools import partial
from typing import Any, Callable, Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax
from numpyro.infer import SVI, Predictive, Trace_ELBO
from numpyro.optim import _NumPyroOptim

from lmpromp_ppl._keys import raw_key, typed_key
from lmpromp_ppl._progress import line_reporter
from lmpromp_ppl.data.core import ModelData, as_float64
from lmpromp_ppl.errors import ConvergenceWarning, LmprompError
from lmpromp_ppl.inference.compiled import compile_in_background, lookup, remember
from lmpromp_ppl.inference.svi_guides import (
    GUIDES,
    cavi_state_from_meanfield,
    make_guide,
    meanfield_guide,
    meanfield_init,
    meanfield_params_from_cavi,
)
from lmpromp_ppl.models.conditionals import draw_integrated_sites
from lmpromp_ppl.models.hyper import Hyperparameters
from lmpromp_ppl.models.lmpromp import check_observations
from lmpromp_ppl.models.registry import model_inputs, resolve_collapse, site_shapes

__all__ = [
    "GUIDES",
    "SviContext",
    "SviResult",
    "make_guide",
    "meanfield_guide",
    "meanfield_init",
    "meanfield_params_from_cavi",
    "cavi_state_from_meanfield",
    "fit_svi",
    "DRAWS_AFTER_FIT",
]

#: Draws :func:`lmpromp_ppl.fit` takes from an SVI fit's guide, whose program :func:`fit_svi` compiles during the fit.
DRAWS_AFTER_FIT = 1000


class SviContext(NamedTuple):
    """Everything :meth:`SviResult.sample` needs besides the parameters."""

    model_name: str
    guide: str
    collapse: str
    rank: int | None
    data: ModelData
    hyper: Hyperparameters
    fixed: dict
    #: the fit's own (model, guide) pair: an automatic guide in it has already
    #: recorded its prototype trace, so drawing from it runs no eager model pass
    programs: tuple | None = None
    #: draw programs compiled (or compiling, as a ``concurrent.futures.Future``) while the fit ran,
    #: by number of draws (:func:`fit_svi`'s ``prepare_draws``)
    draw_programs: Mapping[int, Any] | None = None

    def model_and_guide(self):
        """The (model, guide) of the fit, or a fresh pair from :func:`make_guide`."""
        if self.programs is not None:
            return self.programs
        return make_guide(self.guide, self.model_name, self.data, self.hyper, collapsed=self.collapse,
                          rank=self.rank, fixed_names=tuple(sorted(self.fixed)))


class SviResult(NamedTuple):
    """What :func:`fit_svi` returns.

    Attributes
    ----------
    params : variational parameters (constrained values), name -> array:
        the average of the iterates over the last ``window`` steps, taken on
        the unconstrained scale
    loss_trace : (num_steps_run,) loss (negative ELBO estimate) per step
    num_steps_run : number of optimisation steps taken
    converged : whether the stopping rule fired before ``num_steps``
    seconds : optimisation time, excluding compilation
    compile_seconds : ``SVI.init`` and compilation time
    options : the engine options, for the result's attributes
    context : model, guide, data and hyperparameters, for :meth:`sample`
    """

    params: dict[str, np.ndarray]
    loss_trace: np.ndarray
    num_steps_run: int
    converged: bool
    seconds: float
    compile_seconds: float
    options: dict[str, Any]
    context: SviContext

    def importance_program(self, num_draws: int) -> tuple[Any, tuple]:
        """The lowered (not yet compiled) program of :meth:`importance_log_ratios`, and (model, guide, params, args).

        Lowering traces numpyro's handlers, whose stack is global, so it must run in the
        caller's thread; the returned ``jax.stages.Lowered`` can then be compiled anywhere,
        side by side with other programs (:func:`~lmpromp_ppl.inference.compiled.compile_side_by_side`).
        :meth:`importance_log_ratios` runs the compiled program.
        """
        from numpyro.handlers import seed
        from numpyro.infer.elbo import get_importance_log_probs

        ctx = self.context
        model, guide = ctx.model_and_guide()
        params = {k: jnp.asarray(v) for k, v in self.params.items()}
        args = (self._inputs(), ctx.fixed)
        if ctx.programs is None and ctx.guide != "meanfield":
            # An autoguide sets itself up on its first call by running the model under the
            # enclosing seed handler, which would shift the particles of that first call;
            # set it up here so every call with a key draws the same particles (the fit's
            # own guide, in ``programs``, is set up already).
            get_importance_log_probs(seed(model, 0), seed(guide, 0), args, {}, params)

        def one(k):
            k_model, k_guide = jax.random.split(k)
            lp_model, lp_guide = get_importance_log_probs(seed(model, k_model), seed(guide, k_guide), args, {}, params)
            return sum(v.sum() for v in lp_model.values()) - sum(v.sum() for v in lp_guide.values())

        keys = jax.ShapeDtypeStruct((int(num_draws),), jax.random.split(jax.random.key(0), 1).dtype)
        return jax.jit(jax.vmap(one)).lower(keys), (model, guide, params, args)

    def importance_log_ratios(self, key: jax.Array, num_draws: int, program=None) -> tuple[np.ndarray, tuple]:
        """log p - log q for ``num_draws`` particles of the guide, and (model, guide, params, args).

        The model is the guide's own (collapsed over ``w`` for the automatic guides,
        where ``w`` given theta is exact and cancels from the ratio), through
        numpyro's importance traces; used for the PSIS k-hat of the fit.  ``program``:
        (the compiled program of :meth:`importance_program` for ``num_draws``, its context);
        built here when None.
        """
        if program is None:
            lowered, context = self.importance_program(num_draws)
            program = (lowered.compile(), context)
        executable, context = program
        # the program takes typed keys (a raw key gives the same stream)
        return np.asarray(executable(jax.random.split(typed_key(key), num_draws))), context

    def _inputs(self):
        """The model inputs the fit evaluated (:func:`~lmpromp_ppl.models.registry.model_inputs`)."""
        ctx = self.context
        return model_inputs(ctx.model_name, "none" if ctx.guide == "meanfield" else ctx.collapse, ctx.data)

    def sample(self, key: jax.Array, num_draws: int) -> dict[str, np.ndarray]:
        r"""Draws from q with the contract's site names, each (num_draws, ...).

        Latent and deterministic sites of the model come from the guide (through
        ``numpyro.infer.Predictive``); on a collapsed model ``w`` (and ``h``) are
        then drawn from :math:`p(\mathbf w | \theta, \mathbf y)` for each draw.
        Sites held through ``fixed`` are left out.
        """
        ctx = self.context
        num_draws = int(num_draws)
        if num_draws < 1:
            raise LmprompError(f"num_draws must be >= 1, got {num_draws}")
        program = (ctx.draw_programs or {}).get(num_draws)
        program = _draw_function(ctx, num_draws) if program is None else program.result()
        params = {k: jnp.asarray(v) for k, v in self.params.items()}
        draws = program(raw_key(key), params, self._inputs(), ctx.data, ctx.fixed)
        return {k: np.asarray(v) for k, v in draws.items()}


def _draw_function(ctx: SviContext, num_draws: int) -> Callable:
    """The jitted ``draw(key, params, inputs, data, fixed)`` of :meth:`SviResult.sample`: one program for the
    guide's draws and the integrated sites (op by op, each distinct operation of the model would compile
    on its own)."""
    model, guide = ctx.model_and_guide()
    sites = sorted(site_shapes(model, ctx.data, ctx.fixed, deterministic=True))
    collapse = "none" if ctx.guide == "meanfield" else ctx.collapse

    def draw(key, params, inputs, data, fixed):
        key_q, key_cond = jax.random.split(key)
        predictive = Predictive(model, guide=guide, params=params, num_samples=num_draws, return_sites=sites)
        # the model evaluates its fastest inputs (shared-design statistics where possible)
        draws = dict(predictive(key_q, inputs, fixed))
        if collapse != "none":
            flat = dict(draws)
            flat.update({k: jnp.broadcast_to(v, (num_draws,) + v.shape) for k, v in fixed.items()})
            draws.update(draw_integrated_sites(ctx.model_name, collapse, key_cond, data, ctx.hyper, flat))
        return draws

    return jax.jit(draw)


def _adam(rate: float, decay: float, b1: float = 0.9, b2: float = 0.999, eps: float = 1e-8):
    r"""Adam (Kingma & Ba 2015) whose step size is part of the optimiser state.

    The step size at step ``i`` is ``r * decay ** i`` with ``r`` held in the
    state ``(params, m, v, r)``, so that :func:`fit_svi` can lower it between
    compiled chunks (on a plateau) without recompiling.  Returns numpyro's
    ``(init_fn, update_fn, get_params_fn)`` triple, wrapped by ``_NumPyroOptim``.
    """

    def init_fn(params):
        zeros = jax.tree.map(jnp.zeros_like, params)
        return params, zeros, zeros, jnp.asarray(rate, dtype=jnp.float64)

    def update_fn(i, grads, state):
        params, m, v, r = state
        m = jax.tree.map(lambda a, g: b1 * a + (1 - b1) * g, m, grads)
        v = jax.tree.map(lambda a, g: b2 * a + (1 - b2) * g**2, v, grads)
        t = i + 1
        step = r * decay**i
        params = jax.tree.map(lambda x, a, c: x - step * (a / (1 - b1**t)) / (jnp.sqrt(c / (1 - b2**t)) + eps),
                              params, m, v)
        return params, m, v, r

    return init_fn, update_fn, lambda state: state[0]


def _with_rate(state, rate: float):
    """The SVI state with the optimiser's step size set to ``rate``."""
    i, (params, m, v, _) = state.optim_state
    return state._replace(optim_state=(i, (params, m, v, jnp.asarray(rate, dtype=jnp.float64))))


def _eager_init(svi: SVI, key: Array, data: ModelData, fixed: dict, init: dict):
    return svi.init(key, data, fixed, init_params=init or None)


def fit_svi(
    model_name: str,
    data: ModelData,
    hyper: Hyperparameters,
    key: jax.Array,
    *,
    guide: str = "lowrank",
    collapsed: str = "w",
    num_steps: int = 20000,
    learning_rate: float = 0.01,
    learning_rate_decay: float = 1.0,
    num_particles: int = 1,
    rank: int | None = None,
    stop_tol: float = 1e-4,
    window: int = 500,
    plateau_reductions: int = 5,
    plateau_factor: float = 0.5,
    progress: bool = False,
    init_params: Mapping[str, Any] | None = None,
    fixed: Mapping[str, Any] | None = None,
    prepare_draws: int = DRAWS_AFTER_FIT,
) -> SviResult:
    r"""Fit a guide to the posterior of a declared model by SVI (Adam on the ELBO).

    Parameters
    ----------
    model_name : ``"promp"``, ``"lmpromp"`` or ``"mixture"``
    data : padded model inputs ``(psi (L, S, d), y (L, S), mask (L, S))``
    hyper : hyperparameters
    key : PRNG key (typed or raw)
    guide : ``"meanfield"``, ``"autonormal"`` or ``"lowrank"`` (module docstring)
    collapsed : model of the automatic guides: ``"w"`` (default), ``"wh"``, ``"none"``
    num_steps : maximum number of steps (rounded up to a multiple of ``window``)
    learning_rate : initial Adam step size
    learning_rate_decay : the step size at step ``i`` is
        ``rate * learning_rate_decay ** i`` (1: constant), ``rate`` being
        ``learning_rate`` times ``plateau_factor`` per plateau met so far
    num_particles : Monte Carlo samples per ELBO gradient estimate
    rank : rank of the low-rank guide
    stop_tol : a plateau is a change of the ``window``-step mean loss below
        this relative tolerance or below twice its Monte Carlo standard error
        (module docstring); 0 disables the rule (and the step-size reductions)
    window : steps per chunk, the smoothing window of the stopping rule and
        the averaging window of the returned parameters
    plateau_reductions : number of plateaus on which the step size is
        multiplied by ``plateau_factor`` before the next plateau stops the run
    plateau_factor : step-size reduction factor on a plateau, in (0, 1)
    progress : True prints the mean loss of each chunk to stderr; or a callable
        ``(steps, mean loss) -> None`` called after each chunk
    init_params : initial (constrained) values of variational parameters; for
        the meanfield guide the default is :func:`meanfield_init`
    fixed : values at which some latent sites are held (automatic guides)
    prepare_draws : the program of :meth:`SviResult.sample` for this many draws compiles in
        the background while the fit runs (:data:`DRAWS_AFTER_FIT`, what :func:`lmpromp_ppl.fit`
        draws first); 0 for none

    Returns
    -------
    SviResult
    """
    if not isinstance(hyper, Hyperparameters):
        raise LmprompError("hyper must be a Hyperparameters instance")
    for name, value, minimum in (("num_steps", num_steps, 1), ("num_particles", num_particles, 1),
                                 ("window", window, 2), ("plateau_reductions", plateau_reductions, 0)):
        if isinstance(value, bool) or int(value) != value or value < minimum:
            raise LmprompError(f"{name} must be an integer >= {minimum}, got {value!r}")
    if not (np.isfinite(learning_rate) and learning_rate > 0):
        raise LmprompError(f"learning_rate must be positive, got {learning_rate!r}")
    if not (np.isfinite(plateau_factor) and 0 < plateau_factor < 1):
        raise LmprompError(f"plateau_factor must lie in (0, 1), got {plateau_factor!r}")
    if not (np.isfinite(stop_tol) and stop_tol >= 0):
        raise LmprompError(f"stop_tol must be non-negative, got {stop_tol!r}")
    collapse = resolve_collapse(model_name, collapsed)
    data = as_float64(data)  # compact inputs stay compact: the densities evaluate statistics
    check_observations(data)  # shape and value checks with their own messages
    fixed = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in (fixed or {}).items()}
    model, guide_fn = make_guide(guide, model_name, data, hyper, collapsed=collapse, rank=rank,
                                 fixed_names=tuple(sorted(fixed)))
    if guide == "meanfield":
        init = meanfield_init(data, hyper)
        init.update(init_params or {})
    else:
        init = dict(init_params or {})
    init = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in init.items()}
    # the automatic guides' model evaluates the fastest equal form of the data
    # (shared-design statistics where possible; the meanfield guide's model is the full one)
    inputs = model_inputs(model_name, "none" if guide == "meanfield" else collapse, data)

    if not (np.isfinite(learning_rate_decay) and 0 < learning_rate_decay <= 1):
        raise LmprompError(f"learning_rate_decay must lie in (0, 1], got {learning_rate_decay!r}")
    cache_key = (model_name, guide, collapse, rank, hyper, float(learning_rate_decay),
                 int(num_particles), int(window), tuple(sorted(fixed)),
                 jax.tree_util.tree_structure((inputs, fixed, init)),
                 tuple((jnp.shape(a), jnp.result_type(a)) for a in jax.tree_util.tree_leaves((inputs, fixed, init))))
    start = time.perf_counter()
    cached = lookup(cache_key)
    if cached is None:
        svi = SVI(model, guide_fn, _NumPyroOptim(_adam, float(learning_rate), float(learning_rate_decay)),
                  Trace_ELBO(num_particles=int(num_particles)))

        def run_chunk(state, data, fixed):
            """``window`` steps; their losses and the mean of the unconstrained iterates."""
            def body(carry, _):
                state, total = carry
                state, loss = svi.stable_update(state, data, fixed)
                return (state, jax.tree.map(jnp.add, total, svi.optim.get_params(state.optim_state))), loss

            zeros = jax.tree.map(jnp.zeros_like, svi.optim.get_params(state.optim_state))
            (state, total), loss = lax.scan(body, (state, zeros), None, length=int(window))
            return state, loss, jax.tree.map(lambda t: t / window, total)

        if guide == "meanfield":
            # the hand-written guide has no side effects: compile its initialisation too
            init_fn = jax.jit(lambda k, d, f, p: svi.init(k, d, f, init_params=p))
        else:
            # an autoguide records its prototype trace on first call: initialise eagerly
            init_fn = partial(_eager_init, svi)
        state = init_fn(raw_key(key), inputs, fixed, init)
        draw_programs = {}
        if prepare_draws:
            # lowered here (numpyro's handler stack is global), compiled beside the chunk and the run
            pending = SviContext(model_name, guide, collapse, rank, data, hyper, fixed, (svi.model, svi.guide))
            key_shape = jax.ShapeDtypeStruct((2,), jnp.uint32)
            lowered = _draw_function(pending, int(prepare_draws)).lower(
                key_shape, jax.eval_shape(svi.get_params, state), inputs, data, fixed)
            draw_programs[int(prepare_draws)] = compile_in_background(lowered)
        chunk = jax.jit(run_chunk).lower(state, inputs, fixed).compile()
        cached = (svi, init_fn, chunk, draw_programs)
        remember(cache_key, cached)
    else:
        svi, init_fn, chunk, draw_programs = cached
        state = init_fn(raw_key(key), inputs, fixed, init)
    rate = float(learning_rate)
    state = jax.block_until_ready(_with_rate(state, rate))
    compile_seconds = time.perf_counter() - start

    report = line_reporter(progress, f"svi_{guide}")
    start = time.perf_counter()
    losses: list[np.ndarray] = []
    converged = False
    reductions = 0
    previous = None  # mean loss of the previous chunk
    previous_var = None  # variance of the mean loss of the previous chunk
    while len(losses) * window < num_steps:
        state, chunk_loss, average = chunk(state, inputs, fixed)
        chunk_loss = np.asarray(chunk_loss)
        losses.append(chunk_loss)
        finite = chunk_loss[np.isfinite(chunk_loss)]
        current = float(np.mean(finite)) if finite.size else None
        current_var = float(np.var(finite) / finite.size) if finite.size > 1 else None
        if report is not None and current is not None:
            report(len(losses) * window, current)
        if previous is not None and current is not None and stop_tol > 0:
            noise = 2.0 * np.sqrt(previous_var + current_var) if None not in (previous_var, current_var) else 0.0
            if abs(current - previous) <= max(stop_tol * abs(previous), noise):
                if reductions == plateau_reductions:
                    converged = True
                    break
                reductions += 1
                rate *= plateau_factor
                state = _with_rate(state, rate)
        previous, previous_var = current, current_var
    seconds = time.perf_counter() - start
    if not converged:
        warnings.warn(f"svi_{guide} stopped at its step limit ({num_steps}) before the "
                      f"smoothed loss changed by less than {stop_tol}", ConvergenceWarning, stacklevel=2)
    params = {k: np.asarray(v) for k, v in jax.jit(svi.constrain_fn)(average).items()}
    loss_trace = np.concatenate(losses)
    options = {"guide": guide, "collapsed": "none" if guide == "meanfield" else collapse,
               "num_steps": int(num_steps), "learning_rate": float(learning_rate),
               "learning_rate_decay": float(learning_rate_decay),
               "num_particles": int(num_particles), "rank": rank, "stop_tol": float(stop_tol),
               "window": int(window), "plateau_reductions": int(plateau_reductions),
               "plateau_factor": float(plateau_factor), "final_learning_rate": rate, "fixed": sorted(fixed)}
    context = SviContext(model_name, guide, collapse, rank, data, hyper, fixed, (svi.model, svi.guide), draw_programs)
    return SviResult(params, loss_trace, int(loss_trace.shape[0]), converged, seconds, compile_seconds,
                     options, context)

r"""CAVI replicates as one ``jax.vmap``-ed fit over a leading dataset axis.

Simulation-based calibration fits the same model to hundreds of simulated
datasets of one shape.  :func:`fit_cavi_batched` initialises every replicate
with the thesis's start (ridge regression + PCA, Sec. 4.1.1,
:func:`lmpromp_ppl.inference.init.init_state`; NumPy and scikit-learn, so one
replicate at a time), stacks the states and runs the sweeps of
:func:`lmpromp_ppl.inference.cavi.step` (the updates of eq. 4.3, App. B.1) for
all replicates in one compiled, vectorised ``lax.while_loop``.  Under
``vmap`` the loop runs until every replicate has met its own tolerance; a
replicate that has converged keeps its state (``while_loop``'s batched
predicate selects the old carry), so each replicate's result is the one
:func:`lmpromp_ppl.inference.cavi.fit_cavi` would return for it (one start).

Why not :func:`lmpromp_ppl.inference.cavi.run`: it calls an ahead-of-time
compiled executable, which cannot be traced by ``vmap``; the loop here has
the same stopping rule (relative ELBO change below ``tol``, NaN, or
``max_iter``) built on the public :func:`~lmpromp_ppl.inference.cavi.step`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from lmpromp_ppl.data.core import ModelData
from lmpromp_ppl.errors import DataError, LmprompError
from lmpromp_ppl.inference import cavi
from lmpromp_ppl.inference.cavi import CaviState, HyperArrays
from lmpromp_ppl.models.hyper import Hyperparameters

__all__ = ["BatchedCaviFit", "fit_cavi_batched", "replicate_state", "sample_q_batched"]


class BatchedCaviFit(NamedTuple):
    """Result of :func:`fit_cavi_batched`.

    Attributes
    ----------
    state : :class:`~lmpromp_ppl.inference.cavi.CaviState` whose leaves carry a
        leading replicate axis (R, ...)
    elbo : (R,) final ELBO of each replicate
    iterations : (R,) sweeps run by each replicate
    converged : (R,) whether each replicate met the tolerance
    seconds : wall time of the batched loop, excluding compilation
    compile_seconds : compilation time (0 when already compiled in this process)
    """

    state: CaviState
    elbo: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    seconds: float
    compile_seconds: float


def _iterate_one(state: CaviState, data: cavi.CaviData, hyper: HyperArrays, tol: Array, max_iter: Array):
    """Sweep one replicate until its relative ELBO change is below ``tol`` (or NaN, or ``max_iter``)."""

    def cond(carry):
        _, iteration, previous, converged = carry
        return (iteration < max_iter) & ~converged & ~jnp.isnan(previous)

    def body(carry):
        state, iteration, previous, _ = carry
        state, info = cavi.step(state, data, hyper)
        converged = jnp.abs(info.elbo - previous) <= tol * jnp.abs(info.elbo)
        return state, iteration + 1, info.elbo, converged

    carry = (state, jnp.zeros((), jnp.int32), jnp.asarray(-jnp.inf, jnp.float64), jnp.zeros((), jnp.bool_))
    return jax.lax.while_loop(cond, body, carry)


_batched_iterate = jax.jit(jax.vmap(_iterate_one, in_axes=(0, 0, None, None, None)))
_COMPILED: dict = {}


def _stack(trees: Sequence) -> object:
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *trees)


def fit_cavi_batched(
    datasets: Sequence[ModelData],
    hyper: Hyperparameters,
    *,
    tol: float = 1e-8,
    max_iter: int = 2000,
) -> BatchedCaviFit:
    """Fit the single-type LMProMP by CAVI to R datasets of one shape at once.

    Parameters
    ----------
    datasets : R :class:`ModelData` with identical shapes and the same design
        path (all sharing one design matrix within each dataset, or none)
    hyper : hyperparameters (single component, fixed beta; the thesis's
        column-wise family)
    tol : relative ELBO tolerance of each replicate
    max_iter : maximum sweeps per replicate

    Returns
    -------
    BatchedCaviFit
    """
    from lmpromp_ppl.inference.init import init_state  # init imports cavi

    if not isinstance(hyper, Hyperparameters):
        raise LmprompError(f"hyper must be a Hyperparameters, got {type(hyper).__name__}")
    if hyper.num_components != 1 or hyper.learn_beta:
        raise LmprompError("batched CAVI fits the single-type model with a fixed beta (num_components=1)")
    if not (isinstance(tol, (int, float)) and tol > 0 and math.isfinite(tol)):
        raise LmprompError(f"tol must be a positive number, got {tol!r}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
        raise LmprompError(f"max_iter must be an integer >= 1, got {max_iter!r}")
    datasets = list(datasets)
    if not datasets:
        raise DataError("fit_cavi_batched needs at least one dataset")
    shapes = {tuple(np.shape(a) for a in d) for d in datasets}
    if len(shapes) != 1:
        raise DataError(f"all datasets must have the same shapes, got {sorted(shapes)}")
    prepared = [cavi.prepare_cavi_data(d) for d in datasets]
    paths = {type(p.gram).__name__ for p in prepared}
    if len(paths) != 1:
        raise DataError("all datasets must share their design matrix the same way (fast path or not)")
    hyper.validate_for(datasets[0].num_weights, datasets[0].num_demos)
    states = _stack([init_state(p, hyper) for p in prepared])
    data = _stack(prepared)
    args = (states, data, cavi.hyper_arrays(hyper), jnp.asarray(tol, jnp.float64),
            jnp.asarray(max_iter, jnp.int32))
    leaves, treedef = jax.tree.flatten(args)
    cache_key = (treedef, tuple((np.shape(x), jnp.asarray(x).dtype) for x in leaves))
    start = time.perf_counter()
    compiled = _COMPILED.get(cache_key)
    if compiled is None:
        compiled = _COMPILED[cache_key] = _batched_iterate.lower(*args).compile()
        compile_seconds = time.perf_counter() - start
    else:
        compile_seconds = 0.0
    start = time.perf_counter()
    state, iterations, elbo, converged = jax.block_until_ready(compiled(*args))
    seconds = time.perf_counter() - start
    return BatchedCaviFit(state, np.asarray(elbo), np.asarray(iterations), np.asarray(converged),
                          seconds, compile_seconds)


def replicate_state(fit: BatchedCaviFit, index: int) -> CaviState:
    """The :class:`~lmpromp_ppl.inference.cavi.CaviState` of replicate ``index``."""
    return jax.tree.map(lambda leaf: leaf[index], fit.state)


@jax.jit
def _sample_batched(keys: Array, state: CaviState, template: Array) -> dict[str, Array]:
    return jax.vmap(lambda k, s: cavi.sample_q(k, s, template.shape[0]))(keys, state)


def sample_q_batched(key: Array, fit: BatchedCaviFit, num_draws: int) -> dict[str, np.ndarray]:
    """Independent draws from each replicate's q: site -> (R, num_draws, ...) (:func:`cavi.sample_q`)."""
    if isinstance(num_draws, bool) or int(num_draws) != num_draws or num_draws < 1:
        raise LmprompError(f"num_draws must be a positive integer, got {num_draws!r}")
    num_replicates = fit.elbo.shape[0]
    keys = jax.random.split(key, num_replicates)
    draws = _sample_batched(keys, fit.state, jnp.zeros(int(num_draws)))
    return {name: np.asarray(value) for name, value in draws.items()}

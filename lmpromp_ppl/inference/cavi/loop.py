r"""One sweep and the compiled loop of sweeps.

:func:`step` applies every update of :func:`~.updates.updates_for` in sweep
order, then :func:`~.updates.prune` (a no-op for the single type), and returns
the bound.  :func:`iterate` is the traceable ``lax.while_loop`` of sweeps (used
under ``vmap`` by the batched fits and the split-and-merge search);
:func:`run` calls it compiled ahead of time, in chunks when a progress callback
is given.
"""

from __future__ import annotations

import time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from lmpromp_ppl.inference.cavi.bound import elbo
from lmpromp_ppl.inference.cavi.data import CaviData
from lmpromp_ppl.inference.cavi.state import CaviHyper, CaviInfo, CaviState
from lmpromp_ppl.inference.cavi.updates import prune, updates_for
from lmpromp_ppl.inference.compiled import compiled

__all__ = ["step", "iterate", "compiled_iterate", "RunResult", "run", "CHUNK"]

#: Sweeps between two progress reports of :func:`run`.
CHUNK = 50


@jax.jit
def step(state: CaviState, data: CaviData, hyper: CaviHyper) -> tuple[CaviState, CaviInfo]:
    """One sweep over :func:`~.updates.updates_for` (``state``), then :func:`~.updates.prune`; the state and its ELBO."""
    for update in updates_for(state).values():
        state = update(state, data, hyper)
    state = prune(state, hyper)
    return state, CaviInfo(elbo(state, data, hyper))


class Iteration(NamedTuple):
    """Output of :func:`iterate`: final state, (buffer,) ELBO trace (NaN after the last sweep), sweeps,
    converged, and the last ELBO (also when the trace is shorter than the run)."""

    state: CaviState
    elbo_trace: Array
    iterations: Array
    converged: Array
    elbo: Array


def iterate(
    state: CaviState,
    data: CaviData,
    hyper: CaviHyper,
    tol: Array,
    limit: Array,
    elbo_previous: Array,
    buffer: int,
) -> Iteration:
    """Sweep until the relative ELBO change is below ``tol``, at most ``limit`` times, or NaN.

    The ELBO of the first ``buffer`` sweeps is kept in the trace (later ones are
    dropped; ``buffer=0`` keeps none, for batches of many fits).
    """

    def cond(carry):
        _, iteration, previous, _, converged = carry
        return (iteration < limit) & ~converged & ~jnp.isnan(previous)

    def body(carry):
        state, iteration, previous, trace, _ = carry
        state, info = step(state, data, hyper)
        converged = jnp.abs(info.elbo - previous) <= tol * jnp.abs(info.elbo)
        if buffer:  # sweeps past the buffer are dropped (out-of-bounds updates are no-ops)
            trace = trace.at[iteration].set(info.elbo)
        return state, iteration + 1, info.elbo, trace, converged

    carry = (
        state,
        jnp.zeros((), jnp.int32),
        jnp.asarray(elbo_previous, jnp.float64),
        jnp.full((buffer,), jnp.nan),
        jnp.zeros((), jnp.bool_),
    )
    state, iteration, last, trace, converged = jax.lax.while_loop(cond, body, carry)
    return Iteration(state, trace, iteration, converged, last)


_iterate_jit = jax.jit(iterate, static_argnames="buffer")


def compiled_iterate(state: CaviState, data: CaviData, hyper: CaviHyper, buffer: int) -> tuple[Callable, float]:
    """:func:`iterate` compiled ahead of time for these shapes and ``buffer``; (executable, compile seconds).

    Call ``executable(state, data, hyper, tol, limit, elbo_previous)`` with arrays
    (``tol < 0`` never stops early; the trace keeps the first ``buffer`` sweeps).
    """
    probe = (state, data, hyper, jnp.asarray(0.0, jnp.float64), jnp.asarray(buffer, jnp.int32),
             jnp.asarray(-jnp.inf))
    return compiled(_iterate_jit, probe, buffer=int(buffer))


class RunResult(NamedTuple):
    """Output of :func:`run`.

    Attributes
    ----------
    state : final state
    elbo_trace : (iterations,) ELBO after each sweep
    iterations : sweeps run
    converged : the relative ELBO change fell below ``tol``
    seconds : wall time of the sweeps, excluding compilation
    compile_seconds : ahead-of-time compilation (0 when already compiled in this process)
    """

    state: CaviState
    elbo_trace: np.ndarray
    iterations: int
    converged: bool
    seconds: float
    compile_seconds: float


def run(
    state: CaviState,
    data: CaviData,
    hyper: CaviHyper,
    tol: float,
    max_iter: int,
    *,
    callback: Callable[[int, float], None] | None = None,
) -> RunResult:
    """Iterate :func:`step` in a compiled ``lax.while_loop``.

    Stops when :math:`|\\Delta\\mathcal L| \\le` ``tol`` :math:`|\\mathcal L|`, when the ELBO
    is NaN, or after ``max_iter`` sweeps.  The loop is compiled ahead of time once
    per argument shapes and chunk size (:mod:`lmpromp_ppl.inference.compiled`).
    With ``callback``, the loop runs in chunks of :data:`CHUNK` sweeps and calls
    ``callback(sweeps done, ELBO)`` after each (the progress of a fit); the result
    is the same.  Call ``run`` outside ``jax.jit``.
    """
    max_iter = int(max_iter)
    chunk = min(max_iter, CHUNK) if callback is not None else max_iter
    tol_arr = jnp.asarray(tol, jnp.float64)
    previous = jnp.asarray(-jnp.inf)
    executable, compile_seconds = compiled_iterate(state, data, hyper, chunk)
    traces, done, seconds = [], 0, 0.0
    while True:
        limit = jnp.asarray(min(chunk, max_iter - done), jnp.int32)
        start = time.perf_counter()
        result = executable(state, data, hyper, tol_arr, limit, previous)
        jax.block_until_ready(result)
        seconds += time.perf_counter() - start
        n = int(result.iterations)
        traces.append(np.asarray(result.elbo_trace[:n]))
        done += n
        state = result.state
        if callback is not None and n:
            callback(done, float(traces[-1][-1]))
        if bool(result.converged) or done >= max_iter or n == 0 or np.isnan(traces[-1][-1]):
            break
        previous = result.elbo_trace[n - 1]
    return RunResult(state, np.concatenate(traces), done, bool(result.converged), seconds, compile_seconds)

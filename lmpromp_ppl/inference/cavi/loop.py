r"""One sweep and the compiled loop of sweeps.

:func:`step` applies every update of :func:`~.updates.updates_for` in sweep
order, then :func:`~.updates.prune` (a no-op for the single type), then the
transformations that cannot lower the bound (:mod:`.transform`;
``hyper.transform``), and returns the bound; :func:`iterate` keeps an
extrapolation along the sweep when its bound is higher (:mod:`.accelerate`;
``hyper.overrelax``).  :func:`iterate` is the traceable ``lax.while_loop`` of sweeps (used
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

from lmpromp_ppl.inference.cavi.accelerate import GROWTH, MAX_ETA, extrapolate
from lmpromp_ppl.inference.cavi.bound import elbo
from lmpromp_ppl.inference.cavi.data import CaviData, DiagonalGram
from lmpromp_ppl.inference.cavi.eigenbasis import from_eigenbasis, rotates, to_eigenbasis
from lmpromp_ppl.inference.cavi.state import CaviHyper, CaviInfo, CaviState
from lmpromp_ppl.inference.cavi.transform import rotate_latent, scale_directions, scale_latent
from lmpromp_ppl.inference.cavi.updates import prune, updates_for
from lmpromp_ppl.inference.compiled import compiled

__all__ = ["sweep", "step", "Resume", "fresh", "iterate", "compiled_iterate", "RunResult", "run", "CHUNK"]

#: Sweeps between two progress reports of :func:`run`.
CHUNK = 50
#: The rotation of :func:`~.transform.rotate_latent` precedes a sweep once the last relative change of the
#: bound is below this (rotating from the start took a synthetic fit to a worse optimum, :mod:`.transform`).
ROTATE_BELOW = 1e-4


def sweep(state: CaviState, data: CaviData, hyper: CaviHyper) -> CaviState:
    """The updates of :func:`~.updates.updates_for` (``state``) in order, :func:`~.updates.prune`, then the
    transformations of :mod:`.transform` when ``hyper.transform`` (traceable; no bound)."""
    for update in updates_for(state).values():
        state = update(state, data, hyper)
    state = prune(state, hyper)
    if isinstance(data.gram, DiagonalGram) and state.resp is None:  # the single type on a shared design
        transform = lambda s: scale_directions(scale_latent(s, hyper), data, hyper)  # noqa: E731
    else:
        transform = lambda s: scale_latent(s, hyper)  # noqa: E731
    return jax.lax.cond(hyper.transform > 0, transform, lambda s: s, state)


@jax.jit
def step(state: CaviState, data: CaviData, hyper: CaviHyper) -> tuple[CaviState, CaviInfo]:
    """One :func:`sweep`; the state and its ELBO."""
    state = sweep(state, data, hyper)
    return state, CaviInfo(elbo(state, data, hyper))


class Resume(NamedTuple):
    """What a loop of sweeps carries from one sweep to the next besides the state, so that a loop run in
    chunks continues exactly where the last chunk stopped.

    Attributes
    ----------
    elbo : the bound after the last sweep (-inf before the first)
    eta : the step length of the next over-relaxed step (:mod:`.accelerate`)
    settled : the last relative change of the bound was below :data:`ROTATE_BELOW`
    """

    elbo: Array
    eta: Array
    settled: Array


def fresh() -> Resume:
    """The :class:`Resume` of a loop that starts from a new state."""
    return Resume(jnp.asarray(-jnp.inf, jnp.float64), jnp.asarray(GROWTH, jnp.float64), jnp.zeros((), jnp.bool_))


class Iteration(NamedTuple):
    """Output of :func:`iterate`: final state, (buffer,) ELBO trace (NaN after the last sweep), sweeps,
    converged, the last ELBO (also when the trace is shorter than the run), and the :class:`Resume`
    of a next chunk."""

    state: CaviState
    elbo_trace: Array
    iterations: Array
    converged: Array
    elbo: Array
    resume: Resume


def iterate(
    state: CaviState,
    data: CaviData,
    hyper: CaviHyper,
    tol: Array,
    limit: Array,
    resume: Resume,
    buffer: int,
) -> Iteration:
    """Sweep until the relative ELBO change is below ``tol``, at most ``limit`` times, or NaN.

    The ELBO of the first ``buffer`` sweeps is kept in the trace (later ones are
    dropped; ``buffer=0`` keeps none, for batches of many fits).  On shared-design
    data the sweeps run in the eigenbasis of the Gram matrix, O(L d V) each
    (:mod:`.eigenbasis`), and the state is returned in the original coordinates.
    """
    basis = None
    if rotates(state, data):
        basis = data.gram.basis
        state, data = to_eigenbasis(state, data)

    def cond(carry):
        _, iteration, previous, _, converged, _, _ = carry
        return (iteration < limit) & ~converged & ~jnp.isnan(previous)

    def body(carry):
        state, iteration, previous, trace, _, eta, settled = carry
        state = jax.lax.cond((hyper.transform > 0) & settled, lambda s: rotate_latent(s, hyper), lambda s: s, state)
        swept, info = step(state, data, hyper)
        state, value, eta = jax.lax.cond(
            hyper.overrelax > 0, overrelaxed, lambda *args: (swept, info.elbo, eta), state, swept, info.elbo, eta
        )
        change = jnp.abs(value - previous)
        converged = change <= tol * jnp.abs(value)
        settled = change <= ROTATE_BELOW * jnp.abs(value)
        if buffer:  # sweeps past the buffer are dropped (out-of-bounds updates are no-ops)
            trace = trace.at[iteration].set(value)
        return state, iteration + 1, value, trace, converged, eta, settled

    def overrelaxed(state, swept, value, eta):
        """The extrapolation of :mod:`.accelerate` when its bound beats the sweep's, and the next step length."""
        candidate = extrapolate(state, swept, eta)
        candidate_value = elbo(candidate, data, hyper)
        better = jnp.isfinite(candidate_value) & (candidate_value > value)
        chosen = jax.tree.map(lambda c, s: jnp.where(better, c, s), candidate, swept)
        eta = jnp.where(better, jnp.minimum(GROWTH * eta, MAX_ETA), jnp.maximum(eta / 2.0, GROWTH))
        return chosen, jnp.where(better, candidate_value, value), eta

    carry = (
        state,
        jnp.zeros((), jnp.int32),
        jnp.asarray(resume.elbo, jnp.float64),
        jnp.full((buffer,), jnp.nan),
        jnp.zeros((), jnp.bool_),
        jnp.asarray(resume.eta, jnp.float64),
        jnp.asarray(resume.settled, jnp.bool_),
    )
    state, iteration, last, trace, converged, eta, settled = jax.lax.while_loop(cond, body, carry)
    if basis is not None:
        state = from_eigenbasis(state, basis)
    return Iteration(state, trace, iteration, converged, last, Resume(last, eta, settled))


_iterate_jit = jax.jit(iterate, static_argnames="buffer")


def compiled_iterate(state: CaviState, data: CaviData, hyper: CaviHyper, buffer: int) -> tuple[Callable, float]:
    """:func:`iterate` compiled ahead of time for these shapes and ``buffer``; (executable, compile seconds).

    Call ``executable(state, data, hyper, tol, limit, resume)`` with arrays and a :class:`Resume`
    (``tol < 0`` never stops early; the trace keeps the first ``buffer`` sweeps).
    """
    probe = (state, data, hyper, jnp.asarray(0.0, jnp.float64), jnp.asarray(buffer, jnp.int32), fresh())
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
    per argument shapes (:mod:`lmpromp_ppl.inference.compiled`) and runs in chunks
    of :data:`CHUNK` sweeps, each continuing exactly where the last stopped
    (:class:`Resume`); with ``callback`` it calls ``callback(sweeps done, ELBO)``
    after each chunk (the progress of a fit).  Call ``run`` outside ``jax.jit``.
    """
    max_iter = int(max_iter)
    chunk = CHUNK  # one compiled program per shape, whatever max_iter and whether progress is shown
    tol_arr = jnp.asarray(tol, jnp.float64)
    resume = fresh()
    executable, compile_seconds = compiled_iterate(state, data, hyper, chunk)
    traces, done, seconds = [], 0, 0.0
    while True:
        limit = jnp.asarray(min(chunk, max_iter - done), jnp.int32)
        start = time.perf_counter()
        result = executable(state, data, hyper, tol_arr, limit, resume)
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
        resume = result.resume
    return RunResult(state, np.concatenate(traces), done, bool(result.converged), seconds, compile_seconds)

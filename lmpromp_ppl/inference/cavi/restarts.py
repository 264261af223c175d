"""Restarts of the CAVI loop and the result of a fit."""

from __future__ import annotations

import math
import warnings
from typing import Callable, NamedTuple

import numpy as np

from lmpromp_ppl.errors import ConvergenceWarning, EngineDivergedError, LmprompError
from lmpromp_ppl.inference.cavi.data import CaviData
from lmpromp_ppl.inference.cavi.loop import RunResult, run
from lmpromp_ppl.inference.cavi.state import CaviHyper, CaviState

__all__ = ["CaviFit", "check_options", "check_restart_bound", "best_fit", "best_of_restarts"]


class CaviFit(NamedTuple):
    """Result of :func:`lmpromp_ppl.inference.cavi.fit`.

    Attributes
    ----------
    state : best state over the restarts
    elbo : its final ELBO
    elbo_trace : (iterations,) ELBO after each sweep of the best restart
    iterations : sweeps run by the best restart
    converged : whether the best restart met the tolerance
    seconds : wall time of all restarts, excluding compilation
    compile_seconds : ahead-of-time compilation time (0 when already compiled in this process)
    restart_elbos : final ELBO of every restart, in order
    """

    state: CaviState
    elbo: float
    elbo_trace: np.ndarray
    iterations: int
    converged: bool
    seconds: float
    compile_seconds: float
    restart_elbos: list[float]


def check_options(tol, max_iter, num_restarts) -> None:
    """Validate the loop options of a fit."""
    if not (isinstance(tol, (int, float)) and not isinstance(tol, bool) and tol > 0 and math.isfinite(tol)):
        raise LmprompError(f"tol must be a positive number, got {tol!r}")
    for name, value in (("max_iter", max_iter), ("num_restarts", num_restarts)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise LmprompError(f"{name} must be an integer >= 1, got {value!r}")


def check_restart_bound(final: float, restart: int) -> float:
    """The final bound of a restart; a non-finite one is an :class:`~lmpromp_ppl.errors.EngineDivergedError`."""
    if not math.isfinite(final):
        raise EngineDivergedError(
            f"CAVI diverged (ELBO {final}) in restart {restart + 1}; check beta and the data scaling"
        )
    return final


def best_fit(result: RunResult, final: float, trace, seconds, compile_seconds, restart_elbos, *, tol, max_iter) -> CaviFit:
    """The :class:`CaviFit` of the best restart; warns when it stopped at ``max_iter``."""
    if not result.converged:
        warnings.warn(
            f"CAVI stopped at max_iter={max_iter} before the relative ELBO change fell below tol={tol}",
            ConvergenceWarning,
            stacklevel=4,
        )
    return CaviFit(
        state=result.state,
        elbo=final,
        elbo_trace=np.asarray(trace),
        iterations=int(np.size(trace)),
        converged=result.converged,
        seconds=seconds,
        compile_seconds=compile_seconds,
        restart_elbos=restart_elbos,
    )


def best_of_restarts(
    starts, data: CaviData, hyper: CaviHyper, tol: float, max_iter: int,
    callback: Callable[[int, float], None] | None = None,
) -> CaviFit:
    """Run every start with the compiled loop and keep the best final ELBO (warns at ``max_iter``).

    ``callback(sweeps, ELBO)`` counts the sweeps of all restarts together.
    """
    best, restart_elbos, seconds, compile_seconds, offset = None, [], 0.0, 0.0, 0
    for r, start in enumerate(starts):
        report = None if callback is None else (lambda done, value, o=offset: callback(o + done, value))
        result = run(start, data, hyper, float(tol), int(max_iter), callback=report)
        offset += result.iterations
        seconds += result.seconds
        compile_seconds += result.compile_seconds
        final = check_restart_bound(float(result.elbo_trace[-1]), r)
        restart_elbos.append(final)
        if best is None or final > best[0]:
            best = (final, result)
    final, result = best
    return best_fit(result, final, result.elbo_trace, seconds, compile_seconds, restart_elbos,
                    tol=tol, max_iter=max_iter)

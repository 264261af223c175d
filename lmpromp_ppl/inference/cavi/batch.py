r"""CAVI fitted to many datasets of one shape as one ``jax.vmap``-ed fit over a leading dataset axis.

Simulation-based calibration and the batch row of ``lmpromp bench`` fit the
same model to hundreds of datasets of one shape.  :func:`fit_cavi_batched`
runs the sweeps of :func:`lmpromp_ppl.inference.cavi.step` (the updates of
eq. 4.3, App. B.1) for all datasets in one compiled, vectorised
``lax.while_loop``.  It takes either

* a sequence of :class:`~lmpromp_ppl.data.core.ModelData`: each replicate
  starts at the thesis's initialisation (ridge regression + PCA, Sec. 4.1.1,
  :func:`lmpromp_ppl.inference.cavi.init_state`; NumPy and scikit-learn, so one
  replicate at a time, before the compiled loop), so each replicate's result
  is the one :func:`lmpromp_ppl.inference.cavi.fit` returns for it (one
  start); or
* one stacked :class:`~lmpromp_ppl.inference.cavi.CaviData` whose datasets
  share one design (a :class:`~lmpromp_ppl.inference.cavi.SharedGram` without
  dataset axis): the same initialisation in pure JAX
  (:func:`lmpromp_ppl.inference.cavi.init_state_jax`) runs inside the
  compiled, vmapped program, so thousands of datasets need no Python loop.

Under ``vmap`` the loop runs until every replicate has met its own tolerance;
a replicate that has converged keeps its state (``while_loop``'s batched
predicate selects the old carry).

The loop is :func:`lmpromp_ppl.inference.cavi.iterate` (the traceable loop that
:func:`~lmpromp_ppl.inference.cavi.run` compiles), under ``vmap``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from lmpromp_ppl.data.core import ModelData
from lmpromp_ppl.errors import DataError, LmprompError
from lmpromp_ppl.inference.cavi.data import CaviData, SharedGram, sufficient_statistics
from lmpromp_ppl.inference.cavi.init import init_state, init_state_jax
from lmpromp_ppl.inference.cavi.loop import fresh, iterate
from lmpromp_ppl.inference.cavi.posterior import sample_q
from lmpromp_ppl.inference.cavi.restarts import check_options
from lmpromp_ppl.inference.cavi.linear_response import LinearResponse, response
from lmpromp_ppl.inference.cavi.state import (
    CaviHyper,
    CaviState,
    check_family,
    check_local,
    hyper_arrays,
    with_joint_locals,
)
from lmpromp_ppl.inference.compiled import compiled
from lmpromp_ppl.models.hyper import Hyperparameters

__all__ = ["BatchedCaviFit", "fit_cavi_batched", "replicate_state", "sample_q_batched", "linear_response_batched"]


class BatchedCaviFit(NamedTuple):
    """Result of :func:`fit_cavi_batched`.

    Attributes
    ----------
    state : :class:`~lmpromp_ppl.inference.cavi.CaviState` whose leaves carry a
        leading replicate axis (R, ...)
    elbo : (R,) final ELBO of each replicate
    iterations : (R,) sweeps run by each replicate
    converged : (R,) whether each replicate met the tolerance
    seconds : wall time of the compiled batched program, excluding compilation
        (it includes the initialisation for stacked ``CaviData``, which is
        initialised inside the program)
    compile_seconds : compilation time (0 when already compiled in this process)
    data : the stacked statistics the replicates were fitted to
    """

    state: CaviState
    elbo: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    seconds: float
    compile_seconds: float
    data: CaviData | None = None


def _iterate_one(state: CaviState, data: CaviData, hyper: CaviHyper, tol: Array, max_iter: Array):
    """Sweep one replicate until its relative ELBO change is below ``tol`` (or NaN, or ``max_iter``)."""
    result = iterate(state, data, hyper, tol, max_iter, fresh(), 0)
    return result.state, result.iterations, result.elbo, result.converged


@partial(jax.jit, static_argnames=("latent_dim",))
def _batched_program(states, data, hyper, tol, max_iter, latent_dim: int | None):
    """vmap of (initialisation when ``states`` is None, then :func:`_iterate_one`) over the datasets.

    ``latent_dim`` is None when ``states`` are given (one per dataset, as is
    ``data``); otherwise ``data`` holds stacked statistics with one unbatched
    ``SharedGram`` and each dataset starts at :func:`init_state_jax`.
    """
    if states is None:
        def one(psi_t_y, y_sq, num_obs):
            single = CaviData(psi_t_y, y_sq, num_obs, data.gram)
            return _iterate_one(init_state_jax(single, hyper, latent_dim), single, hyper, tol, max_iter)

        return jax.vmap(one)(data.psi_t_y, data.y_sq, data.num_obs)
    return jax.vmap(_iterate_one, in_axes=(0, 0, None, None, None))(states, data, hyper, tol, max_iter)


def _stack(trees: Sequence) -> object:
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *trees)


def _prepare_datasets(datasets: Sequence[ModelData], hyper: Hyperparameters, family: str = "columnwise",
                      local: str = "meanfield"):
    """(initial states, data), both stacked over the replicates, from R ModelData (NumPy initialisation)."""
    datasets = list(datasets)
    if not datasets:
        raise DataError("fit_cavi_batched needs at least one dataset")
    if not all(isinstance(d, ModelData) for d in datasets):
        raise DataError("fit_cavi_batched needs a sequence of ModelData or one stacked CaviData")
    shapes = {tuple(np.shape(a) for a in d) for d in datasets}
    if len(shapes) != 1:
        raise DataError(f"all datasets must have the same shapes, got {sorted(shapes)}")
    prepared = [sufficient_statistics(d) for d in datasets]
    paths = {type(p.gram).__name__ for p in prepared}
    if len(paths) != 1:
        raise DataError("all datasets must share their design matrix the same way (fast path or not)")
    hyper.validate_for(datasets[0].num_weights, datasets[0].num_demos)
    lift = with_joint_locals if local == "joint" else (lambda state: state)  # noqa: E731
    return _stack([lift(init_state(p, hyper, family=family)) for p in prepared]), _stack(prepared)


def _check_stacked(data: CaviData, hyper: Hyperparameters) -> None:
    """Shapes of stacked statistics: psi_t_y (B, L, d), y_sq and num_obs (B, L), one unbatched SharedGram."""
    gram = data.gram
    if not isinstance(gram, SharedGram) or np.ndim(gram.basis) != 2 or np.ndim(data.psi_t_y) != 3:
        raise DataError("stacked CaviData needs psi_t_y of shape (B, L, d) and one SharedGram without dataset axis")
    B, L, d = np.shape(data.psi_t_y)
    if np.shape(data.y_sq) != (B, L) or np.shape(data.num_obs) != (B, L) or np.shape(gram.basis) != (d, d):
        raise DataError(f"stacked CaviData: y_sq and num_obs must be ({B}, {L}) and the gram basis ({d}, {d})")
    if B < 1:
        raise DataError("fit_cavi_batched needs at least one dataset")
    hyper.validate_for(d, L)


def fit_cavi_batched(
    datasets: Sequence[ModelData] | CaviData,
    hyper: Hyperparameters,
    *,
    tol: float = 1e-8,
    max_iter: int = 2000,
    family: str = "columnwise",
    local: str = "meanfield",
) -> BatchedCaviFit:
    """Fit the single-type LMProMP by CAVI (eq. 4.3) to R datasets of one shape at once.

    Parameters
    ----------
    datasets : either R :class:`ModelData` with identical shapes and the same
        design path (all sharing one design matrix within each dataset, or
        none), initialised one at a time by
        :func:`lmpromp_ppl.inference.cavi.init_state`; or one
        :class:`~lmpromp_ppl.inference.cavi.CaviData` with a leading dataset
        axis on ``psi_t_y`` (R, L, d), ``y_sq`` (R, L) and ``num_obs`` (R, L)
        and one shared design (:class:`~lmpromp_ppl.inference.cavi.SharedGram`,
        no dataset axis), initialised inside the compiled program by
        :func:`lmpromp_ppl.inference.cavi.init_state_jax`
    hyper : hyperparameters (single component, fixed beta; the thesis's
        column-wise family)
    tol : relative ELBO tolerance of each replicate
    max_iter : maximum sweeps per replicate
    family, local : the families of q(M) and of the local factors (:func:`~lmpromp_ppl.inference.cavi.fit`);
        other than the defaults only for a sequence of ModelData

    Returns
    -------
    BatchedCaviFit
    """
    if not isinstance(hyper, Hyperparameters):
        raise LmprompError(f"hyper must be a Hyperparameters, got {type(hyper).__name__}")
    if hyper.num_components != 1 or hyper.learn_beta:
        raise LmprompError("batched CAVI fits the single-type model with a fixed beta (num_components=1)")
    check_options(tol, max_iter, 1)
    check_family(family)
    check_local(local)
    if isinstance(datasets, CaviData):
        if (family, local) != ("columnwise", "meanfield"):
            raise LmprompError("stacked CaviData start in the thesis's family; pass ModelData for another family")
        _check_stacked(datasets, hyper)
        states, data, latent_dim = None, datasets, hyper.latent_dim
    else:
        (states, data), latent_dim = _prepare_datasets(datasets, hyper, family, local), None
    args = (states, data, hyper_arrays(hyper, 0.0), jnp.asarray(tol, jnp.float64), jnp.asarray(max_iter, jnp.int32))
    executable, compile_seconds = compiled(_batched_program, args, latent_dim=latent_dim)
    start = time.perf_counter()
    state, iterations, elbo, converged = jax.block_until_ready(executable(*args))
    seconds = time.perf_counter() - start
    return BatchedCaviFit(state, np.asarray(elbo), np.asarray(iterations), np.asarray(converged),
                          seconds, compile_seconds, data)


@jax.jit
def _responses(states: CaviState, data: CaviData, hyper: CaviHyper):
    return jax.vmap(lambda s, d: response(s, d, hyper, False))(states, data)


def linear_response_batched(fit: BatchedCaviFit, hyper: Hyperparameters) -> tuple[LinearResponse, float, float]:
    """The linear response (:mod:`.linear_response`) of every replicate of a joint-family batched fit, vmapped.

    Returns the :class:`~.linear_response.LinearResponse` with a leading replicate axis,
    the seconds of the compiled program and its compilation.
    """
    if fit.state.wh_cov is None or fit.data is None:
        raise LmprompError("linear response needs a batched fit of ModelData in the joint local family")
    args = (fit.state, fit.data, hyper_arrays(hyper, 0.0))
    executable, compile_seconds = compiled(_responses, args)
    start = time.perf_counter()
    lr = jax.block_until_ready(executable(*args))
    return lr, time.perf_counter() - start, compile_seconds


def replicate_state(fit: BatchedCaviFit, index: int) -> CaviState:
    """The :class:`~lmpromp_ppl.inference.cavi.CaviState` of replicate ``index``."""
    return jax.tree.map(lambda leaf: leaf[index], fit.state)


@jax.jit
def _sample_batched(keys: Array, state: CaviState, template: Array) -> dict[str, Array]:
    return jax.vmap(lambda k, s: sample_q(k, s, template.shape[0], learned_beta=False))(keys, state)


def sample_q_batched(key: Array, fit: BatchedCaviFit, num_draws: int) -> dict[str, np.ndarray]:
    """Independent draws from each replicate's q: site -> (R, num_draws, ...) (:func:`~lmpromp_ppl.inference.cavi.sample_q`)."""
    if isinstance(num_draws, bool) or int(num_draws) != num_draws or num_draws < 1:
        raise LmprompError(f"num_draws must be a positive integer, got {num_draws!r}")
    num_replicates = fit.elbo.shape[0]
    keys = jax.random.split(key, num_replicates)
    draws = _sample_batched(keys, fit.state, jnp.zeros(int(num_draws)))
    return {name: np.asarray(value) for name, value in draws.items()}

"""Fitting by CAVI: validated options, starts, restarts and (for the mixture) the split-and-merge search."""

from __future__ import annotations

import math

import jax
import numpy as np
from jax import Array

from lmpromp_ppl._progress import reporter
from lmpromp_ppl.data.core import ModelData
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference.cavi.data import check_model_data, sufficient_statistics
from lmpromp_ppl.inference.cavi.init import init_mixture_state, init_state
from lmpromp_ppl.inference.cavi.restarts import CaviFit, best_of_restarts, check_options
from lmpromp_ppl.inference.cavi.search import SEARCHES, fit_with_search
from lmpromp_ppl.inference.cavi.state import (
    check_acceleration,
    check_family,
    check_local,
    hyper_arrays,
    with_joint_locals,
)
from lmpromp_ppl.models.hyper import Hyperparameters

__all__ = ["fit"]


def fit(
    data: ModelData,
    hyper: Hyperparameters,
    key: Array,
    *,
    mixture: bool = False,
    tol: float = 1e-8,
    max_iter: int = 2000,
    num_restarts: int = 1,
    progress=False,
    shared_psi: bool | None = None,
    family: str = "columnwise",
    prune_threshold: float | None = None,
    search: str | None = None,
    max_moves: int | None = None,
    accelerate: str = "scale",
    local: str = "meanfield",
) -> CaviFit:
    """Fit the LMProMP (``mixture=False``, Sec. 4.1) or the mixture of LMProMPs (Sec. 4.2) by CAVI.

    Single type (``hyper.num_components`` must be 1): the first start is the
    thesis's initialisation (ridge regression + PCA,
    :func:`~lmpromp_ppl.inference.cavi.init_state`); further starts perturb it
    with keys split from ``key``; the best final bound wins.

    Mixture (K = ``hyper.num_components``): each start clusters the ridge weights
    by k-means++ (scikit-learn, 10 inits, a seed drawn from a key split from
    ``key``) and runs PCA per cluster (:func:`~lmpromp_ppl.inference.cavi.init_mixture_state`).
    With ``search="split_merge"`` (default) each start is then improved by merge
    and split moves accepted only when they raise the bound
    (:mod:`lmpromp_ppl.inference.cavi.search`); ``search="none"`` runs plain
    CAVI from each start.

    Parameters
    ----------
    data : padded model inputs
    hyper : hyperparameters (``latent_dim`` V, ``num_components`` K, ``kappa0``,
        ``learn_beta`` with ``beta_a0``, ``beta_b0``)
    key : jax PRNG key for the starts
    mixture : fit the mixture
    tol : stop when the relative ELBO change is below ``tol``
    max_iter : maximum number of sweeps per start (warns with ConvergenceWarning when hit)
    num_restarts : number of starts
    progress : True for a progress bar when stderr is a terminal, or a callable
        ``(sweeps, ELBO) -> None`` called every :data:`~lmpromp_ppl.inference.cavi.loop.CHUNK` sweeps
    shared_psi : see :func:`~lmpromp_ppl.inference.cavi.sufficient_statistics`
    family : ``"columnwise"`` (the thesis's isotropic q(m_v), default) or
        ``"rowwise"`` (rows of M share one V x V covariance), see
        :data:`~lmpromp_ppl.inference.cavi.FAMILIES`
    prune_threshold : mixture only: remove a component when its expected number
        of demonstrations falls below this (default 0.5; 0 disables removal)
    search : mixture only: ``"split_merge"`` (default) or ``"none"``
    max_moves : mixture only: at most this many accepted moves per start (default 2K)
    accelerate : the acceleration of the sweeps, each of which keeps the bound
        non-decreasing (:data:`~lmpromp_ppl.inference.cavi.ACCELERATIONS`):
        ``"scale"`` (default: after each sweep the bound-maximising rescaling of each
        latent dimension (:mod:`.transform`) and, for the single type on a shared
        design, of each eigen-direction of the weights; then an over-relaxed step,
        kept when it raises the bound, :mod:`.accelerate`), ``"overrelax"`` (the
        over-relaxed step only) or ``"none"`` (the thesis's plain sweeps)
    local : the family of the local factors (:data:`~lmpromp_ppl.inference.cavi.LOCAL_FAMILIES`):
        ``"meanfield"`` (the thesis's q(w_i) q(h_i), default) or ``"joint"`` (one joint
        Gaussian q(w_i, h_i) per demonstration; the single type only)

    Returns
    -------
    CaviFit
    """
    if not isinstance(hyper, Hyperparameters):
        raise LmprompError(f"hyper must be a Hyperparameters, got {type(hyper).__name__}")
    check_family(family)
    check_options(tol, max_iter, num_restarts)
    check_acceleration(accelerate)
    check_local(local)
    if mixture and local != "meanfield":
        raise LmprompError("the joint local family is derived for the single-type LMProMP, not for the mixture")
    if not mixture:
        given = [name for name, value in (("prune_threshold", prune_threshold), ("search", search),
                                          ("max_moves", max_moves)) if value is not None]
        if given:
            raise LmprompError(f"option(s) {', '.join(given)} apply to the mixture only")
        if hyper.num_components != 1:
            raise LmprompError(
                f"the single-type LMProMP needs num_components=1, got {hyper.num_components}"
            )
    prune_threshold = 0.5 if prune_threshold is None else prune_threshold
    search = "split_merge" if search is None else search
    if not (isinstance(prune_threshold, (int, float)) and 0 <= prune_threshold and math.isfinite(prune_threshold)):
        raise LmprompError(f"prune_threshold must be a number >= 0, got {prune_threshold!r}")
    if search not in SEARCHES:
        raise LmprompError(f"unknown search {search!r}; choose from {list(SEARCHES)}")
    if max_moves is not None and (isinstance(max_moves, bool) or not isinstance(max_moves, (int, np.integer)) or max_moves < 0):
        raise LmprompError(f"max_moves must be an integer >= 0, got {max_moves!r}")
    check_model_data(data)
    hyper.validate_for(data.num_weights, data.num_demos)
    if mixture and hyper.num_components > data.num_demos:
        raise LmprompError(
            f"more mixture components (K={hyper.num_components}) than demonstrations (L={data.num_demos})"
        )
    cavi_data = sufficient_statistics(data, shared_psi)
    hyper_arr = hyper_arrays(hyper, prune_threshold if mixture else 0.0, accelerate)
    keys = jax.random.split(key, num_restarts)
    label = "CAVI mixture" if mixture else "CAVI"
    with reporter(progress, int(max_iter) * int(num_restarts), label) as callback:
        if not mixture:
            lift = with_joint_locals if local == "joint" else (lambda s: s)  # noqa: E731
            starts = (lift(init_state(cavi_data, hyper, key=None if r == 0 else keys[r], family=family))
                      for r in range(num_restarts))
            return best_of_restarts(starts, cavi_data, hyper_arr, tol, max_iter, callback)
        starts = [init_mixture_state(cavi_data, hyper, keys[r], family=family) for r in range(num_restarts)]
        if search == "none":
            return best_of_restarts(starts, cavi_data, hyper_arr, tol, max_iter, callback)
        seed = int(jax.random.randint(jax.random.fold_in(key, 1), (), 0, np.iinfo(np.int32).max))
        return fit_with_search(starts, cavi_data, hyper_arr, tol=tol, max_iter=max_iter, max_moves=max_moves,
                               seed=seed, callback=callback)

"""Fitting by CAVI: validated options, starts, restarts and (for the mixture) the split-and-merge search."""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import numpy as np
from jax import Array

from lmpromp_ppl._progress import reporter
from lmpromp_ppl.data.core import ModelData
from lmpromp_ppl.errors import EngineDivergedError, LmprompError
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

__all__ = ["fit", "fit_lr", "CaviLrFit", "RESAMPLE_CHOICES"]


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


#: Values of ``fit_lr(resample=...)``: resample by importance weights when k-hat is small enough, or never.
RESAMPLE_CHOICES = ("auto", "never")


class CaviLrFit(NamedTuple):
    """Result of :func:`fit_lr`: the joint-family CAVI fit, its linear response and its importance diagnostics.

    Attributes
    ----------
    fit : the :class:`CaviFit` of the joint local family
    lr : the :class:`~.linear_response.LinearResponse` of the global quantities
    lr_seconds : wall time of the linear response, excluding compilation
    lr_compile_seconds : its compilation (0 when already compiled in this process)
    psis_khat : Pareto k-hat of the importance ratios of the linear-response Gaussian on the
        collapsed model (:mod:`.importance`), or None (``psis_note`` says why)
    psis_note : why ``psis_khat`` is None, or ""
    resampled : whether :meth:`sample` resamples by the importance weights (k-hat below
        :data:`~lmpromp_ppl.inference.psis.KHAT_RESAMPLE` and ``resample="auto"``)
    inputs : the collapsed model's inputs (for the importance ratios)
    data : the model inputs of the fit
    hyper : the fit's hyperparameters
    refresh : exact-conditional Gibbs sweeps applied to every draw of :meth:`sample`
        (:mod:`lmpromp_ppl.inference.refresh`; 0: the draws of the Gaussian or of the
        importance resampling as they are)
    """

    fit: CaviFit
    lr: object
    lr_seconds: float
    lr_compile_seconds: float
    psis_khat: float | None
    psis_note: str
    resampled: bool
    inputs: object
    data: object
    hyper: Hyperparameters
    refresh: int = 0

    @property
    def state(self):
        """The joint-family CAVI state."""
        return self.fit.state

    def sample(self, key: Array, num_draws: int) -> dict:
        """Draws of every site: importance-resampled when :attr:`resampled`, else the linear-response draws;
        then :attr:`refresh` exact-conditional sweeps from each (:func:`lmpromp_ppl.inference.refresh.refresh`)."""
        return self.sample_timed(key, num_draws)[0]

    def sample_timed(self, key: Array, num_draws: int) -> tuple[dict, float, float]:
        """:meth:`sample`, and the seconds of the refresh sweeps and of their compilation (0 without sweeps)."""
        from lmpromp_ppl.inference.cavi.importance import importance_draws
        from lmpromp_ppl.inference.cavi.linear_response import sample_lr
        from lmpromp_ppl.inference.refresh import refresh

        learned = bool(self.fit.state.beta_learned)
        key, key_refresh = jax.random.split(key)
        if self.resampled:
            draws = importance_draws(key, self.lr, self.inputs, self.hyper, num_draws, learned, self.data)[0]
        else:
            draws = sample_lr(key, self.lr, self.fit.state, num_draws, learned)
        if not self.refresh:
            return draws, 0.0, 0.0
        return refresh(key_refresh, draws, self.data, self.hyper, self.refresh, timed=True)

    def log_density(self, draws: dict) -> Array:
        """log density of the linear-response draws (global Gaussian and joint local q), before any refresh:
        refreshed draws have no closed-form density (the importance diagnostics use the Gaussian's)."""
        from lmpromp_ppl.inference.cavi.linear_response import log_q_lr

        return log_q_lr(self.lr, self.fit.state, draws)

    def log_ratios(self, key: Array, num_draws: int) -> np.ndarray:
        """Importance log ratios of the global quantities on the collapsed model (:mod:`.importance`)."""
        from lmpromp_ppl.inference.cavi.importance import global_log_ratios

        learned = bool(self.fit.state.beta_learned)
        return global_log_ratios(key, self.lr, self.inputs, self.hyper, num_draws, learned)[1]


def fit_lr(
    data: ModelData,
    hyper: Hyperparameters,
    key: Array,
    *,
    tol: float = 1e-8,
    max_iter: int = 2000,
    num_restarts: int = 1,
    progress=False,
    shared_psi: bool | None = None,
    family: str = "rowwise",
    accelerate: str = "scale",
    resample: str = "auto",
    refresh: int | None = None,
) -> CaviLrFit:
    """Fit the single-type LMProMP by CAVI in the joint local family, then correct the global covariances.

    The engine ``cavi_lr``: :func:`fit` with ``local="joint"`` (one joint Gaussian
    q(w_i, h_i) per demonstration; ``family`` of q(M), row-wise by default), then the
    linear-response covariance of :math:`(b, M, \\log\\alpha, \\log\\lambda, \\log\\beta)`
    (:mod:`.linear_response`), then the Pareto k-hat of that Gaussian as an importance
    proposal on the model with w and h integrated out (:mod:`.importance`, ratios of
    :data:`~.importance.POOL` draws of a key split from ``key``).  With ``resample="auto"``
    draws are importance-resampled when k-hat < :data:`~lmpromp_ppl.inference.psis.KHAT_RESAMPLE`.
    Every draw then takes ``refresh`` sweeps of the exact conditionals
    (:mod:`lmpromp_ppl.inference.refresh`; default
    :data:`~lmpromp_ppl.inference.refresh.REFRESH_SWEEPS`), a Markov kernel that leaves the
    posterior invariant and so can only bring the draws closer to it: it removes the bias of
    q(alpha) that no covariance correction can (docs/derivation.md, *Refreshing the draws*).
    """
    import time

    from lmpromp_ppl.inference.cavi.importance import POOL, global_log_ratios, resamples
    from lmpromp_ppl.inference.cavi.linear_response import linear_response
    from lmpromp_ppl.inference.psis import psis
    from lmpromp_ppl.inference.refresh import REFRESH_SWEEPS, check_refresh
    from lmpromp_ppl.models.registry import model_inputs

    if resample not in RESAMPLE_CHOICES:
        raise LmprompError(f"unknown resample {resample!r}; choose from {list(RESAMPLE_CHOICES)}")
    refresh = check_refresh(REFRESH_SWEEPS if refresh is None else refresh)
    key_fit, key_ratio = jax.random.split(key)
    result = fit(data, hyper, key_fit, tol=tol, max_iter=max_iter, num_restarts=num_restarts, progress=progress,
                 shared_psi=shared_psi, family=family, accelerate=accelerate, local="joint")
    cavi_data = sufficient_statistics(data, shared_psi)
    hyper_arr = hyper_arrays(hyper, 0.0, accelerate)
    start = time.perf_counter()
    lr, compile_seconds = linear_response(result.state, cavi_data, hyper_arr, timed=True)
    lr_seconds = time.perf_counter() - start - compile_seconds
    if not (np.all(np.isfinite(np.asarray(lr.cov))) and float(lr.residual) < 1e-6):
        raise EngineDivergedError(
            "the linear response failed: the bound's Hessian is not positive definite at the fitted state "
            f"(relative residual {float(lr.residual):.3g}); did the fit converge? raise max_iter or lower tol"
        )
    inputs = model_inputs("lmpromp", "wh", data)
    learned = bool(result.state.beta_learned)
    _, ratios = global_log_ratios(key_ratio, lr, inputs, hyper, POOL, learned)
    _, khat, note = psis(ratios)
    return CaviLrFit(result, lr, lr_seconds, compile_seconds, khat, note, resamples(resample, khat), inputs, data, hyper,
                     refresh)

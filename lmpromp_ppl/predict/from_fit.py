r"""Prediction from a saved or fresh fit (:class:`~lmpromp_ppl.results.FitResult`).

:func:`predict_from_fit` ties observations in data units to the fit's basis
and scaling, conditions the plug-in or Bayesian predictive, and returns the
trajectory distribution and samples in data units.  ``lmpromp predict`` calls it.

Defaults: the exact conditional :math:`p(\mathbf w | \mathbf o)` (the thesis's
eqs. 4.6-4.7 only with ``exact=False``, docs/derivation.md), averaged over
posterior draws (``bayesian=True``; the plug-in posterior mean of ``M`` is
meaningless for a sampler, whose draws of ``M`` differ by rotations), with the
observation noise of the fit (its learned ``beta`` when ``beta`` was inferred).
Two bands are returned: ``sd`` of the movement :math:`\Psi\mathbf w` and
``sd_obs`` of a new observation of it (``sd`` with the noise variance added).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from lmpromp_ppl._keys import PREDICTION, seed_key

from lmpromp_ppl.errors import DataError, LmprompError
from lmpromp_ppl.predict.conditioning import SITES, condition, condition_draws
from lmpromp_ppl.predict.timing import (
    TimingCurve,
    TimingPosterior,
    ViaPoints,
    duration_prior,
    power_mixture,
    rows_at,
    sample_over_timing,
    timed_moments,
    timed_rows,
    timing_curve,
    timing_nodes,
    timing_posterior,
    via_rows,
)
from lmpromp_ppl.predict.trajectories import sample_trajectories

__all__ = ["Prediction", "predict_from_fit", "population_prediction", "noise_sd_of", "training_durations", "evidence_samples",
           "residual_correlation", "timing_curve_of"]


class Prediction(NamedTuple):
    """A predicted trajectory distribution in data units.

    With an estimated timing the phase-space moments are averaged over the
    timing posterior, and ``time``, ``time_mean``, ``time_sd`` give the
    prediction in real time (seconds from the observation's start).
    """

    phase: np.ndarray  # (P,)
    mean: np.ndarray  # (P, D)
    sd: np.ndarray  # (P, D) movement (noise-free trajectory)
    sd_obs: np.ndarray  # (P, D) a new observation: movement plus observation noise
    samples: np.ndarray  # (N, P, D)
    component_weights: np.ndarray  # (K,) responsibilities (1 for single-type models)
    noise_sd: np.ndarray  # (D,) observation noise s.d. in data units
    duration: float | None = None  # the known or estimated duration (posterior median)
    duration_interval: np.ndarray | None = None  # (2,) central 90 % interval (estimated timing)
    time: np.ndarray | None = None  # (Q,) real time from the observation's start
    time_mean: np.ndarray | None = None  # (Q, D)
    time_sd: np.ndarray | None = None  # (Q, D)
    timing: TimingPosterior | None = None


def noise_sd_of(result) -> np.ndarray:
    r"""Observation-noise s.d. per DoF in data units: :math:`E[\beta]^{-1/2}` when
    ``beta`` was learned (posterior mean), else the fixed ``hyper.beta``."""
    beta = result.point.get("beta") if result.point else None
    if beta is None and result.draws is not None and "beta" in result.draws:
        beta = np.mean(result.draws["beta"])
    beta = result.hyper.beta if beta is None else float(np.mean(beta))
    return np.asarray(result.scaling.scale, dtype=float) / np.sqrt(beta)


def training_durations(result) -> np.ndarray:
    """Each training demonstration's duration (last minus first time, the data's time unit), from ``observed_data``."""
    if not result.observed or "t" not in result.observed:
        raise LmprompError("this fit holds no training times; estimating the timing needs a fit of demonstrations")
    t = np.asarray(result.observed["t"], dtype=float)
    return np.nanmax(t, axis=1) - np.nanmin(t, axis=1)


#: The prediction averages over this many quantile nodes of the timing posterior (:func:`~lmpromp_ppl.predict.timing.timing_nodes`).
TIMING_NODES = 16


def residual_correlation(result) -> float | None:
    r"""The correlation length, in phase, of the training demonstrations' residuals about their fitted weights.

    For each training demonstration i and DoF d the residual
    :math:`r_{id}(z) = y_{id}(z) - \psi(z)^\top \mathrm E[\mathbf w_{id}]` (standardised
    units) is a series whose integrated autocorrelation time
    :math:`\tau = n / n_{\text{eff}}` (numpyro's effective sample size, Geyer's
    initial monotone sequence) says how many consecutive samples carry one
    sample's worth of information.  Returned: the median over series of
    :math:`\max(\tau, 1) / (n - 1)`, the phase spanned by one effective sample.
    ``None`` when the fit holds no per-demonstration weights or training data.
    """
    from numpyro.diagnostics import effective_sample_size

    from lmpromp_ppl.basis import rbf_basis

    point = result.point or {}
    if "w" not in point or not result.observed or "t" not in result.observed or "y" not in result.observed:
        return None
    t, y = np.asarray(result.observed["t"], dtype=float), np.asarray(result.observed["y"], dtype=float)
    w = np.asarray(point["w"], dtype=float)
    D, J = result.num_dofs, result.num_basis
    if w.shape != (t.shape[0], D * J):
        return None
    scale, shift = np.asarray(result.scaling.scale, dtype=float), np.asarray(result.scaling.mean, dtype=float)
    lengths = []
    for i, z in enumerate(result.training_phases()):
        if z.size < 8:
            continue
        psi = np.asarray(rbf_basis(z, J, result.width))
        residual = (y[i][: z.size] - shift) / scale - psi @ w[i].reshape(D, J).T
        for d in range(D):
            if not np.all(np.isfinite(residual[:, d])) or np.std(residual[:, d]) == 0:
                continue
            tau = z.size / float(effective_sample_size(residual[None, :, d]))
            lengths.append(max(tau, 1.0) / (z.size - 1))
    return float(np.median(lengths)) if lengths else None


def evidence_samples(time: np.ndarray, rule: int | str | None, prior, num_basis: int,
                     correlation: float | None = None) -> np.ndarray:
    r"""Indices of the observed samples whose likelihood weighs the timing.

    The model's noise is independent per sample, but a recording's departure
    from the basis expansion is smooth, so a dense recording (LASA's 1000
    samples) would count the same misfit hundreds of times: its likelihood
    then prefers the duration under which *more* basis functions span the
    observed segment (a shorter one, which fits the segment's detail better),
    with a spuriously narrow interval.  The rules keep evenly spaced samples,
    one per correlation length :math:`\ell` in phase:
    :math:`\lceil t_{\max} / (T_{\text{prior}}\, \ell) \rceil + 1` of them, with
    :math:`T_{\text{prior}}` the prior median.

    * ``"residual"`` (default): :math:`\ell` from the training residuals
      (:func:`residual_correlation`, passed as ``correlation``); on LASA it is
      about 25 samples of 1000, on GunPoint 3.4 of 150, and on data that follow
      the model (white residuals) one sample, so every sample counts.  Falls
      back to ``"basis"`` when ``correlation`` is ``None``.
    * ``"basis"``: :math:`\ell = 1 / (2 (J - 1))`, two samples per basis spacing.
    * an int keeps that many samples; ``None`` keeps all.

    docs/derivation.md gives the measurements.
    """
    time = np.asarray(time, dtype=float)
    if rule is None:
        return np.arange(time.size)
    if rule == "residual" and correlation is None:
        rule = "basis"
    if rule in ("basis", "residual"):
        length = 1.0 / (2.0 * (num_basis - 1)) if rule == "basis" else float(correlation)
        span = float(time.max()) / math.exp(prior.loc) if time.size else 0.0
        count = int(math.ceil(span / length)) + 1
    elif isinstance(rule, (int, np.integer)) and not isinstance(rule, bool) and rule >= 1:
        count = int(rule)
    else:
        raise DataError(f"timing_points must be 'residual', 'basis', a positive integer or None, got {rule!r}")
    if time.size <= count:
        return np.arange(time.size)
    targets = np.linspace(time.min(), time.max(), count)
    return np.unique(np.abs(time[None, :] - targets[:, None]).argmin(axis=1))


def _draw_sites(result, bayesian: bool, max_draws: int) -> dict:
    if bayesian:
        draws = result.posterior_draws()
        flat = {k: np.asarray(v).reshape((-1,) + np.asarray(v).shape[2:]) for k, v in draws.items() if k in SITES[result.model]}
        n = next(iter(flat.values())).shape[0]
        keep = np.linspace(0, n - 1, min(n, max_draws)).astype(int)
        return {k: jnp.asarray(v[keep]) for k, v in flat.items()}
    return {k: jnp.asarray(result.point[k])[None] for k in SITES[result.model]}


def _timing_evidence(result, time: np.ndarray, values: np.ndarray, noise: np.ndarray, timing_points):
    """The duration prior and the observed rows that weigh the timing (:func:`evidence_samples`)."""
    prior = duration_prior(training_durations(result))
    correlation = residual_correlation(result) if timing_points == "residual" else None
    sub = evidence_samples(time, timing_points, prior, result.num_basis, correlation)
    return prior, timed_rows(time[sub], values[sub], noise_sd=noise, scaling=result.scaling, timed=True)


def timing_curve_of(result, time: np.ndarray, values: np.ndarray, *, timing_points: int | str | None = "residual",
                    bayesian: bool = True, exact: bool = True, max_draws: int = 200,
                    max_start: float = 0.0) -> TimingCurve:
    """The log likelihood of the duration of an observation that began with the movement
    (``time``: seconds from its start, ``values`` (T, D) in data units) on one grid over the
    prior's range, as :func:`predict_from_fit` weighs it with ``duration="estimate"``
    (:func:`~lmpromp_ppl.predict.timing.timing_curve`); with ``max_start > 0`` the observation
    may have begun at any phase up to ``max_start`` (``time`` from the observation's start) and
    the curve runs over the duration and the start phase."""
    time, values = np.asarray(time, dtype=float), np.asarray(values, dtype=float)
    noise = np.broadcast_to(np.asarray(noise_sd_of(result), dtype=float), (result.num_dofs,))
    prior, rows = _timing_evidence(result, time, values, noise, timing_points)
    return timing_curve(result.model, _draw_sites(result, bayesian, max_draws), rows, prior, result.hyper.gamma,
                        exact=exact, num_dofs=result.num_dofs, num_basis=result.num_basis, width=result.width,
                        max_start=max_start)


def predict_from_fit(
    result,
    phase: np.ndarray,
    values: np.ndarray,
    *,
    duration: float | str | None = None,
    max_start: float = 0.0,
    timing_points: int | str | None = "residual",
    timing_power: float | np.ndarray = 1.0,
    timing_weights: np.ndarray | None = None,
    via: ViaPoints | None = None,
    noise_sd: float | np.ndarray | None = None,
    bayesian: bool = True,
    exact: bool = True,
    num_phases: int = 100,
    query: np.ndarray | None = None,
    time_query: np.ndarray | None = None,
    num_samples: int = 20,
    max_draws: int = 200,
    key=None,
) -> Prediction:
    r"""Condition ``result`` on observed positions (and via-points) and predict the whole movement.

    Parameters
    ----------
    result : a FitResult (fresh or from :func:`lmpromp_ppl.load`)
    phase : (T,) phases in [0, 1] of the observations, or, with ``duration``
        given, their times in seconds from the movement's start
    values : (T, D) positions in data units; NaN marks an unobserved entry
        (partial observation of some DoF); T = 0 gives the population
        (unconditioned) movement distribution
    duration : ``None`` (``phase`` are phases), the movement's duration (times
        map to phases ``t / duration``), or ``"estimate"``: the posterior over
        the duration given the observation (:mod:`lmpromp_ppl.predict.timing`),
        with a log-normal prior from the training durations, and the prediction
        averaged over it
    max_start : with ``duration="estimate"``, also estimate the phase at which
        the observation began, uniform on ``[0, max_start]`` (0: it began with the movement)
    timing_points : the observed samples that enter the timing's likelihood: ``"residual"``
        (default: one per correlation length of the training residuals), ``"basis"`` (two per
        basis spacing), a number of evenly spaced samples, or ``None`` (all); :func:`evidence_samples`
    timing_power : with ``duration="estimate"``, the power :math:`\kappa \in [0, 1]` of the timing's
        likelihood, :math:`p(\tau | \mathbf{o}) \propto p(\tau)\, p(\mathbf{o} | \tau)^\kappa`
        (1: the model's posterior; 0: the prior), or several powers, whose posteriors are mixed with
        ``timing_weights``; :func:`lmpromp_ppl.api.calibrate_timing` weighs the candidate powers
        by cross-validation over the training demonstrations (its ``powers`` and ``weights``)
    timing_weights : with several ``timing_power``, their weights (non-negative)
    via : via-points (:class:`~lmpromp_ppl.predict.timing.ViaPoints`), at phases or,
        when ``via.timed``, at seconds from the observation's start (needs a duration)
    noise_sd : observation noise s.d. in data units (scalar or per DoF);
        default :func:`noise_sd_of` the fit
    bayesian : average over posterior draws (default) instead of plugging in
        the posterior mean
    exact : the exact conditional p(w | o) (default); ``False`` gives the
        thesis's approximation, eqs. 4.6-4.7
    num_phases : predict at this many equally spaced phases in [0, 1] ...
    query : ... or at these phases
    time_query : with a duration, the real times (seconds from the observation's start) of
        ``time_mean``, ``time_sd``; default ``num_phases`` times up to the longest likely end
    key : PRNG key of the sampled trajectories; default: derived from the fit's seed
    """
    values = np.asarray(values, dtype=float)
    phase = np.asarray(phase, dtype=float)
    D = result.num_dofs
    if values.ndim != 2 or values.shape[1] != D:
        raise DataError(f"observed positions must have shape (T, {D}) for this fit, got {values.shape}")
    if phase.shape != (values.shape[0],):
        raise DataError(f"{phase.shape[0]} phases for {values.shape[0]} observed samples")
    if np.any(np.isinf(values)):
        raise DataError("observed positions contain inf")
    estimate = isinstance(duration, str)
    if estimate and duration != "estimate":
        raise DataError(f"duration must be a positive number or 'estimate', got {duration!r}")
    if not estimate and duration is not None and not (np.isfinite(duration) and duration > 0):
        raise DataError(f"duration must be positive and finite, got {duration!r}")
    if max_start and not estimate:
        raise DataError("max_start needs duration='estimate'")
    power_mixture(timing_power, timing_weights)  # checked before any work
    timed = duration is not None
    if not timed and (np.any(phase < 0) or np.any(phase > 1)):
        raise DataError("observation phases must lie in [0, 1]; pass a duration to map times to phases")
    if timed and not estimate and np.any(phase > duration * (1 + 1e-9)):
        raise DataError(f"observation times exceed the duration {duration}")
    if via is not None and via.timed and not timed:
        raise DataError("via-points at times (seconds) need a duration (a number or 'estimate')")
    if noise_sd is None:
        noise_sd = noise_sd_of(result)
    noise = np.broadcast_to(np.asarray(noise_sd, dtype=float), (D,))
    basis = dict(num_dofs=D, num_basis=result.num_basis, width=result.width)
    rows = timed_rows(phase, values, noise_sd=noise, scaling=result.scaling, timed=timed)
    via_part = None if via is None else via_rows(
        via.at, via.position, velocity=via.velocity, position_sd=via.position_sd, velocity_sd=via.velocity_sd,
        scaling=result.scaling, timed=via.timed,
    )
    gamma = result.hyper.gamma
    draws = _draw_sites(result, bayesian, max_draws)
    timing = None
    if estimate:
        prior, evidence_rows = _timing_evidence(result, phase, values, noise, timing_points)
        timing = timing_posterior(result.model, draws, evidence_rows, prior, gamma, exact=exact, max_start=max_start,
                                  power=timing_power, power_weights=timing_weights, **basis)
        chosen, grid_weights = timing_nodes(timing.weights, TIMING_NODES)
        durations, starts = timing.duration[chosen], timing.start[chosen]
    else:
        durations, starts, grid_weights = np.array([1.0 if duration is None else float(duration)]), np.zeros(1), np.ones(1)
    posts, component_weights = [], []
    for T, z0 in zip(durations, starts):
        obs = rows_at(rows, T, z0, **basis)
        extra = None if via_part is None else rows_at(via_part, T, z0, **basis)
        if bayesian:
            post = condition_draws(result.model, draws, obs, gamma, exact=exact, via=extra)
        else:
            post = condition(result.model, {k: v[0] for k, v in draws.items()}, obs, gamma, exact=exact, via=extra)
        posts.append(post.weights)
        component_weights.append(np.exp(np.asarray(post.weights.log_weights)))
    query = np.linspace(0.0, 1.0, num_phases) if query is None else np.asarray(query, dtype=float)
    span = float(np.max(durations * (1.0 - starts))) if timed else 1.0
    if time_query is not None and not timed:
        raise DataError("time_query needs a duration (a number or 'estimate')")
    if time_query is not None:
        time = np.asarray(time_query, dtype=float)
    else:
        time = np.linspace(0.0, span, num_phases) if timed else None
    moments = timed_moments(posts, grid_weights, durations, starts, np.zeros(1) if time is None else time, query, **basis)
    key = seed_key(result.seed, PREDICTION) if key is None else key
    if len(posts) == 1:
        paths = np.asarray(sample_trajectories(key, posts[0], query, num_samples, **basis))
    else:
        paths = sample_over_timing(key, posts, grid_weights, query, num_samples, **basis)
    scale, shift = np.asarray(result.scaling.scale), np.asarray(result.scaling.mean)
    weights = component_weights[0] if len(posts) == 1 else np.ones(1)
    sd = np.asarray(moments.sd) * scale
    return Prediction(
        phase=query,
        mean=np.asarray(moments.mean) * scale + shift,
        sd=sd,
        sd_obs=np.sqrt(sd**2 + noise**2),
        samples=paths * scale + shift,
        component_weights=weights / weights.sum(),
        noise_sd=noise,
        duration=None if duration is None else (timing.estimate if estimate else float(duration)),
        duration_interval=None if timing is None else np.asarray(timing.interval),
        time=time,
        time_mean=None if time is None else np.asarray(moments.time_mean) * scale + shift,
        time_sd=None if time is None else np.asarray(moments.time_sd) * scale,
        timing=timing,
    )


def population_prediction(result, **options) -> Prediction:
    """The movement distribution of a new demonstration, conditioned on nothing (options as :func:`predict_from_fit`)."""
    return predict_from_fit(result, np.zeros(0), np.zeros((0, result.num_dofs)), **options)

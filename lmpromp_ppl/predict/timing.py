r"""Prediction when the timing is unknown: the duration (and start) of a partial observation.

A movement of duration :math:`T` that started at phase :math:`z_0` before the
observation began puts the observation's time :math:`t` (seconds from the
start of the observation) at phase :math:`z = z_0 + t / T`.  Every row of an
observation is linear-Gaussian in the weights given the timing
:math:`\tau = (T, z_0)`, so the likelihood of the timing is the evidence that
conditioning already computes (eq. 3.2 / Sec. 4.1.2, averaged over the
posterior draws :math:`\theta_s` of any engine):

.. math::

    p(\mathbf{o} | \tau) = \frac1S \sum_s \mathcal{N}(\mathbf{o} | \Psi_o(\tau)\,\mathbf{b}_s,\
    \Sigma_o + \Psi_o(\tau)\,\Sigma_{w,s}\,\Psi_o(\tau)^T), \qquad
    p(\tau | \mathbf{o}) \propto p(T)\, p(z_0)\, p(\mathbf{o} | \tau).

The control variables :math:`\mathbf{h}` (and the weights) are integrated out
exactly, so the timing and the latent shape explain the observation together:
a slow movement is not mistaken for a different shape, nor the other way round.

**Why a grid.** The timing has one or two dimensions, its likelihood is cheap
(one conditioning per draw) and it can be multimodal (a partial movement may
fit the start of a slow and of a fast execution); a grid in :math:`\log T`
(times a grid in :math:`z_0`) evaluates it everywhere it matters, gives the
posterior quantiles without a sampler's tuning or a local optimiser's risk of
the wrong mode, and is refined once around its mass
(:func:`timing_posterior`).  The prediction is the mixture over the grid,

.. math::

    p(y(t) | \mathbf{o}) = \sum_g p(\tau_g | \mathbf{o})\, p(y(z_0^{(g)} + t/T_g) | \mathbf{o}, \tau_g),

in real time (:func:`timed_moments`, the phase held at 1 once a movement has
ended) and in the phase of the movement.

**The duration prior** (:func:`duration_prior`) is log-normal, fitted to the
training demonstrations' durations (stored with every fit as
``observed_data.t``): the location is the mean of :math:`\log T_i`, the scale
their standard deviation times :math:`\sqrt{1 + 1/L}` (the predictive spread
of a new duration), at least :data:`MIN_LOG_SCALE` (so that training sets of
equal durations, such as GunPoint's, still allow a 5 % change of speed).
The start phase has a uniform prior on ``[0, max_start]``.

**Via-points** (positions, optionally velocities, at phases or at times) are
constraints on the rest of the movement, not evidence about the timing: they
enter the prediction at each grid point (:func:`~lmpromp_ppl.predict.conditioning.condition_further`),
not :math:`p(\tau | \mathbf{o})`.  Velocities are in data units per second
when a duration is known or estimated (rows :math:`\dot\psi(z)^T / T`), per
unit of phase otherwise.
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.scipy.special import logsumexp

from lmpromp_ppl.basis import DEFAULT_WIDTH, rbf_basis, rbf_basis_derivative
from lmpromp_ppl.data.core import Scaling
from lmpromp_ppl.errors import DataError
from lmpromp_ppl.predict.conditioning import condition
from lmpromp_ppl.predict.gaussian import GaussianMixture
from lmpromp_ppl.predict.observations import POSITION, VELOCITY, Observation, _noise_per_dof
from lmpromp_ppl.predict.trajectories import sample_weights, trajectory_distribution

__all__ = [
    "MIN_LOG_SCALE",
    "TimedRows",
    "DurationPrior",
    "TimingPosterior",
    "TimedMoments",
    "timed_rows",
    "via_rows",
    "timing_nodes",
    "join_rows",
    "rows_at",
    "duration_prior",
    "timing_log_likelihood",
    "timing_posterior",
    "power_mixture",
    "TimingCurve",
    "timing_curve",
    "tempered_log_score",
    "TIMING_POWERS",
    "timed_moments",
    "sample_over_timing",
    "ViaPoints",
]

#: Smallest scale of the log-normal duration prior (5 % in duration).
MIN_LOG_SCALE = 0.05
#: Grid points of each pass in log duration (two passes: the prior's range, then the posterior's).
GRID_SIZE = 121
#: Grid points in the start phase when the start is estimated.
START_GRID_SIZE = 21
#: The posterior keeps grid points down to this fraction of its largest weight.
RELATIVE_FLOOR = 1e-9
#: Candidate powers of the timing likelihood when it is calibrated (:func:`tempered_log_score`):
#: 0 (the prior alone) and 31 powers from 2**-10 to 1, evenly spaced in log.
TIMING_POWERS = np.concatenate([[0.0], np.geomspace(2.0**-10, 1.0, 31)])
#: Grid points in log duration of a :class:`TimingCurve` (one pass over the prior's range).
CURVE_GRID_SIZE = 241


class TimedRows(NamedTuple):
    r"""Linear-Gaussian rows whose phase may depend on the timing.

    Row n observes DoF ``dof[n]`` (position or velocity, ``order[n]``) at
    ``time[n]``: seconds from the observation's start when ``timed[n]``
    (phase :math:`z_0 + t/T`), a phase otherwise.  Values and noise
    variances are standardised (the fit's :class:`~lmpromp_ppl.data.Scaling`).
    """

    time: Array
    timed: Array
    dof: Array
    order: Array
    values: Array
    noise_var: Array

    @property
    def num_rows(self) -> int:
        return self.values.shape[0]


class DurationPrior(NamedTuple):
    """Log-normal prior of a movement's duration: ``log T ~ N(loc, scale**2)`` (time unit of the data)."""

    loc: float
    scale: float

    def log_density(self, log_duration: np.ndarray) -> np.ndarray:
        """Log density of ``log T`` (the grid's coordinate)."""
        z = (np.asarray(log_duration) - self.loc) / self.scale
        return -0.5 * z**2 - math.log(self.scale) - 0.5 * math.log(2.0 * math.pi)


class ViaPoints(NamedTuple):
    """Via-points in data units: ``position`` (V, D) and optionally ``velocity`` (V, D), NaN = free.

    ``at`` (V,) holds phases, or seconds from the observation's start when
    ``timed``.  ``position_sd`` and ``velocity_sd`` (scalar or (D,)) say how
    tightly to pass; 0 passes exactly.
    """

    at: np.ndarray
    position: np.ndarray
    velocity: np.ndarray | None = None
    position_sd: float | np.ndarray = 0.0
    velocity_sd: float | np.ndarray = 0.0
    timed: bool = False


class TimingPosterior(NamedTuple):
    """The posterior over the timing on its grid (flattened over duration x start)."""

    duration: np.ndarray  # (G,) T of each grid point
    start: np.ndarray  # (G,) start phase z0 of each grid point
    log_prior: np.ndarray  # (G,) log prior density (in log T and z0) times the cell size
    log_likelihood: np.ndarray  # (G,) log p(o | T, z0)
    weights: np.ndarray  # (G,) posterior probabilities, summing to 1
    estimate: float  # posterior median of T
    interval: np.ndarray  # (2,) central 90 % interval of T
    start_estimate: float  # posterior median of z0 (0 when not estimated)

    def quantile(self, q) -> np.ndarray:
        """Quantiles of the duration's posterior (the grid's cumulative weights, interpolated in log T)."""
        return _quantile(self.duration, self.weights, q)


class TimedMoments(NamedTuple):
    """Moments of the prediction averaged over the timing posterior (standardised units)."""

    time: Array  # (Q,) real time from the observation's start
    time_mean: Array  # (Q, D)
    time_sd: Array  # (Q, D)
    phase: Array  # (P,)
    mean: Array  # (P, D)
    sd: Array  # (P, D)


def _quantile(values: np.ndarray, weights: np.ndarray, q) -> np.ndarray:
    order = np.argsort(values, kind="stable")
    v, w = np.log(values[order]), weights[order]
    cdf = np.cumsum(w) - 0.5 * w
    return np.exp(np.interp(np.asarray(q, dtype=float), cdf, v))


def _rows(time, timed, dof, order, values, sd) -> TimedRows:
    return TimedRows(
        time=jnp.asarray(time, dtype=jnp.float64), timed=jnp.asarray(timed, dtype=bool),
        dof=jnp.asarray(dof, dtype=jnp.int32), order=jnp.asarray(order, dtype=jnp.int32),
        values=jnp.asarray(values, dtype=jnp.float64), noise_var=jnp.asarray(np.asarray(sd) ** 2, dtype=jnp.float64),
    )


def timed_rows(
    time: np.ndarray, values: np.ndarray, *, noise_sd, scaling: Scaling, timed: bool = True
) -> TimedRows:
    """Rows of an observed (partial) movement: ``values`` (T, D) in data units at ``time`` (T,), NaN = unobserved.

    ``time`` is in seconds from the observation's start (``timed=True``) or in phases.
    ``noise_sd`` (scalar or (D,)) is in data units.
    """
    t = np.asarray(time, dtype=float)
    y = np.asarray(values, dtype=float)
    num_dofs = np.asarray(scaling.scale).shape[0]
    if t.ndim != 1 or y.shape != (t.shape[0], num_dofs):
        raise DataError(f"an observation needs times (T,) and values (T, {num_dofs}), got {t.shape} and {y.shape}")
    if not np.all(np.isfinite(t)) or np.any(np.isinf(y)):
        raise DataError("observation times must be finite and values finite or NaN")
    if timed and np.any(t < 0):
        raise DataError("observation times must be seconds from the movement's start (>= 0)")
    noise = _noise_per_dof("noise_sd", noise_sd, num_dofs)
    mask = np.isfinite(y)
    index_t, index_k = np.nonzero(mask)
    scale, mean = np.asarray(scaling.scale, dtype=float), np.asarray(scaling.mean, dtype=float)
    return _rows(
        t[index_t], np.full(index_t.size, timed), index_k, np.full(index_t.size, POSITION),
        (y[index_t, index_k] - mean[index_k]) / scale[index_k], noise[index_k] / scale[index_k],
    )


def via_rows(
    at: np.ndarray,
    position: np.ndarray,
    *,
    velocity: np.ndarray | None = None,
    position_sd=0.0,
    velocity_sd=0.0,
    scaling: Scaling,
    timed: bool = False,
) -> TimedRows:
    """Rows of V via-points: ``position`` (V, D) and optionally ``velocity`` (V, D) in data units, NaN = free.

    ``at`` (V,) are phases (``timed=False``) or seconds from the observation's
    start.  ``position_sd`` / ``velocity_sd`` (scalar or (D,), data units) say
    how tightly to pass; 0 passes exactly.
    """
    at = np.asarray(at, dtype=float)
    num_dofs = np.asarray(scaling.scale).shape[0]
    position = np.asarray(position, dtype=float)
    if at.ndim != 1 or position.shape != (at.shape[0], num_dofs):
        raise DataError(f"via-points need times or phases (V,) and positions (V, {num_dofs}), got {at.shape} and {position.shape}")
    if not np.all(np.isfinite(at)):
        raise DataError("via-point times or phases must be finite")
    if not timed and (np.any(at < 0) or np.any(at > 1)):
        raise DataError("via-point phases must lie in [0, 1]")
    if timed and np.any(at < 0):
        raise DataError("via-point times must be >= 0 (seconds from the observation's start)")
    scale, mean = np.asarray(scaling.scale, dtype=float), np.asarray(scaling.mean, dtype=float)
    parts = []
    for order, table, sd, shift in (
        (POSITION, position, position_sd, mean),
        (VELOCITY, velocity, velocity_sd, np.zeros(num_dofs)),
    ):
        if table is None:
            continue
        table = np.asarray(table, dtype=float)
        if table.shape != position.shape or np.any(np.isinf(table)):
            raise DataError(f"via-point velocities must have shape {position.shape} (NaN = free), got {table.shape}")
        noise = _noise_per_dof("via-point sd", sd, num_dofs)
        index_v, index_k = np.nonzero(np.isfinite(table))
        parts.append(_rows(
            at[index_v], np.full(index_v.size, timed), index_k, np.full(index_v.size, order),
            (table[index_v, index_k] - shift[index_k]) / scale[index_k], noise[index_k] / scale[index_k],
        ))
    rows = join_rows(*parts)
    if rows.num_rows == 0:
        raise DataError("the via-points constrain nothing (every entry is NaN)")
    return rows


def join_rows(*rows: TimedRows) -> TimedRows:
    """Stack rows in the given order."""
    return TimedRows(*(jnp.concatenate(leaves, axis=0) for leaves in zip(*rows)))


def rows_at(rows: TimedRows, duration, start, *, num_dofs: int, num_basis: int, width: float = DEFAULT_WIDTH) -> Observation:
    r"""The :class:`Observation` of ``rows`` under duration ``T`` and start phase ``z0`` (traceable).

    Timed rows sit at phase :math:`z_0 + t/T`; velocity rows are
    :math:`\dot\psi(z)^T / T` (per second).
    """
    duration = jnp.asarray(duration, dtype=jnp.float64)
    phase = jnp.where(rows.timed, start + rows.time / duration, rows.time)
    value = rbf_basis(phase, num_basis, width)
    slope = rbf_basis_derivative(phase, num_basis, width) / duration
    phi = jnp.where((rows.order == VELOCITY)[:, None], slope, value)
    onehot = jax.nn.one_hot(rows.dof, num_dofs, dtype=phi.dtype)
    psi = (onehot[:, :, None] * phi[:, None, :]).reshape(rows.num_rows, num_dofs * num_basis)
    return Observation(psi, rows.values, rows.noise_var, phase, rows.dof, rows.order)


def duration_prior(durations: np.ndarray, min_scale: float = MIN_LOG_SCALE) -> DurationPrior:
    """Log-normal prior of a new movement's duration from training durations (module docstring)."""
    durations = np.asarray(durations, dtype=float)
    durations = durations[np.isfinite(durations)]
    if durations.size == 0 or np.any(durations <= 0):
        raise DataError("the duration prior needs positive training durations")
    logs = np.log(durations)
    spread = float(np.std(logs, ddof=1) * math.sqrt(1.0 + 1.0 / logs.size)) if logs.size > 1 else 0.0
    return DurationPrior(float(np.mean(logs)), max(spread, float(min_scale)))


def _row_bucket(num_rows: int) -> int:
    """The smallest of 4, 5, 6, 7 times a power of two that holds ``num_rows`` (at most 25 % more)."""
    power = 1
    while 7 * power < num_rows:
        power *= 2
    return next(m * power for m in (4, 5, 6, 7) if m * power >= num_rows)


def _padded_rows(rows: TimedRows, num_dofs: int) -> tuple[TimedRows, int]:
    r"""``rows`` padded to :func:`_row_bucket` rows that observe nothing: DoF ``num_dofs`` (out of range,
    so their design row is zero), value 0, noise variance 1.  Each adds exactly
    :math:`\log\mathcal N(0 | 0, 1)` to the log evidence at every timing."""
    num_pad = _row_bucket(rows.num_rows) - rows.num_rows
    if num_pad == 0:
        return rows, 0
    pad = lambda a, fill: jnp.concatenate([jnp.asarray(a), jnp.full((num_pad,), fill, dtype=jnp.asarray(a).dtype)])
    return TimedRows(time=pad(rows.time, 0.0), timed=pad(rows.timed, False), dof=pad(rows.dof, num_dofs),
                     order=pad(rows.order, POSITION), values=pad(rows.values, 0.0),
                     noise_var=pad(rows.noise_var, 1.0)), num_pad


def timing_log_likelihood(
    model: str, draws: dict, rows: TimedRows, duration: Array, start: Array, gamma, *,
    exact: bool = True, num_dofs: int, num_basis: int, width: float = DEFAULT_WIDTH,
) -> Array:
    r""":math:`\log \frac1S\sum_s p(\mathbf{o} | \tau, \theta_s)` at each timing ``(duration[g], start[g])``.

    ``draws`` holds the sites of ``model`` with one leading draw axis (S may be 1: a plug-in fit).
    The rows are padded to one of a few sizes (:func:`_padded_rows`; their exact, constant
    contribution taken off again), so observations of nearby lengths share one compiled program.
    """
    padded, num_pad = _padded_rows(rows, num_dofs)
    loglik = _timing_log_likelihood(model, draws, padded, duration, start, gamma, exact=exact, num_dofs=num_dofs,
                                    num_basis=num_basis, width=width)
    return loglik + 0.5 * num_pad * math.log(2.0 * math.pi)


@partial(jax.jit, static_argnames=("model", "exact", "num_dofs", "num_basis", "width"))
def _timing_log_likelihood(
    model: str, draws: dict, rows: TimedRows, duration: Array, start: Array, gamma, *,
    exact: bool = True, num_dofs: int, num_basis: int, width: float = DEFAULT_WIDTH,
) -> Array:
    num_draws = next(iter(draws.values())).shape[0]

    def one(timing):
        obs = rows_at(rows, timing[0], timing[1], num_dofs=num_dofs, num_basis=num_basis, width=width)
        evidence = jax.vmap(lambda p: condition(model, p, obs, gamma, exact=exact).log_evidence)(draws)
        return logsumexp(evidence) - math.log(num_draws)

    return jax.lax.map(one, jnp.stack([duration, start], axis=1), batch_size=8)


def _start_grid(max_start: float, size: int) -> np.ndarray:
    """The start phases of a timing grid: ``size`` points on ``[0, max_start]``, or only 0."""
    if not 0.0 <= max_start < 1.0:
        raise DataError(f"max_start must lie in [0, 1), got {max_start}")
    return np.linspace(0.0, max_start, size) if max_start > 0 else np.zeros(1)


def _grid(log_lo: float, log_hi: float, starts: np.ndarray, max_time: float, num: int):
    log_t = np.linspace(log_lo, log_hi, num)
    step = (log_hi - log_lo) / max(num - 1, 1)
    duration = np.repeat(np.exp(log_t), starts.size)
    start = np.tile(starts, num)
    start_step = starts[1] - starts[0] if starts.size > 1 else 1.0
    # a timing is possible when every observed time falls inside the movement
    possible = start + max_time / duration <= 1.0 + 1e-12
    return duration, start, np.log(step * start_step), possible


def timing_posterior(
    model: str, draws: dict, rows: TimedRows, prior: DurationPrior, gamma, *,
    exact: bool = True, num_dofs: int, num_basis: int, width: float = DEFAULT_WIDTH,
    max_start: float = 0.0, power: float | np.ndarray = 1.0, power_weights: np.ndarray | None = None,
    grid_size: int = GRID_SIZE, start_grid_size: int = START_GRID_SIZE,
) -> TimingPosterior:
    r"""The posterior over the duration (and, with ``max_start > 0``, the start phase) on a grid.

    ``power`` :math:`\kappa` tempers the likelihood, :math:`p_\kappa(\tau | \mathbf{o}) \propto
    p(\tau)\, p(\mathbf{o} | \tau)^\kappa`; several powers with ``power_weights`` :math:`\pi_k`
    give the mixture :math:`\sum_k \pi_k\, p_{\kappa_k}(\tau | \mathbf{o})`, each component
    normalised on the grid (the average over powers of :func:`lmpromp_ppl.api.calibrate_timing`).

    First pass: ``grid_size`` points in log T over the prior's ``loc +- 6 scale``
    (above the longest observed time), times ``start_grid_size`` start phases in
    ``[0, max_start]``.  Second pass: the same number of points over the range
    where the first pass's posterior exceeds :data:`RELATIVE_FLOOR` of its
    largest value, widened by one cell on each side.
    """
    starts = _start_grid(max_start, start_grid_size)
    timed = np.asarray(rows.timed)
    times = np.asarray(rows.time)[timed]
    if times.size == 0:
        raise DataError("estimating the timing needs observed values at times (seconds)")
    max_time = float(times.max())
    log_lo = prior.loc - 6.0 * prior.scale
    log_hi = prior.loc + 6.0 * prior.scale
    if max_time > 0:
        log_lo = max(log_lo, math.log(max_time))
        if log_hi <= log_lo:
            log_hi = log_lo + 6.0 * prior.scale
    basis = dict(exact=exact, num_dofs=num_dofs, num_basis=num_basis, width=width)
    powers, log_mix = power_mixture(power, power_weights)

    def evaluate(lo, hi):
        duration, start, log_cell, possible = _grid(lo, hi, starts, max_time, grid_size)
        loglik = np.asarray(timing_log_likelihood(model, draws, rows, jnp.asarray(duration), jnp.asarray(start),
                                                  gamma, **basis))
        # log T ~ N(loc, scale^2) and z0 ~ U[0, max_start], times the grid cell
        log_prior = prior.log_density(np.log(duration)) - (math.log(max_start) if max_start > 0 else 0.0) + log_cell
        ok = possible & np.isfinite(loglik)
        parts = np.where(ok[None], log_prior[None] + powers[:, None] * np.where(ok, loglik, 0.0)[None], -np.inf)
        if powers.size == 1:
            log_post = parts[0]
        else:  # each tempered posterior normalised on this grid, then mixed
            parts = parts - np.asarray(logsumexp(jnp.asarray(parts), axis=1, keepdims=True))
            log_post = np.asarray(logsumexp(jnp.asarray(parts + log_mix[:, None]), axis=0))
        return duration, start, log_prior, np.where(possible, loglik, -np.inf), log_post

    duration, start, log_prior, loglik, log_post = evaluate(log_lo, log_hi)
    if not np.any(np.isfinite(log_post)):
        raise DataError("no timing on the grid explains the observation (every likelihood is zero)")
    keep = log_post >= np.max(log_post) + math.log(RELATIVE_FLOOR)
    step = (log_hi - log_lo) / (grid_size - 1)
    lo = max(log_lo, float(np.log(duration[keep]).min()) - step)
    hi = min(log_hi, float(np.log(duration[keep]).max()) + step)
    if hi - lo > 1e-9:
        duration, start, log_prior, loglik, log_post = evaluate(lo, hi)
    weights = np.exp(log_post - logsumexp(jnp.asarray(log_post)))
    weights = weights / weights.sum()
    order = np.argsort(start, kind="stable")
    start_median = float(np.interp(0.5, np.cumsum(weights[order]) - 0.5 * weights[order], start[order])) \
        if max_start > 0 else 0.0
    return TimingPosterior(
        duration=duration, start=start, log_prior=log_prior, log_likelihood=loglik, weights=weights,
        estimate=float(_quantile(duration, weights, 0.5)), interval=_quantile(duration, weights, [0.05, 0.95]),
        start_estimate=start_median,
    )


def power_mixture(power, power_weights) -> tuple[np.ndarray, np.ndarray]:
    """The powers with positive weight and their log weights (normalised)."""
    powers = np.atleast_1d(np.asarray(power, dtype=float))
    if powers.ndim != 1 or powers.size == 0 or np.any(~np.isfinite(powers)) or np.any(powers < 0) or np.any(powers > 1):
        raise DataError(f"timing powers must lie in [0, 1], got {power!r}")
    if power_weights is None:
        if powers.size != 1:
            raise DataError("several timing powers need their weights")
        return powers, np.zeros(1)
    weights = np.atleast_1d(np.asarray(power_weights, dtype=float))
    if weights.shape != powers.shape or np.any(~np.isfinite(weights)) or np.any(weights < 0) or weights.sum() <= 0:
        raise DataError(f"timing power weights must be {powers.size} non-negative numbers, not all 0")
    keep = weights > 0
    with np.errstate(divide="ignore"):
        return powers[keep], np.log(weights[keep] / weights.sum())


class TimingCurve(NamedTuple):
    """The log likelihood of the duration on one fixed grid in log T over the prior's range: of the
    duration alone (start 0), or, with ``start``, of the duration and the start phase (uniform prior)."""

    log_duration: np.ndarray  # (G,)
    log_prior: np.ndarray  # (G,) log prior density of log T
    log_likelihood: np.ndarray  # (G,) log p(o | T), or (G, S) log p(o | T, z0) (-inf where impossible)
    start: np.ndarray | None = None  # (S,) start phases z0 on [0, max_start], or None (start 0)


def timing_curve(
    model: str, draws: dict, rows: TimedRows, prior: DurationPrior, gamma, *,
    exact: bool = True, num_dofs: int, num_basis: int, width: float = DEFAULT_WIDTH, grid_size: int = CURVE_GRID_SIZE,
    max_start: float = 0.0, start_grid_size: int = START_GRID_SIZE,
) -> TimingCurve:
    """:func:`timing_log_likelihood` on ``grid_size`` points in log T over the prior's ``loc +- 6 scale``
    (above the longest observed time), for any power of the likelihood (:func:`tempered_log_score`);
    with ``max_start > 0`` times ``start_grid_size`` start phases on ``[0, max_start]``, as
    :func:`timing_posterior` weighs an observation that may have begun after the movement."""
    starts = _start_grid(max_start, start_grid_size)
    times = np.asarray(rows.time)[np.asarray(rows.timed)]
    if times.size == 0:
        raise DataError("estimating the timing needs observed values at times (seconds)")
    max_time = float(times.max())
    log_lo = max(prior.loc - 6.0 * prior.scale, math.log(max(max_time, 1e-300)))
    log_hi = max(prior.loc + 6.0 * prior.scale, log_lo + 6.0 * prior.scale)
    log_t = np.linspace(log_lo, log_hi, grid_size)
    duration, start, _, possible = _grid(log_lo, log_hi, starts, max_time, grid_size)
    loglik = np.asarray(timing_log_likelihood(model, draws, rows, jnp.asarray(duration), jnp.asarray(start), gamma,
                                              exact=exact, num_dofs=num_dofs, num_basis=num_basis, width=width))
    if max_start == 0:
        return TimingCurve(log_t, prior.log_density(log_t), loglik)
    loglik = np.where(possible, loglik, -np.inf).reshape(grid_size, starts.size)
    return TimingCurve(log_t, prior.log_density(log_t), loglik, starts)


def tempered_log_score(curve: TimingCurve, log_duration: float, powers: np.ndarray = TIMING_POWERS) -> np.ndarray:
    r"""Log density of the true ``log_duration`` under the tempered posterior, for each power :math:`\kappa`:

    .. math::

        \log p_\kappa(\log T^\ast | \mathbf{o}), \qquad
        p_\kappa(\log T | \mathbf{o}) \propto p(\log T)\, p(\mathbf{o} | T)^\kappa,

    normalised by the trapezoidal rule on the curve's grid (the log density
    interpolated linearly between grid points); a duration off the
    grid scores ``log(1e-300)``.  A curve with start phases tempers the joint
    likelihood and integrates the start out (uniform prior, trapezoidal rule):
    :math:`p_\kappa(\log T | \mathbf{o}) \propto p(\log T)\int p(\mathbf{o} | T, z_0)^\kappa\,dz_0`,
    a timing the observation cannot fit (it would run past the movement's end)
    excluded at every power.  Summed over held-out demonstrations it is the
    cross-validated log score that :func:`lmpromp_ppl.api.calibrate_timing` maximises.
    """
    powers = np.asarray(powers, dtype=float)
    if curve.start is None:
        loglik = np.where(np.isfinite(curve.log_likelihood), curve.log_likelihood, -1e300)  # 0 * -inf is NaN
        log_post = curve.log_prior[None, :] + powers[:, None] * loglik[None, :]
    else:  # p_kappa(log T, z0 | o) on the grid, z0 integrated out (trapezoid); impossible timings excluded at any power
        loglik = np.where(np.isfinite(curve.log_likelihood), curve.log_likelihood, 0.0)
        joint = np.where(np.isfinite(curve.log_likelihood)[None], powers[:, None, None] * loglik[None], -np.inf)
        top = np.max(joint, axis=(1, 2), keepdims=True)
        marginal = np.trapezoid(np.exp(joint - top), curve.start, axis=2)
        with np.errstate(divide="ignore"):
            log_post = curve.log_prior[None, :] + np.log(marginal)
        log_post = np.where(np.isfinite(log_post), log_post, -1e300)
    log_post = log_post - np.max(log_post, axis=1, keepdims=True)
    log_norm = np.log(np.trapezoid(np.exp(log_post), curve.log_duration, axis=1))
    if not curve.log_duration[0] <= log_duration <= curve.log_duration[-1]:
        return np.full(powers.size, math.log(1e-300))
    # interpolated in log density: exact where the log density is linear, accurate in the tails
    at = np.array([np.interp(log_duration, curve.log_duration, lp) for lp in log_post])
    return np.maximum(at - log_norm, math.log(1e-300))


def _mixture_moments(weights: np.ndarray, means: Array, sds: Array) -> tuple[Array, Array]:
    w = jnp.asarray(weights)[:, None, None]
    mean = jnp.sum(w * means, axis=0)
    second = jnp.sum(w * (sds**2 + means**2), axis=0)
    return mean, jnp.sqrt(jnp.maximum(second - mean**2, 0.0))


def timed_moments(
    posteriors: list[GaussianMixture], weights: np.ndarray, durations: np.ndarray, starts: np.ndarray,
    time: np.ndarray, phase: np.ndarray, *, num_dofs: int, num_basis: int, width: float = DEFAULT_WIDTH,
) -> TimedMoments:
    """Moments averaged over timing grid points (weights summing to 1), each with its conditioned weights.

    Real time ``t`` maps to phase ``min(z0 + t/T, 1)`` at each grid point (a movement rests at its end).
    """
    basis = dict(num_dofs=num_dofs, num_basis=num_basis, width=width)
    t_means, t_sds, z_means, z_sds = [], [], [], []
    for post, duration, start in zip(posteriors, durations, starts):
        at = np.clip(start + np.asarray(time) / duration, 0.0, 1.0)
        in_time = trajectory_distribution(post, at, **basis)
        in_phase = trajectory_distribution(post, phase, **basis)
        t_means.append(in_time.mean), t_sds.append(in_time.sd)
        z_means.append(in_phase.mean), z_sds.append(in_phase.sd)
    weights = np.asarray(weights) / np.sum(weights)
    time_mean, time_sd = _mixture_moments(weights, jnp.stack(t_means), jnp.stack(t_sds))
    mean, sd = _mixture_moments(weights, jnp.stack(z_means), jnp.stack(z_sds))
    return TimedMoments(jnp.asarray(time), time_mean, time_sd, jnp.asarray(phase), mean, sd)


def timing_nodes(weights: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """The grid points (indices) and weights of a ``count``-point quadrature of the timing posterior.

    Systematic resampling at the midpoint quantiles :math:`(i + 1/2)/n` of the
    grid's cumulative weights (in the grid's order), repeated points merged:
    every point carries mass :math:`1/n` (or a multiple), so the quadrature
    keeps the posterior's spread and tails, which keeping the heaviest points
    would cut.  The prediction conditions on the observation once per node.
    """
    weights = np.asarray(weights, dtype=float)
    cumulative = np.cumsum(weights / weights.sum())
    targets = (np.arange(count) + 0.5) / count
    index = np.minimum(np.searchsorted(cumulative, targets), weights.size - 1)
    nodes, counts = np.unique(index, return_counts=True)
    return nodes, counts / count


def sample_over_timing(key, posteriors: list[GaussianMixture], weights: np.ndarray, phase: np.ndarray,
                       num_samples: int, *, num_dofs: int, num_basis: int, width: float = DEFAULT_WIDTH) -> np.ndarray:
    """Trajectories (N, P, D) at ``phase``: a grid point drawn by its weight, then weights from its predictive."""
    key_grid, key_weights = jax.random.split(key)
    weights = np.asarray(weights) / np.sum(weights)
    choice = np.asarray(jax.random.choice(key_grid, weights.size, (num_samples,), p=jnp.asarray(weights)))
    design = rbf_basis(phase, num_basis, width)  # (P, J)
    out = np.empty((num_samples, len(phase), num_dofs))
    for n, (g, k) in enumerate(zip(choice, jax.random.split(key_weights, num_samples))):
        w = np.asarray(sample_weights(k, posteriors[g], 1))[0].reshape(num_dofs, num_basis)
        out[n] = np.asarray(design) @ w.T
    return out

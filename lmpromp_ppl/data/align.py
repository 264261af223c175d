r"""Aligning the phases of demonstrations of different speeds (dynamic time warping).

A ProMP maps each demonstration's time linearly to the phase, so two
demonstrations of one movement performed with different speed *profiles* (a
slow start, a fast middle) put the same part of the movement at different
phases, and the movement distribution blurs it.  :func:`align_phases` gives
each sample a phase on a common clock instead:

1. every demonstration is resampled at ``num_points`` equally spaced linear
   phases and each DoF is scaled to unit variance over all demonstrations;
2. the reference is the medoid (the demonstration with the least summed
   squared Euclidean distance to the others at linear phase); with
   ``by_label`` one per label (each known movement type on its own clock;
   off by default, since a mixture fit must not see the labels);
3. dynamic time warping of each demonstration against its reference, with a
   Sakoe-Chiba band of ``band`` times the length (no sample moves more than
   that fraction of the movement), gives a monotone path; a sample's phase is
   the mean linear phase of the reference samples it is matched to, smoothed
   over ``smooth`` of the movement, made non-decreasing and pinned to 0 and 1.

The result is the same :class:`~lmpromp_ppl.data.Demonstrations` with
``warp`` set: the model, every engine and the stored fit
(``observed_data.aligned_phase``) use the aligned phases.  The reference keeps
its linear phase, so the model's phase is the reference's time over its
duration; a new movement's timing (:mod:`lmpromp_ppl.predict.timing`) is
estimated on that clock.

The cumulative cost of each row of the DTW table is a running minimum,
:math:`D_{ij} = S_j + \min_{k \le j} (a_k - S_{k-1})` with :math:`S` the
row's cumulative cost and :math:`a_k = \min(D_{i-1,k-1}, D_{i-1,k})`, so a
row takes a few vectorised operations and a 200-point alignment about a
millisecond.
"""

from __future__ import annotations

import numpy as np

from lmpromp_ppl.data.core import Demonstrations
from lmpromp_ppl.errors import DataError

__all__ = ["ALIGN_METHODS", "align_phases", "dtw_path"]

#: ``align=`` values that :func:`lmpromp_ppl.fit` and ``lmpromp fit --align`` take.
ALIGN_METHODS = ("dtw",)


def dtw_path(cost: np.ndarray, band: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The minimum-cost monotone path through ``cost`` (n, m) from (0, 0) to (n-1, m-1).

    Steps (1, 1), (1, 0), (0, 1); with ``band``, cells farther than ``band``
    from the diagonal (rescaled to the table's shape) are excluded.
    Returns the row and column indices of the path, in order.
    """
    cost = np.asarray(cost, dtype=float)
    n, m = cost.shape
    cols = np.arange(m)
    allowed = np.ones((n, m), dtype=bool)
    if band is not None:
        centre = np.arange(n)[:, None] * (m - 1) / max(n - 1, 1)
        allowed = np.abs(cols[None, :] - centre) <= max(band, abs(m - n) + 1)
    table = np.full((n, m), np.inf)
    row_cost = np.where(allowed[0], cost[0], np.inf)
    table[0] = np.cumsum(row_cost)
    for i in range(1, n):
        previous = table[i - 1]
        a = np.minimum(previous, np.concatenate([[np.inf], previous[:-1]]))
        c = np.where(allowed[i], cost[i], 0.0)
        cumulative = np.cumsum(c)
        shifted = np.concatenate([[0.0], cumulative[:-1]])
        row = cumulative + np.minimum.accumulate(np.where(allowed[i], a - shifted, np.inf))
        table[i] = np.where(allowed[i], row, np.inf)
    if not np.isfinite(table[-1, -1]):
        raise DataError("no warping path within the band; widen it")
    i, j = n - 1, m - 1
    rows, columns = [i], [j]
    while i > 0 or j > 0:
        options = (
            (table[i - 1, j - 1] if i > 0 and j > 0 else np.inf, i - 1, j - 1),
            (table[i - 1, j] if i > 0 else np.inf, i - 1, j),
            (table[i, j - 1] if j > 0 else np.inf, i, j - 1),
        )
        _, i, j = min(options, key=lambda o: o[0])
        rows.append(i)
        columns.append(j)
    return np.array(rows[::-1]), np.array(columns[::-1])


def _resampled(demos: Demonstrations, grid: np.ndarray, scale: np.ndarray) -> list[np.ndarray]:
    out = []
    for t, y in zip(demos.times, demos.positions):
        z = (t - t[0]) / (t[-1] - t[0])
        out.append(np.stack([np.interp(grid, z, y[:, d]) for d in range(y.shape[1])], axis=1) / scale)
    return out


def _medoid(curves: list[np.ndarray], members: np.ndarray) -> int:
    stack = np.stack([curves[i] for i in members])
    distance = ((stack[:, None] - stack[None]) ** 2).sum(axis=(2, 3))
    return int(members[np.argmin(distance.sum(axis=1))])


def align_phases(
    demos: Demonstrations,
    method: str = "dtw",
    *,
    num_points: int = 200,
    band: float = 0.2,
    smooth: float = 0.05,
    by_label: bool = False,
) -> Demonstrations:
    """``demos`` with aligned phases (``warp``); the method is the module docstring's.

    Parameters
    ----------
    demos : the demonstrations (data units; each DoF is scaled internally)
    method : ``"dtw"``
    num_points : samples per demonstration at which the warping is computed
    band : the Sakoe-Chiba band, a fraction of the movement in (0, 1]
    smooth : width of the moving average applied to each warp, a fraction of the movement
    by_label : one reference per label of ``demos.labels``
    """
    if method not in ALIGN_METHODS:
        raise DataError(f"unknown alignment {method!r}; choose from {', '.join(ALIGN_METHODS)}")
    if not (0.0 < band <= 1.0):
        raise DataError(f"band must lie in (0, 1], got {band}")
    if not (0.0 <= smooth < 0.5):
        raise DataError(f"smooth must lie in [0, 0.5), got {smooth}")
    if num_points < 10:
        raise DataError(f"num_points must be at least 10, got {num_points}")
    grid = np.linspace(0.0, 1.0, num_points)
    scale = np.concatenate(demos.positions).std(axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    curves = _resampled(demos, grid, scale)
    labels = np.zeros(demos.num_demos, dtype=int) if demos.labels is None or not by_label else np.unique(demos.labels, return_inverse=True)[1]
    width = max(int(round(smooth * num_points)), 1)
    kernel = np.ones(width) / width
    warps, references = [], {}
    for label in np.unique(labels):
        references[int(label)] = _medoid(curves, np.flatnonzero(labels == label))
    for i, (t, curve) in enumerate(zip(demos.times, curves)):
        reference = curves[references[int(labels[i])]]
        cost = ((curve[:, None, :] - reference[None, :, :]) ** 2).sum(axis=-1)
        rows, cols = dtw_path(cost, band=int(round(band * num_points)))
        matched = np.bincount(rows, weights=grid[cols], minlength=num_points) / np.bincount(rows, minlength=num_points)
        if width > 1:
            padded = np.concatenate([np.full(width, matched[0]), matched, np.full(width, matched[-1])])
            matched = np.convolve(padded, kernel, mode="same")[width:-width]
        matched = np.maximum.accumulate(np.clip(matched, 0.0, 1.0))
        z = np.interp((t - t[0]) / (t[-1] - t[0]), grid, matched)
        z = (z - z[0]) / (z[-1] - z[0]) if z[-1] > z[0] else (t - t[0]) / (t[-1] - t[0])
        z[0], z[-1] = 0.0, 1.0
        warps.append(np.maximum.accumulate(z))
    return demos.with_warp(warps)

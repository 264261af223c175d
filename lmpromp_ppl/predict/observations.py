r"""Linear-Gaussian observations of a (possibly partial) new movement (thesis Sec. 3.1.2).

An :class:`Observation` is the triple :math:`(\Psi_o, \mathbf{o}, \Sigma_o)` of
eqs. (3.2), (3.3) and (4.4)-(4.7): every row observes one scalar
:math:`o_n = \psi_n^T \mathbf{w} + \epsilon_n` with
:math:`\epsilon_n \sim \mathcal{N}(0, \sigma_n^2)`, so :math:`\Sigma_o` is diagonal.
A row is a position (a row of :func:`lmpromp_ppl.basis.design_matrix`) or a
velocity (a row of :func:`lmpromp_ppl.basis.velocity_design_matrix`) of one DoF
at one phase.  Rows may observe any subset of the DoF at any subset of phases,
so partial observations ("only DoF 0 at the first three phases") and
via-points are the same object.  :func:`concatenate` joins observations.

Everything lives in the standardised space of the fit (see
:class:`lmpromp_ppl.data.Scaling`); pass ``scaling=`` to the builders to
standardise values and noise given in the original units.

The builders check their input with NumPy and raise :class:`DataError` on a
problem; they are not meant to be traced.  The :class:`Observation` they return
is a pytree of arrays and can be passed to the jit-compiled conditioning
functions.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np
import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

from lmpromp_ppl.basis import DEFAULT_WIDTH, design_matrix, velocity_design_matrix
from lmpromp_ppl.data.core import Scaling
from lmpromp_ppl.errors import DataError

__all__ = [
    "POSITION",
    "VELOCITY",
    "Observation",
    "observe",
    "via_point",
    "concatenate",
    "empty_observation",
]

#: Value of :attr:`Observation.order` for a position row.
POSITION = 0
#: Value of :attr:`Observation.order` for a velocity row.
VELOCITY = 1


class Observation(NamedTuple):
    r"""Observed rows :math:`\mathbf{o} = \Psi_o \mathbf{w} + \epsilon`, :math:`\epsilon \sim \mathcal{N}(0, \Sigma_o)`.

    Attributes
    ----------
    psi : (N, d) array
        :math:`\Psi_o`, one row per observed scalar.
    values : (N,) array
        :math:`\mathbf{o}` (standardised units).
    noise_var : (N,) array
        Diagonal of :math:`\Sigma_o` (variances, standardised units, >= 0).
    phase : (N,) array
        Phase of each row.
    dof : (N,) int array
        DoF of each row.
    order : (N,) int array
        :data:`POSITION` (0) or :data:`VELOCITY` (1).
    """

    psi: Array
    values: Array
    noise_var: Array
    phase: Array
    dof: Array
    order: Array

    @property
    def num_rows(self) -> int:
        """N, the number of observed scalars."""
        return self.values.shape[0]

    @property
    def num_weights(self) -> int:
        """d, the weight dimension."""
        return self.psi.shape[1]

    @property
    def cov(self) -> Array:
        r""":math:`\Sigma_o` as a dense (N, N) diagonal matrix."""
        return jnp.diag(self.noise_var)


def _float_array(name: str, value: ArrayLike) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DataError(f"{name} is not numeric: {exc}") from None
    return arr


def _select_dofs(dofs: Sequence[int] | None, num_dofs: int) -> np.ndarray:
    if isinstance(num_dofs, bool) or int(num_dofs) != num_dofs or num_dofs < 1:
        raise DataError(f"num_dofs must be an integer >= 1, got {num_dofs!r}")
    if dofs is None:
        return np.arange(num_dofs)
    sel = np.atleast_1d(np.asarray(dofs))
    if sel.ndim != 1 or sel.size == 0 or not np.issubdtype(sel.dtype, np.integer):
        raise DataError(f"dofs must be a non-empty list of integer DoF indices, got {dofs!r}")
    if np.any(sel < 0) or np.any(sel >= num_dofs):
        raise DataError(f"dofs {sel.tolist()} out of range for {num_dofs} DoF")
    if np.unique(sel).size != sel.size:
        raise DataError(f"dofs {sel.tolist()} contain duplicates")
    return sel


def _noise_per_dof(name: str, noise_sd: ArrayLike, num_selected: int) -> np.ndarray:
    sd = _float_array(name, noise_sd)
    if sd.ndim == 0:
        sd = np.full(num_selected, float(sd))
    if sd.shape != (num_selected,):
        raise DataError(
            f"{name} must be a scalar or have one entry per observed DoF ({num_selected}), got shape {sd.shape}"
        )
    if not np.all(np.isfinite(sd)) or np.any(sd < 0):
        raise DataError(f"{name} must be finite and non-negative, got {sd.tolist()}")
    return sd


def _values_table(name: str, values: ArrayLike, num_times: int, num_selected: int) -> np.ndarray:
    arr = _float_array(name, values)
    if arr.ndim == 1 and num_selected == 1 and arr.shape[0] == num_times:
        arr = arr[:, None]
    if arr.shape != (num_times, num_selected):
        raise DataError(
            f"{name} must have shape ({num_times}, {num_selected}) (phases x observed DoF), got {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise DataError(f"{name} contain NaN or inf")
    return arr


def _check_basis(num_basis: int, width: float) -> None:
    if isinstance(num_basis, bool) or int(num_basis) != num_basis or num_basis < 2:
        raise DataError(f"num_basis must be an integer >= 2, got {num_basis!r}")
    if not np.isfinite(width) or width <= 0:
        raise DataError(f"width must be positive and finite, got {width!r}")


def _build(
    rows: np.ndarray,
    values: np.ndarray,
    sd: np.ndarray,
    phase: np.ndarray,
    sel: np.ndarray,
    order: int,
) -> Observation:
    num_times, num_selected = values.shape
    return Observation(
        psi=jnp.asarray(rows),
        values=jnp.asarray(values.reshape(-1)),
        noise_var=jnp.asarray(np.tile(sd**2, num_times)),
        phase=jnp.asarray(np.repeat(phase, num_selected)),
        dof=jnp.asarray(np.tile(sel, num_times), dtype=jnp.int32),
        order=jnp.full(num_times * num_selected, order, dtype=jnp.int32),
    )


def observe(
    phase: ArrayLike,
    values: ArrayLike,
    *,
    dofs: Sequence[int] | None = None,
    noise_sd: ArrayLike = 0.1,
    num_dofs: int,
    num_basis: int,
    width: float = DEFAULT_WIDTH,
    mask: ArrayLike | None = None,
    scaling: Scaling | None = None,
) -> Observation:
    r"""Observe positions of some DoF at some phases (:math:`\Psi_o`, :math:`\mathbf{o}`, :math:`\Sigma_o` of eq. 3.2).

    Parameters
    ----------
    phase : (T,) array
        Phases in [0, 1] (any order, irregular spacing allowed).
    values : (T, len(dofs)) array
        Observed positions; (T,) is accepted when one DoF is observed.
    dofs : sequence of int, optional
        Indices of the observed DoF (default: all ``num_dofs``).
    noise_sd : float or (len(dofs),) array
        Observation-noise standard deviation per observed DoF (0 for
        noiseless).  The default 0.1 is :math:`\beta^{-1/2}` for the default
        ``beta = 100`` of :mod:`lmpromp_ppl.models.hyper`.
    num_dofs, num_basis, width
        The basis of the fit (:func:`lmpromp_ppl.basis.design_matrix`).
    mask : (T, len(dofs)) bool array, optional
        ``True`` where an entry is observed; other entries are dropped, so any
        subset of (phase, DoF) pairs can be observed.
    scaling : Scaling, optional
        When given, ``values`` and ``noise_sd`` are in the original units and
        are standardised with it.

    Returns
    -------
    Observation
        Rows ordered time-major over the selected DoF (row ``t * len(dofs) + j``
        is DoF ``dofs[j]`` at ``phase[t]``), masked entries removed.
    """
    _check_basis(num_basis, width)
    sel = _select_dofs(dofs, num_dofs)
    z = _float_array("phase", phase)
    if z.ndim != 1:
        raise DataError(f"phase must be one-dimensional, got shape {z.shape}")
    if not np.all(np.isfinite(z)):
        raise DataError("phase contains NaN or inf")
    table = _values_table("values", values, z.shape[0], sel.size)
    sd = _noise_per_dof("noise_sd", noise_sd, sel.size)
    if scaling is not None:
        scale = _scaling_scale(scaling, num_dofs)[sel]
        table = (table - np.asarray(scaling.mean, dtype=np.float64)[sel]) / scale
        sd = sd / scale
    full = np.asarray(design_matrix(z, num_dofs, num_basis, width))
    rows = full.reshape(z.shape[0], num_dofs, -1)[:, sel, :].reshape(z.shape[0] * sel.size, -1)
    obs = _build(rows, table, sd, z, sel, POSITION)
    if mask is None:
        return obs
    keep = np.asarray(mask)
    if keep.shape != table.shape or keep.dtype != np.bool_:
        raise DataError(f"mask must be a boolean array of shape {table.shape}, got {keep.dtype} {keep.shape}")
    index = np.flatnonzero(keep.reshape(-1))
    return Observation(*(leaf[index] for leaf in obs))


def _scaling_scale(scaling: Scaling, num_dofs: int) -> np.ndarray:
    scale = np.asarray(scaling.scale, dtype=np.float64)
    if scale.shape != (num_dofs,) or np.asarray(scaling.mean).shape != (num_dofs,):
        raise DataError(f"scaling is for {scale.shape} DoF, the basis has {num_dofs}")
    return scale


def via_point(
    phase: float,
    position: ArrayLike,
    *,
    velocity: ArrayLike | None = None,
    dofs: Sequence[int] | None = None,
    position_sd: ArrayLike = 1e-3,
    velocity_sd: ArrayLike = 1e-3,
    duration: float = 1.0,
    num_dofs: int,
    num_basis: int,
    width: float = DEFAULT_WIDTH,
    scaling: Scaling | None = None,
) -> Observation:
    r"""A via-point: a position, optionally a velocity, at one phase.

    The velocity rows are :math:`\dot\psi(z)^T / \text{duration}`
    (:func:`lmpromp_ppl.basis.velocity_design_matrix`), so ``velocity`` is a
    time derivative for a movement lasting ``duration`` (phase derivative when
    ``duration = 1``).

    Parameters
    ----------
    phase : float
        Phase of the via-point.
    position : (len(dofs),) array
        Position of the selected DoF.
    velocity : (len(dofs),) array, optional
        Velocity of the selected DoF.
    dofs : sequence of int, optional
        Selected DoF (default all).
    position_sd, velocity_sd : float or (len(dofs),) array
        Noise standard deviations (how tightly to pass through the point).
    duration : float
        Movement duration that maps phase velocity to time velocity.
    num_dofs, num_basis, width
        The basis of the fit.
    scaling : Scaling, optional
        When given, position, velocity and the noise are in original units.

    Returns
    -------
    Observation
        Position rows followed by velocity rows.
    """
    _check_basis(num_basis, width)
    sel = _select_dofs(dofs, num_dofs)
    z = _float_array("phase", phase)
    if z.ndim != 0 or not np.isfinite(z):
        raise DataError(f"phase of a via-point must be a finite scalar, got {phase!r}")
    if not np.isfinite(duration) or duration <= 0:
        raise DataError(f"duration must be positive and finite, got {duration!r}")
    z = z[None]
    pos = _values_table("position", np.atleast_1d(_float_array("position", position))[None, :], 1, sel.size)
    pos_sd = _noise_per_dof("position_sd", position_sd, sel.size)
    scale = None if scaling is None else _scaling_scale(scaling, num_dofs)[sel]
    if scale is not None:
        pos = (pos - np.asarray(scaling.mean, dtype=np.float64)[sel]) / scale
        pos_sd = pos_sd / scale
    pos_rows = np.asarray(design_matrix(z, num_dofs, num_basis, width))[sel]
    parts = [_build(pos_rows, pos, pos_sd, z, sel, POSITION)]
    if velocity is not None:
        vel = _values_table("velocity", np.atleast_1d(_float_array("velocity", velocity))[None, :], 1, sel.size)
        vel_sd = _noise_per_dof("velocity_sd", velocity_sd, sel.size)
        if scale is not None:
            vel = vel / scale
            vel_sd = vel_sd / scale
        vel_rows = np.asarray(velocity_design_matrix(z, num_dofs, num_basis, duration, width))[sel]
        parts.append(_build(vel_rows, vel, vel_sd, z, sel, VELOCITY))
    return concatenate(*parts)


def concatenate(*observations: Observation) -> Observation:
    """Join observations of the same weight space (rows stacked in the given order)."""
    if not observations:
        raise DataError("concatenate needs at least one observation")
    sizes = {obs.psi.shape[1] for obs in observations}
    if len(sizes) != 1:
        raise DataError(f"observations have different weight dimensions {sorted(sizes)}")
    return Observation(*(jnp.concatenate(leaves, axis=0) for leaves in zip(*observations)))


def empty_observation(num_weights: int) -> Observation:
    """An observation with no rows: conditioning on it returns the prior."""
    return Observation(
        psi=jnp.zeros((0, num_weights)),
        values=jnp.zeros((0,)),
        noise_var=jnp.zeros((0,)),
        phase=jnp.zeros((0,)),
        dof=jnp.zeros((0,), dtype=jnp.int32),
        order=jnp.zeros((0,), dtype=jnp.int32),
    )

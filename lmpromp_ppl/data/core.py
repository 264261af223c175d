"""The :class:`Demonstrations` type and its conversion to model inputs.

Demonstrations hold per-demonstration times ``(T_i,)`` and positions
``(T_i, D)``; lengths may differ.  :meth:`Demonstrations.phases` maps each
demonstration's time to [0, 1] by its own start and duration (docs/cli.md).
:func:`standardise` scales each DoF to zero mean and unit variance on the
training set; the :class:`Scaling` is stored with every fit.
:func:`model_data` turns demonstrations into the padded arrays that every
engine consumes (:class:`ModelData`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple, Sequence

import numpy as np
import jax.numpy as jnp
from jax import Array

from lmpromp_ppl.basis import DEFAULT_WIDTH, design_matrix
from lmpromp_ppl.errors import DataError

__all__ = ["Demonstrations", "Scaling", "ModelData", "standardise", "model_data"]


def _as_float(name: str, a, ndim: int) -> np.ndarray:
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DataError(f"{name} is not numeric: {exc}") from None
    if arr.ndim != ndim:
        raise DataError(f"{name} must have {ndim} dimension(s), got shape {arr.shape}")
    return arr


@dataclass(frozen=True, eq=False)
class Demonstrations:
    """A set of demonstrated trajectories.

    Attributes
    ----------
    times : tuple of (T_i,) float arrays, strictly increasing
    positions : tuple of (T_i, D) float arrays
    labels : (L,) unicode array or None (e.g. movement types)
    dof_names : tuple of D strings
    name : free-text name of the dataset
    """

    times: tuple[np.ndarray, ...]
    positions: tuple[np.ndarray, ...]
    labels: np.ndarray | None = None
    dof_names: tuple[str, ...] = ()
    name: str = ""
    metadata: dict = field(default_factory=dict)

    def __post_init__(self):
        times = tuple(self.times)
        positions = tuple(self.positions)
        if len(times) != len(positions):
            raise DataError(
                f"got {len(times)} time arrays but {len(positions)} position arrays"
            )
        if len(times) < 2:
            raise DataError(f"need at least 2 demonstrations, got {len(times)}")
        t_out, y_out = [], []
        num_dofs = None
        for i, (t, y) in enumerate(zip(times, positions)):
            t = _as_float(f"times of demonstration {i}", t, 1)
            y = _as_float(f"positions of demonstration {i}", y, 2)
            if t.size == 0 or y.size == 0:
                raise DataError(f"demonstration {i} is empty")
            if y.shape[0] != t.shape[0]:
                raise DataError(
                    f"demonstration {i} has {t.shape[0]} times but {y.shape[0]} positions"
                )
            if num_dofs is None:
                num_dofs = y.shape[1]
            elif y.shape[1] != num_dofs:
                raise DataError(
                    f"ragged DoF: demonstration {i} has {y.shape[1]} DoF, demonstration 0 has {num_dofs}"
                )
            if not np.all(np.isfinite(t)):
                raise DataError(f"times of demonstration {i} contain NaN or inf")
            if not np.all(np.isfinite(y)):
                raise DataError(f"positions of demonstration {i} contain NaN or inf")
            if t.size > 1 and not np.all(np.diff(t) > 0):
                raise DataError(f"times of demonstration {i} are not strictly increasing")
            if t.size < 2:
                raise DataError(f"demonstration {i} has fewer than 2 samples")
            t.setflags(write=False)
            y.setflags(write=False)
            t_out.append(t)
            y_out.append(y)
        object.__setattr__(self, "times", tuple(t_out))
        object.__setattr__(self, "positions", tuple(y_out))
        if self.labels is not None:
            labels = np.asarray(self.labels).astype(str)
            if labels.shape != (len(t_out),):
                raise DataError(
                    f"labels must have shape ({len(t_out)},), got {labels.shape}"
                )
            object.__setattr__(self, "labels", labels)
        names = tuple(str(n) for n in self.dof_names) or tuple(f"dof{k}" for k in range(num_dofs))
        if len(names) != num_dofs:
            raise DataError(f"{len(names)} DoF names given for {num_dofs} DoF")
        object.__setattr__(self, "dof_names", names)

    # ------------------------------------------------------------------ shape
    @property
    def num_demos(self) -> int:
        return len(self.times)

    @property
    def num_dofs(self) -> int:
        return self.positions[0].shape[1]

    @property
    def lengths(self) -> np.ndarray:
        return np.array([t.shape[0] for t in self.times])

    def __len__(self) -> int:
        return self.num_demos

    def phases(self) -> tuple[np.ndarray, ...]:
        """Each demonstration's time mapped to [0, 1] by its own start and duration."""
        return tuple((t - t[0]) / (t[-1] - t[0]) for t in self.times)

    def subset(self, index: Sequence[int] | np.ndarray) -> "Demonstrations":
        """The demonstrations at ``index`` (a list of indices or a boolean mask)."""
        idx = np.arange(self.num_demos)[np.asarray(index)]
        return Demonstrations(
            times=tuple(self.times[i] for i in idx),
            positions=tuple(self.positions[i] for i in idx),
            labels=None if self.labels is None else self.labels[idx],
            dof_names=self.dof_names,
            name=self.name,
            metadata=dict(self.metadata),
        )

    def with_positions(self, positions: Sequence[np.ndarray]) -> "Demonstrations":
        """The same demonstrations with new positions (same shapes)."""
        return Demonstrations(
            self.times, tuple(positions), self.labels, self.dof_names, self.name, dict(self.metadata)
        )

    def __repr__(self) -> str:
        lengths = self.lengths
        span = f"{lengths.min()}" if lengths.min() == lengths.max() else f"{lengths.min()}-{lengths.max()}"
        return (
            f"Demonstrations(name={self.name!r}, L={self.num_demos}, D={self.num_dofs}, "
            f"T={span}, labels={None if self.labels is None else sorted(set(self.labels))})"
        )


@dataclass(frozen=True)
class Scaling:
    """Per-DoF affine scaling: ``standardised = (y - mean) / scale``."""

    mean: np.ndarray
    scale: np.ndarray

    def apply(self, y):
        return (np.asarray(y) - self.mean) / self.scale

    def invert(self, y):
        return np.asarray(y) * self.scale + self.mean

    def invert_sd(self, sd):
        return np.asarray(sd) * self.scale

    def to_dict(self) -> dict:
        return {"mean": np.asarray(self.mean).tolist(), "scale": np.asarray(self.scale).tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Scaling":
        return cls(np.asarray(d["mean"], dtype=float), np.asarray(d["scale"], dtype=float))

    @classmethod
    def identity(cls, num_dofs: int) -> "Scaling":
        return cls(np.zeros(num_dofs), np.ones(num_dofs))


def standardise(
    demos: Demonstrations, scaling: Scaling | None = None
) -> tuple[Demonstrations, Scaling]:
    """Scale each DoF to zero mean and unit variance over all samples.

    With ``scaling`` given (for test data), apply it instead of estimating one.
    A DoF with zero variance keeps scale 1.
    """
    if scaling is None:
        stacked = np.concatenate(demos.positions, axis=0)
        mean = stacked.mean(axis=0)
        scale = stacked.std(axis=0)
        scale = np.where(scale > 0, scale, 1.0)
        scaling = Scaling(mean, scale)
    return demos.with_positions([scaling.apply(y) for y in demos.positions]), scaling


class ModelData(NamedTuple):
    """Padded model inputs shared by every engine.

    Attributes
    ----------
    psi : (L, S, d) design matrices; padded rows are zero
    y : (L, S) flattened observations (time-major, see :mod:`lmpromp_ppl.basis`); 0 where padded
    mask : (L, S) 1.0 for an observed entry, 0.0 for padding or a missing value
    """

    psi: Array
    y: Array
    mask: Array

    @property
    def num_demos(self) -> int:
        return self.psi.shape[0]

    @property
    def num_weights(self) -> int:
        return self.psi.shape[2]

    def shares_psi(self) -> bool:
        """True when every demonstration has the same design matrix and no padding."""
        psi = np.asarray(self.psi)
        return bool(np.all(np.asarray(self.mask) == 1.0) and np.all(psi == psi[:1]))


def model_data(
    demos: Demonstrations, num_basis: int, width: float = DEFAULT_WIDTH, phases: Sequence[np.ndarray] | None = None
) -> ModelData:
    """Build :class:`ModelData` from (standardised) demonstrations.

    Demonstrations of different lengths are padded with masked rows.
    """
    phases = demos.phases() if phases is None else phases
    num_dofs = demos.num_dofs
    size = max(p.shape[0] for p in phases) * num_dofs
    d = num_dofs * num_basis
    psi = np.zeros((demos.num_demos, size, d))
    y = np.zeros((demos.num_demos, size))
    mask = np.zeros((demos.num_demos, size))
    for i, (z, pos) in enumerate(zip(phases, demos.positions)):
        n = z.shape[0] * num_dofs
        psi[i, :n] = np.asarray(design_matrix(z, num_dofs, num_basis, width))
        y[i, :n] = pos.reshape(-1)
        mask[i, :n] = 1.0
    return ModelData(jnp.asarray(psi), jnp.asarray(y), jnp.asarray(mask))

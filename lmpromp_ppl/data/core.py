"""The :class:`Demonstrations` type and its conversion to model inputs.

Demonstrations hold per-demonstration times ``(T_i,)`` and positions
``(T_i, D)``; lengths may differ.  :meth:`Demonstrations.phases` maps each
demonstration's time to [0, 1] by its own start and duration (docs/cli.md).
:func:`standardise` scales each DoF to zero mean and unit variance on the
training set; the :class:`Scaling` is stored with every fit.
:func:`model_data` turns demonstrations into the compact model inputs that
every engine consumes (:class:`PhaseData`: each demonstration's basis at its
phases, O(L T (J + D)) memory); :class:`ModelData` is the dense form with one
design matrix per demonstration, for any design.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple, Sequence

import numpy as np
import jax.numpy as jnp
from jax import Array

from lmpromp_ppl.basis import DEFAULT_WIDTH, rbf_basis
from lmpromp_ppl.errors import DataError

__all__ = [
    "Demonstrations", "Scaling", "ModelData", "PhaseData", "SharedDesign", "DemoStatistics", "as_float64",
    "gram_eigenbasis", "shared_design", "demo_statistics",
    "standardise", "model_data",
]


def _as_float(name: str, a, ndim: int) -> np.ndarray:
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DataError(f"{name} is not numeric: {exc}") from None
    if arr.ndim != ndim:
        raise DataError(f"{name} must have {ndim} dimension(s), got shape {arr.shape}")
    return arr


def _checked_warp(warp, times) -> tuple[np.ndarray, ...]:
    warp = tuple(warp)
    if len(warp) != len(times):
        raise DataError(f"{len(warp)} aligned phase arrays for {len(times)} demonstrations")
    out = []
    for i, (z, t) in enumerate(zip(warp, times)):
        z = _as_float(f"aligned phases of demonstration {i}", z, 1)
        if z.shape != t.shape:
            raise DataError(f"demonstration {i} has {t.shape[0]} times but {z.shape[0]} aligned phases")
        if not np.all(np.isfinite(z)) or np.any(np.diff(z) < 0) or z[0] != 0.0 or z[-1] != 1.0:
            raise DataError(f"aligned phases of demonstration {i} must be finite and non-decreasing from 0 to 1")
        z.setflags(write=False)
        out.append(z)
    return tuple(out)


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
    warp : tuple of (T_i,) phases in [0, 1], non-decreasing from 0 to 1, or None:
        each sample's phase after aligning the demonstrations
        (:func:`lmpromp_ppl.data.align.align_phases`); None maps time linearly
    """

    times: tuple[np.ndarray, ...]
    positions: tuple[np.ndarray, ...]
    labels: np.ndarray | None = None
    dof_names: tuple[str, ...] = ()
    name: str = ""
    metadata: dict = field(default_factory=dict)
    warp: tuple[np.ndarray, ...] | None = None

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
        if self.warp is not None:
            object.__setattr__(self, "warp", _checked_warp(self.warp, t_out))

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
        """Each demonstration's phases: its aligned ``warp`` when set, else its time mapped
        to [0, 1] by its own start and duration."""
        if self.warp is not None:
            return self.warp
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
            warp=None if self.warp is None else tuple(self.warp[i] for i in idx),
        )

    def with_positions(self, positions: Sequence[np.ndarray]) -> "Demonstrations":
        """The same demonstrations with new positions (same shapes)."""
        return Demonstrations(
            self.times, tuple(positions), self.labels, self.dof_names, self.name, dict(self.metadata), self.warp
        )

    def with_warp(self, warp: Sequence[np.ndarray] | None) -> "Demonstrations":
        """The same demonstrations with aligned phases ``warp`` (None: linear in time)."""
        return Demonstrations(
            self.times, self.positions, self.labels, self.dof_names, self.name, dict(self.metadata),
            None if warp is None else tuple(warp),
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
    """Dense model inputs: one design matrix per demonstration.

    The general form, for any design (tests, simulation, via-points); the one
    data path (:func:`model_data`) gives the compact :class:`PhaseData`
    instead, which every engine also accepts.

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

    def dense(self) -> "ModelData":
        return self


class PhaseData(NamedTuple):
    r"""Compact model inputs: each demonstration's basis at its phases, in O(L T (J + D)) memory.

    The design matrix of demonstration i is block-diagonal over the DoF,
    :math:`\Psi_i = \mathbf I_D \otimes \Phi_i` in the layout of
    :mod:`lmpromp_ppl.basis` (row ``t * D + k``, columns ``k * J : (k + 1) * J``),
    so storing :math:`\Phi_i` (T, J) instead of :math:`\Psi_i` (T D, D J) saves a
    factor of :math:`D^2`; when every demonstration has the same phases one
    :math:`\Phi` is stored for all (``phi`` with a leading 1).  For L = 1000,
    T = 120, D = 7, J = 60 that is 13 MB instead of the dense 2.8 GB.  The
    engines compute their statistics from it (:func:`lmpromp_ppl.inference.cavi.sufficient_statistics`);
    :attr:`psi`, :attr:`y` and :attr:`mask` give the dense view of :class:`ModelData`
    (built on demand) for the code that needs single design matrices.

    Attributes
    ----------
    phi : (L, T, J) or (1, T, J) the single-DoF basis at each demonstration's phases; 0 where padded
    values : (L, T, D) observations; 0 where not observed
    observed : (L, T, D) 1.0 for an observed entry, 0.0 for padding or a missing value
    """

    phi: Array
    values: Array
    observed: Array

    @property
    def num_demos(self) -> int:
        return self.values.shape[0]

    @property
    def num_dofs(self) -> int:
        return self.values.shape[2]

    @property
    def num_basis(self) -> int:
        return self.phi.shape[2]

    @property
    def num_weights(self) -> int:
        return self.num_dofs * self.num_basis

    @property
    def psi(self) -> Array:
        """The dense design matrices (L, T D, D J) of :class:`ModelData`."""
        L, T, D = self.values.shape
        J = self.num_basis
        eye = jnp.eye(D, dtype=jnp.result_type(self.phi))
        # psi[l, t, k, m, j] = eye[k, m] * phi[l, t, j]
        dense = eye[None, None, :, :, None] * jnp.asarray(self.phi)[:, :, None, None, :]
        return jnp.broadcast_to(dense, (L, T, D, D, J)).reshape(L, T * D, D * J)

    @property
    def y(self) -> Array:
        """(L, T D) the observations flattened time-major, as :attr:`ModelData.y`."""
        return jnp.reshape(self.values, (self.num_demos, -1))

    @property
    def mask(self) -> Array:
        """(L, T D) the mask flattened time-major, as :attr:`ModelData.mask`."""
        return jnp.reshape(self.observed, (self.num_demos, -1))

    def shares_psi(self) -> bool:
        """True when every demonstration has the same design matrix and no padding."""
        phi = np.asarray(self.phi)
        return bool(np.all(np.asarray(self.observed) == 1.0) and (phi.shape[0] == 1 or np.all(phi == phi[:1])))

    def dense(self) -> ModelData:
        """The same inputs as :class:`ModelData` (O(L T D^2 J) memory)."""
        return ModelData(self.psi, self.y, self.mask)


def as_float64(data: ModelData | PhaseData) -> ModelData | PhaseData:
    """The same model inputs (of the same type) as float64 JAX arrays."""
    return type(data)._make(jnp.asarray(a, dtype=jnp.float64) for a in data)


def _statistics_num_demos(stats) -> int:
    """L, from the (L, d) cross products of :class:`SharedDesign` and :class:`DemoStatistics`."""
    return stats.cross.shape[0]


def _statistics_num_weights(stats) -> int:
    """d, from the (L, d) cross products of :class:`SharedDesign` and :class:`DemoStatistics`."""
    return stats.cross.shape[1]


class SharedDesign(NamedTuple):
    r"""Sufficient statistics of demonstrations that share one fully observed design, in its eigenbasis.

    When every demonstration has the same design :math:`\Psi` (the same phases,
    nothing padded or missing), the Gaussian likelihood of the weights depends
    on the data only through :math:`\Psi^T\Psi`, :math:`\Psi^T\mathbf y_i`,
    :math:`\mathbf y_i^T\mathbf y_i` and the number of samples.  In the
    eigenbasis :math:`\Psi^T\Psi = \mathbf U\,\mathrm{diag}(\mathbf g)\,\mathbf U^T`
    the collapsed densities of :mod:`lmpromp_ppl.models.collapsed` take
    O(L d V) per evaluation instead of O(L S (d + V)^2), with no d x d
    factorisation (the priors on ``w`` are isotropic plus rank V).  Built once,
    outside any compiled program, by :func:`shared_design`.

    Attributes
    ----------
    rotation : (d, d) the orthogonal :math:`\mathbf U` (block-diagonal over the DoF for :class:`PhaseData`)
    eig : (d,) the eigenvalues :math:`\mathbf g \ge 0` of :math:`\Psi^T\Psi`
    cross : (L, d) :math:`\mathbf U^T\Psi^T\mathbf y_i`
    sq : (L,) :math:`\mathbf y_i^T\mathbf y_i`
    count : (L,) the number of samples of each demonstration (all equal)
    """

    rotation: Array
    eig: Array
    cross: Array
    sq: Array
    count: Array

    num_demos = property(_statistics_num_demos)
    num_weights = property(_statistics_num_weights)


def gram_eigenbasis(block: Array, num_dofs: int = 1) -> tuple[Array, Array]:
    r"""The eigenbasis of the Gram matrix :math:`\mathbf I_D \otimes \mathbf B^T\mathbf B` of a design.

    ``block`` is the single-DoF basis :math:`\Phi` (T, J) of :class:`PhaseData` with
    ``num_dofs = D``, or a whole design matrix :math:`\Psi` (S, d) with ``num_dofs = 1``.
    One eigendecomposition of :math:`\mathbf B^T\mathbf B` gives :math:`\mathbf U = \mathbf I_D
    \otimes \mathbf U_B` and the eigenvalues (clipped at 0) repeated D times.  JAX, so it can
    be traced (CAVI's statistics and :func:`shared_design` both use it).

    Returns
    -------
    rotation : (D J, D J) orthogonal; eig : (D J,)
    """
    block = jnp.asarray(block, dtype=jnp.float64)
    eig, basis = jnp.linalg.eigh(block.T @ block)
    return jnp.kron(jnp.eye(num_dofs), basis), jnp.tile(jnp.maximum(eig, 0.0), num_dofs)


def shared_design(data: "ModelData | PhaseData") -> SharedDesign | None:
    """The :class:`SharedDesign` statistics of concrete model inputs, or None when the design is not shared.

    None when the demonstrations' designs differ or any entry is padded or
    missing; the declarations then use the dense form.  Computed in float64 by
    :func:`gram_eigenbasis`, as CAVI's shared path computes its rotation (one J x J
    eigendecomposition for :class:`PhaseData`, d x d for :class:`ModelData`).
    """
    if isinstance(data, SharedDesign):
        return data
    if not data.shares_psi():
        return None
    if isinstance(data, PhaseData):
        phi = jnp.asarray(data.phi, dtype=jnp.float64)[0]
        values = jnp.asarray(data.values, dtype=jnp.float64)
        num_dofs = values.shape[2]
        rotation, eig = gram_eigenbasis(phi, num_dofs)
        # Psi^T y_i, block k = Phi^T y_i[:, k]; rotated block-wise by U_phi
        u_phi = rotation[: phi.shape[1], : phi.shape[1]]
        cross = jnp.einsum("tj,ltk->lkj", phi @ u_phi, values).reshape(values.shape[0], -1)
        sq = jnp.sum(values**2, axis=(1, 2))
        count = jnp.full(values.shape[0], values.shape[1] * num_dofs, dtype=jnp.float64)
    else:
        psi = jnp.asarray(data.psi, dtype=jnp.float64)[0]
        y = jnp.asarray(data.y, dtype=jnp.float64)
        rotation, eig = gram_eigenbasis(psi)
        cross = y @ (psi @ rotation)
        sq = jnp.sum(y**2, axis=1)
        count = jnp.full(y.shape[0], y.shape[1], dtype=jnp.float64)
    return SharedDesign(rotation, eig, cross, sq, count)


class DemoStatistics(NamedTuple):
    r"""Per-demonstration sufficient statistics of the Gaussian likelihood of the weights, for any designs.

    :math:`\log\mathcal N(\mathbf y_i | \Psi_i\mathbf w_i, \beta^{-1}\mathbf I)` over the
    observed entries depends on the data only through :math:`\mathbf G_i = \Psi_i^T\Psi_i`,
    :math:`\mathbf c_i = \Psi_i^T\mathbf y_i`, :math:`\mathbf y_i^T\mathbf y_i` and the number
    of observed entries (masked rows count as zero rows).  The form the declarations evaluate
    when the demonstrations do not share one design (different lengths or phases, missing
    values): O(L d^2) memory instead of the dense O(L S d), and each collapsed density needs
    one d x d factorisation per demonstration instead of an S-sized low-rank one.  Built once,
    outside compiled code, by :func:`demo_statistics` (from :class:`PhaseData` without the dense
    design: :math:`\mathbf G_i` is block-diagonal over the DoF).

    Attributes
    ----------
    gram : (L, d, d); cross : (L, d); sq : (L,); count : (L,)
    """

    gram: Array
    cross: Array
    sq: Array
    count: Array

    num_demos = property(_statistics_num_demos)
    num_weights = property(_statistics_num_weights)


def demo_statistics(data: "ModelData | PhaseData") -> DemoStatistics:
    r"""The :class:`DemoStatistics` of model inputs (float64).

    From :class:`PhaseData`, block k of :math:`\mathbf G_i` is :math:`\Phi_i^T\mathrm{diag}(\mathbf o_{ik})\Phi_i`
    and of :math:`\mathbf c_i` it is :math:`\Phi_i^T(\mathbf o_{ik}\odot\mathbf y_{ik})` (``o`` the
    observed flags); from :class:`ModelData`, the products of the masked design.
    """
    if isinstance(data, DemoStatistics):
        return data
    if isinstance(data, PhaseData):
        phi = jnp.asarray(data.phi, dtype=jnp.float64)
        observed = jnp.asarray(data.observed, dtype=jnp.float64)
        values = jnp.where(observed > 0, jnp.asarray(data.values, dtype=jnp.float64), 0.0)
        num_demos, _, num_dofs = values.shape
        num_basis = phi.shape[2]
        phi = jnp.broadcast_to(phi, (num_demos,) + phi.shape[1:])
        blocks = jnp.einsum("ltj,ltk,lti->lkji", phi, observed, phi)  # (L, D, J, J)
        eye = jnp.eye(num_dofs)
        gram = (eye[None, :, None, :, None] * blocks[:, :, :, None, :]).reshape(
            num_demos, num_dofs * num_basis, num_dofs * num_basis)
        cross = jnp.einsum("ltj,ltk->lkj", phi, values).reshape(num_demos, -1)
        return DemoStatistics(gram, cross, jnp.sum(values**2, axis=(1, 2)), jnp.sum(observed, axis=(1, 2)))
    psi, y, mask = (jnp.asarray(a, dtype=jnp.float64) for a in data)
    psi = jnp.where(mask[..., None] > 0, psi, 0.0)  # a masked entry may hold NaN
    y = jnp.where(mask > 0, y, 0.0)
    return DemoStatistics(jnp.einsum("lsd,lse->lde", psi, psi), jnp.einsum("lsd,ls->ld", psi, y),
                          jnp.sum(y**2, axis=-1), jnp.sum(mask, axis=-1))


def model_data(
    demos: Demonstrations, num_basis: int, width: float = DEFAULT_WIDTH, phases: Sequence[np.ndarray] | None = None
) -> PhaseData:
    """Build the compact model inputs (:class:`PhaseData`) from (standardised) demonstrations.

    Demonstrations of different lengths are padded with unobserved samples;
    demonstrations that share their phases share one basis matrix.
    """
    phases = demos.phases() if phases is None else phases
    num_steps = max(p.shape[0] for p in phases)
    first = np.asarray(phases[0])
    # phases computed from different clocks agree only up to rounding (LASA: 2e-16)
    shared = all(p.shape == first.shape and np.allclose(p, first, rtol=0.0, atol=1e-12) for p in phases)
    if shared:
        phi = np.asarray(rbf_basis(first, num_basis, width))[None]
    else:
        phi = np.zeros((demos.num_demos, num_steps, num_basis))
        for i, z in enumerate(phases):
            phi[i, : z.shape[0]] = np.asarray(rbf_basis(z, num_basis, width))
    values = np.zeros((demos.num_demos, num_steps, demos.num_dofs))
    observed = np.zeros_like(values)
    for i, pos in enumerate(demos.positions):
        values[i, : pos.shape[0]] = pos
        observed[i, : pos.shape[0]] = 1.0
    return PhaseData(jnp.asarray(phi), jnp.asarray(values), jnp.asarray(observed))

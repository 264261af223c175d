r"""Normalised Gaussian radial basis functions of ProMPs (thesis Sec. 3.1).

For one degree of freedom the basis at phase :math:`z \in [0, 1]` is

.. math::

    b_j(z) = \exp\!\left(-\frac{(z - c_j)^2}{2\sigma^2}\right), \qquad
    \psi_j(z) = \frac{b_j(z)}{\sum_k b_k(z)},

with ``J`` centres :math:`c_j` spread linearly over [0, 1].  The thesis writes
:math:`\exp(-0.5 (t - c_i)^2 / (2h))` with :math:`h = (c_{i+1} - c_i)^2`, that
is a Gaussian of variance :math:`\sigma^2 = 2h` (``width=2.0``:
:math:`\sigma^2` = ``width`` times the squared centre spacing).

Defaults (:data:`DEFAULT_NUM_BASIS`, :data:`DEFAULT_WIDTH`): the thesis's
width 2 makes neighbouring basis functions nearly collinear: with J = 10 the
Gram matrix :math:`\Psi^T\Psi` of a demonstration has condition number
2.9e6, so weights fitted to real recordings reach magnitudes of 40 to 1000 on
standardised data.  ``width = 1`` (condition number 3.3e3 at J = 10) keeps
them of order one; docs/defaults.md gives the measurements behind both
defaults.

Multi-DoF layout (used everywhere in lmpromp-ppl)
-------------------------------------------------
* Weights are DoF-major: ``w = [w_1, ..., w_D]``, weight ``j`` of DoF ``k`` is
  entry ``k * J + j`` (the thesis's concatenation).
* Observations are time-major: ``y`` of shape ``(T, D)`` flattened row-wise,
  so row ``t * D + k`` of :math:`\Psi` is DoF ``k`` at time ``t``.
* :math:`\Psi` is therefore ``(T * D, D * J)`` with row ``t * D + k`` holding
  :math:`\psi(z_t)^T` in columns ``k * J : (k + 1) * J`` and zeros elsewhere.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array
from jax.typing import ArrayLike

__all__ = [
    "DEFAULT_NUM_BASIS",
    "DEFAULT_WIDTH",
    "THESIS_WIDTH",
    "centres",
    "rbf_basis",
    "rbf_basis_derivative",
    "block_basis",
    "design_matrix",
    "velocity_design_matrix",
]


#: Basis functions per DoF (J) when none is given (docs/defaults.md).
DEFAULT_NUM_BASIS = 20
#: Basis width: the Gaussians' variance in units of the squared centre spacing (docs/defaults.md).
DEFAULT_WIDTH = 1.0
#: The thesis's basis width (with J = 10): kept by ``--preset thesis`` runs and the synthetic generators.
THESIS_WIDTH = 2.0


def centres(num_basis: int) -> Array:
    """Centres of ``num_basis`` basis functions spread linearly over [0, 1]."""
    if num_basis < 2:
        raise ValueError(f"num_basis must be at least 2, got {num_basis}")
    return jnp.linspace(0.0, 1.0, num_basis)


def _variance(num_basis: int, width: float) -> float:
    spacing = 1.0 / (num_basis - 1)
    return width * spacing**2


def _unnormalised(phase: ArrayLike, num_basis: int, width: float) -> tuple[Array, Array]:
    z = jnp.asarray(phase, dtype=jnp.float64)[..., None]
    c = centres(num_basis)
    var = _variance(num_basis, width)
    # Shift the exponent by its row maximum: the normalised basis is unchanged
    # and phases far outside [0, 1] do not underflow to 0/0.
    exponent = -0.5 * (z - c) ** 2 / var
    exponent = exponent - jnp.max(exponent, axis=-1, keepdims=True)
    return jnp.exp(exponent), (z - c) / var


def rbf_basis(phase: ArrayLike, num_basis: int, width: float = DEFAULT_WIDTH) -> Array:
    """Normalised basis :math:`\\psi(z)`, shape ``phase.shape + (num_basis,)``.

    Each row sums to one.  ``phase`` may be any array of phases (irregular,
    sparse, of any length).
    """
    b, _ = _unnormalised(phase, num_basis, width)
    return b / jnp.sum(b, axis=-1, keepdims=True)


def rbf_basis_derivative(phase: ArrayLike, num_basis: int, width: float = DEFAULT_WIDTH) -> Array:
    r"""Derivative :math:`d\psi/dz` with respect to the phase.

    With :math:`b_j' = -b_j (z - c_j)/\sigma^2` and :math:`S = \sum_k b_k`,
    :math:`\psi_j' = b_j'/S - b_j S'/S^2 = \psi_j (g_j - \sum_k \psi_k g_k)`
    where :math:`g_j = -(z - c_j)/\sigma^2`.  Divide by the movement duration
    to get a time derivative.  Rows sum to zero.
    """
    b, scaled = _unnormalised(phase, num_basis, width)
    psi = b / jnp.sum(b, axis=-1, keepdims=True)
    g = -scaled
    return psi * (g - jnp.sum(psi * g, axis=-1, keepdims=True))


def block_basis(phi: ArrayLike, num_dofs: int) -> Array:
    """Block-diagonal multi-DoF matrix from a single-DoF basis ``phi`` (T, J).

    Returns ``(T * num_dofs, num_dofs * J)`` in the layout of the module
    docstring: row ``t * D + k``, columns ``k * J : (k + 1) * J``.
    """
    phi = jnp.asarray(phi)
    num_steps, num_basis = phi.shape
    eye = jnp.eye(num_dofs, dtype=phi.dtype)
    # out[t, k, l, j] = eye[k, l] * phi[t, j]
    out = eye[None, :, :, None] * phi[:, None, None, :]
    return out.reshape(num_steps * num_dofs, num_dofs * num_basis)


def design_matrix(phase: ArrayLike, num_dofs: int, num_basis: int, width: float = DEFAULT_WIDTH) -> Array:
    """:math:`\\Psi_{1:T}` for the given phases: ``(T * D, D * J)``."""
    return block_basis(rbf_basis(phase, num_basis, width), num_dofs)


def velocity_design_matrix(
    phase: ArrayLike, num_dofs: int, num_basis: int, duration: float = 1.0, width: float = DEFAULT_WIDTH
) -> Array:
    """Velocity basis :math:`\\dot\\Psi`: the phase derivative divided by ``duration``."""
    return block_basis(rbf_basis_derivative(phase, num_basis, width) / duration, num_dofs)

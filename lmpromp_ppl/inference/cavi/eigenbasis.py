r"""The loop of sweeps in the eigenbasis of a shared Gram matrix: O(L d V) per sweep.

When every demonstration has the same design, :math:`\Psi^T\Psi = U\operatorname{diag}(s)U^T`
(:class:`~.data.SharedGram`).  Every prior on :math:`w_i`, :math:`b_k` and the rows
of :math:`M_k` is isotropic, so the orthogonal change of coordinates

.. math::

    w_i' = U^Tw_i,\quad b_k' = U^Tb_k,\quad M_k' = U^TM_k,\quad \Psi_i^Ty_i \mapsto U^T\Psi_i^Ty_i

leaves the model, the variational family and the bound unchanged (the Jacobian is
1, :math:`\|U^Tx\|=\|x\|`, a column-wise or row-wise q(M) stays one) and turns the
Gram matrix into :math:`\operatorname{diag}(s)` (:class:`~.data.DiagonalGram`).
There the weight covariances are diagonal (:class:`~.data.DiagonalCovariance`) and
no update needs a d x d product: a sweep costs :math:`O(LdKV + dV^2)` instead of
the :math:`O(Ld^2)` of rotating every weight mean into and out of the basis.
:func:`~.loop.iterate` rotates in before its first sweep and out after its last,
:math:`O(Ld^2)` once per fit; ``tests/test_cavi.py`` checks that the path gives the
general path's bound and factors.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array

from lmpromp_ppl.inference.cavi.data import (
    CaviData,
    DiagonalCovariance,
    DiagonalGram,
    EigenCovariance,
    SharedGram,
)
from lmpromp_ppl.inference.cavi.state import CaviState

__all__ = ["rotates", "to_eigenbasis", "from_eigenbasis"]


def rotates(state: CaviState, data: CaviData) -> bool:
    """Whether the loop runs in the eigenbasis: the data share one design (:class:`~.data.SharedGram`)
    and the state's weight covariances are stored in its basis (:class:`~.data.EigenCovariance`)."""
    return isinstance(data.gram, SharedGram) and isinstance(state.w_cov, EigenCovariance)


def to_eigenbasis(state: CaviState, data: CaviData) -> tuple[CaviState, CaviData]:
    """The state and data in the coordinates :math:`U^T\\cdot` of the shared eigenbasis (module docstring).

    The state's weight covariances must be stored in that basis (:class:`~.data.EigenCovariance`
    with the data's U, as every start on this path has them).
    """
    if not rotates(state, data):
        raise TypeError("the eigenbasis loop needs shared-design data and weight covariances in its basis")
    basis = data.gram.basis
    rotated = state._replace(
        w_mean=state.w_mean @ basis,
        w_cov=DiagonalCovariance(state.w_cov.variances),
        b_mean=state.b_mean @ basis,
        M_mean=jnp.einsum("dj,kdv->kjv", basis, state.M_mean),
        wh_cov=None if state.wh_cov is None else jnp.einsum("dj,ikdv->ikjv", basis, state.wh_cov),
    )
    return rotated, data._replace(psi_t_y=data.psi_t_y @ basis, gram=DiagonalGram(data.gram.eigvals))


def from_eigenbasis(state: CaviState, basis: Array) -> CaviState:
    """Undo :func:`to_eigenbasis`: the state in the original weight coordinates, covariances in the basis U."""
    return state._replace(
        w_mean=state.w_mean @ basis.T,
        w_cov=EigenCovariance(basis, state.w_cov.variances),
        b_mean=state.b_mean @ basis.T,
        M_mean=jnp.einsum("dj,kjv->kdv", basis, state.M_mean),
        wh_cov=None if state.wh_cov is None else jnp.einsum("dj,ikjv->ikdv", basis, state.wh_cov),
    )

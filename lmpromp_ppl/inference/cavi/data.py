r"""Data statistics of the CAVI engine and the storage of the weight covariances.

Every update reads the data only through :class:`CaviData`: :math:`\Psi_i^Ty_i`,
:math:`y_i^Ty_i`, the number of observed entries and the Gram matrices
:math:`\Psi_i^T\Psi_i` over the observed entries (thesis Sec. 4.1.1).

Shared design matrix
--------------------
When every demonstration has the same :math:`\Psi` (``shares_psi()`` of :class:`~lmpromp_ppl.data.core.PhaseData` or :class:`~lmpromp_ppl.data.core.ModelData`),
:func:`sufficient_statistics` computes one eigendecomposition
:math:`\Psi^T\Psi = U \operatorname{diag}(s) U^T` per fit and the weight
covariances are kept in that basis (:class:`EigenCovariance`):
:math:`\Sigma_{w_i} = U \operatorname{diag}(1/(\beta s + \bar\alpha_i)) U^T`,
so that a sweep costs :math:`O(L d^2)` instead of :math:`O(L d^3)`.

Every prior on w, b and the rows of M is isotropic, so the model keeps its form
in the rotated coordinates :math:`U^Tw_i, U^Tb, U^TM`, where the Gram matrix is
:math:`\operatorname{diag}(s)`.  The loop of sweeps runs there
(:mod:`.eigenbasis`, with :class:`DiagonalGram` and :class:`DiagonalCovariance`),
which makes a sweep :math:`O(L d V)` (:math:`O(L d K V)` for the mixture); the
state is rotated back after the loop, so no rotated quantity leaves it.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array

from lmpromp_ppl.data.core import ModelData, PhaseData, gram_eigenbasis
from lmpromp_ppl.errors import DataError

__all__ = [
    "DemoGrams",
    "SharedGram",
    "DiagonalGram",
    "CaviData",
    "sufficient_statistics",
    "check_model_data",
    "FullCovariance",
    "EigenCovariance",
    "DiagonalCovariance",
    "Covariance",
    "cov_trace",
    "cov_logdet",
    "cov_matrices",
    "logdet_psd",
    "gram_quadratic",
    "gram_trace",
    "gram_sandwich",
    "cov_apply",
]


class DemoGrams(NamedTuple):
    """Per-demonstration masked Gram matrices :math:`\\Psi_i^T \\Psi_i`, (L, d, d)."""

    matrices: Array


class SharedGram(NamedTuple):
    """One Gram matrix :math:`\\Psi^T\\Psi = U \\operatorname{diag}(s) U^T` shared by all demonstrations.

    Attributes
    ----------
    basis : (d, d) orthogonal eigenvectors U (columns)
    eigvals : (d,) eigenvalues s (clipped at 0)
    """

    basis: Array
    eigvals: Array


class DiagonalGram(NamedTuple):
    """The shared Gram matrix in its own eigenbasis, :math:`\\operatorname{diag}(s)`: the data of the rotated loop.

    Attributes
    ----------
    eigvals : (d,) eigenvalues s (clipped at 0)
    """

    eigvals: Array


class CaviData(NamedTuple):
    """Sufficient statistics of the data used by every update.

    Attributes
    ----------
    psi_t_y : (L, d) :math:`\\Psi_i^T y_i` over observed entries
    y_sq : (L,) :math:`y_i^T y_i` over observed entries
    num_obs : (L,) number of observed entries :math:`n_i`
    gram : :class:`DemoGrams` (general path), :class:`SharedGram` (fast path) or
        :class:`DiagonalGram` (the fast path's data rotated into the eigenbasis, inside the loop)
    """

    psi_t_y: Array
    y_sq: Array
    num_obs: Array
    gram: DemoGrams | SharedGram | DiagonalGram


def sufficient_statistics(data: ModelData | PhaseData, shared_psi: bool | None = None) -> CaviData:
    """Precompute the data statistics for CAVI.

    Parameters
    ----------
    data : compact model inputs (:class:`PhaseData`, from the one data path) or dense
        ones (:class:`ModelData`: psi (L, S, d), y (L, S), mask (L, S))
    shared_psi : use the fast path with one eigendecomposition of :math:`\\Psi^T\\Psi`.
        ``None`` chooses it when the demonstrations share one design matrix
        (``data.shares_psi()``); ``True`` demands it (error when they do not).

    Returns
    -------
    CaviData
    """
    check_model_data(data)
    shares = data.shares_psi()
    if shared_psi is None:
        shared_psi = shares
    elif shared_psi and not shares:
        raise DataError("shared_psi=True but the demonstrations do not share one design matrix")
    if isinstance(data, PhaseData):
        return _phase_statistics(data, shared_psi)
    mask = jnp.asarray(data.mask, jnp.float64)
    # masked entries (padding, or NaN for a missing value) are neutralised
    psi = jnp.where(mask[..., None] > 0, jnp.asarray(data.psi, jnp.float64), 0.0)
    y = jnp.where(mask > 0, jnp.asarray(data.y, jnp.float64), 0.0)
    psi_t_y = jnp.einsum("isd,is->id", psi, y)
    y_sq = jnp.sum(y**2, axis=1)
    num_obs = jnp.sum(mask, axis=1)
    if shared_psi:
        gram: DemoGrams | SharedGram = SharedGram(*gram_eigenbasis(psi[0]))
    else:
        gram = DemoGrams(jnp.einsum("isd,is,ise->ide", psi, mask, psi))
    return CaviData(psi_t_y, y_sq, num_obs, gram)


def _phase_statistics(data: PhaseData, shared_psi: bool) -> CaviData:
    r"""The statistics of :func:`sufficient_statistics` from compact inputs, never forming :math:`\Psi_i`.

    With :math:`\Psi_i = \mathbf I_D \otimes \Phi_i` (:class:`PhaseData`), block k of
    :math:`\Psi_i^T y_i` is :math:`\Phi_i^T y_{i,k}` and block (k, k) of the masked Gram
    matrix is :math:`\Phi_i^T \operatorname{diag}(o_{i,k}) \Phi_i` (the off-diagonal blocks
    are 0): O(L T D J) for the first, O(L T D J^2) for the second.  On the shared path
    the one Gram matrix is :math:`\mathbf I_D \otimes \Phi^T\Phi`, so one J x J
    eigendecomposition :math:`\Phi^T\Phi = U_\phi \operatorname{diag}(s_\phi) U_\phi^T`
    gives :math:`U = \mathbf I_D \otimes U_\phi` and :math:`s` = ``s_phi`` repeated D times.
    """
    observed = jnp.asarray(data.observed, jnp.float64)
    values = jnp.where(observed > 0, jnp.asarray(data.values, jnp.float64), 0.0)
    phi = jnp.asarray(data.phi, jnp.float64)
    L, _, D = values.shape
    J = phi.shape[-1]
    psi_t_y = jnp.einsum("itj,itk->ikj", jnp.broadcast_to(phi, (L,) + phi.shape[1:]), values).reshape(L, D * J)
    y_sq = jnp.sum(values**2, axis=(1, 2))
    num_obs = jnp.sum(observed, axis=(1, 2))
    if shared_psi:
        return CaviData(psi_t_y, y_sq, num_obs, SharedGram(*gram_eigenbasis(phi[0], D)))
    blocks = jnp.einsum("itj,itk,itl->ikjl", jnp.broadcast_to(phi, (L,) + phi.shape[1:]), observed,
                        jnp.broadcast_to(phi, (L,) + phi.shape[1:]))  # (L, D, J, J)
    eye = jnp.eye(D, dtype=blocks.dtype)
    grams = (eye[None, :, None, :, None] * blocks[:, :, :, None, :]).reshape(L, D * J, D * J)
    return CaviData(psi_t_y, y_sq, num_obs, DemoGrams(grams))


def check_model_data(data: ModelData | PhaseData) -> None:
    """Refuse model inputs the engine cannot use, with a :class:`~lmpromp_ppl.errors.DataError`."""
    if isinstance(data, PhaseData):
        phi, values, observed = (np.asarray(a) for a in data)
        if (phi.ndim != 3 or values.ndim != 3 or observed.shape != values.shape
                or phi.shape[0] not in (1, values.shape[0]) or phi.shape[1] != values.shape[1]):
            raise DataError(
                f"inconsistent PhaseData shapes: phi {phi.shape}, values {values.shape}, observed {observed.shape}"
            )
        if not np.all((observed == 0.0) | (observed == 1.0)):
            raise DataError("PhaseData.observed must contain only 0 and 1")
        if not np.all(np.isfinite(values[observed == 1.0])):
            raise DataError("observed entries of PhaseData.values contain NaN or inf")
        if not np.all(np.isfinite(np.broadcast_to(phi, values.shape[:2] + phi.shape[2:])[np.any(observed == 1.0, axis=-1)])):
            raise DataError("basis rows of observed samples contain NaN or inf")
        return
    if not isinstance(data, ModelData):
        raise DataError(f"expected ModelData or PhaseData, got {type(data).__name__}")
    psi, y, mask = (np.asarray(a) for a in data)
    if psi.ndim != 3 or y.shape != psi.shape[:2] or mask.shape != psi.shape[:2]:
        raise DataError(
            f"inconsistent ModelData shapes: psi {psi.shape}, y {y.shape}, mask {mask.shape}"
        )
    if not np.all((mask == 0.0) | (mask == 1.0)):
        raise DataError("ModelData.mask must contain only 0 and 1")
    observed = mask == 1.0
    if not np.all(np.isfinite(y[observed])):
        raise DataError("observed entries of ModelData.y contain NaN or inf")
    if not np.all(np.isfinite(psi[observed])):
        raise DataError("design-matrix rows of observed entries contain NaN or inf")


# --------------------------------------------------------------------------- weight covariances
class FullCovariance(NamedTuple):
    """Weight covariances stored as (L, d, d) matrices (general path)."""

    matrices: Array


class EigenCovariance(NamedTuple):
    """Weight covariances :math:`\\Sigma_{w_i} = U \\operatorname{diag}(v_i) U^T` with a shared U.

    Attributes
    ----------
    basis : (d, d) the eigenvectors U of the shared Gram matrix
    variances : (L, d) the variances :math:`v_i` in that basis
    """

    basis: Array
    variances: Array


class DiagonalCovariance(NamedTuple):
    """Weight covariances :math:`\\operatorname{diag}(v_i)` in the rotated coordinates of :class:`DiagonalGram`.

    Attributes
    ----------
    variances : (L, d) the variances :math:`v_i`
    """

    variances: Array


Covariance = FullCovariance | EigenCovariance | DiagonalCovariance


def cov_trace(cov: Covariance) -> Array:
    """(L,) :math:`\\operatorname{tr}\\Sigma_{w_i}`."""
    if isinstance(cov, (EigenCovariance, DiagonalCovariance)):
        return jnp.sum(cov.variances, axis=-1)
    return jnp.trace(cov.matrices, axis1=-2, axis2=-1)


def logdet_psd(matrices: Array) -> Array:
    """log-determinants of positive definite matrices (Cholesky)."""
    chol = jnp.linalg.cholesky(matrices)
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)


def cov_logdet(cov: Covariance) -> Array:
    """(L,) :math:`\\log|\\Sigma_{w_i}|`."""
    if isinstance(cov, (EigenCovariance, DiagonalCovariance)):
        return jnp.sum(jnp.log(cov.variances), axis=-1)
    return logdet_psd(cov.matrices)


def cov_matrices(cov: Covariance) -> Array:
    """The weight covariances as (..., L, d, d) matrices, whatever the storage."""
    if isinstance(cov, DiagonalCovariance):
        return cov.variances[..., :, None] * jnp.eye(cov.variances.shape[-1])
    if isinstance(cov, EigenCovariance):
        return jnp.einsum("...dj,...ij,...ej->...ide", cov.basis, cov.variances, cov.basis)
    return cov.matrices


def gram_quadratic(gram: DemoGrams | SharedGram | DiagonalGram, x: Array) -> Array:
    """:math:`x_i^T \\Psi_i^T\\Psi_i x_i` for (L, d) x."""
    if isinstance(gram, DiagonalGram):
        return x**2 @ gram.eigvals
    if isinstance(gram, SharedGram):
        return jnp.sum(gram.eigvals * (x @ gram.basis) ** 2, axis=-1)
    return jnp.einsum("id,ide,ie->i", x, gram.matrices, x)


def gram_trace(gram: DemoGrams | SharedGram | DiagonalGram, cov: Covariance) -> Array:
    """:math:`\\operatorname{tr}(\\Psi_i^T\\Psi_i \\Sigma_{w_i})` (same basis on the fast path)."""
    if (isinstance(gram, SharedGram) and isinstance(cov, EigenCovariance)) or (
        isinstance(gram, DiagonalGram) and isinstance(cov, DiagonalCovariance)
    ):
        return cov.variances @ gram.eigvals
    if isinstance(gram, DemoGrams) and isinstance(cov, FullCovariance):
        return jnp.einsum("ide,ied->i", gram.matrices, cov.matrices)
    raise TypeError(
        f"weight covariance {type(cov).__name__} does not match the data path {type(gram).__name__}"
    )


def gram_sandwich(gram: DemoGrams | SharedGram | DiagonalGram, x: Array, y: Array) -> Array:
    """(L, V, V) :math:`X_i^T \\Psi_i^T\\Psi_i Y_i` for (L, d, V) x and y."""
    if isinstance(gram, DiagonalGram):
        return jnp.einsum("idu,d,idv->iuv", x, gram.eigvals, y)
    if isinstance(gram, SharedGram):
        rx = jnp.einsum("dj,idv->ijv", gram.basis, x)
        ry = jnp.einsum("dj,idv->ijv", gram.basis, y)
        return jnp.einsum("iju,j,ijv->iuv", rx, gram.eigvals, ry)
    return jnp.einsum("idu,ide,iev->iuv", x, gram.matrices, y)


def cov_apply(cov: Covariance, x: Array) -> Array:
    """(L, d, V) :math:`\\Sigma_{w_i} X` for one (d, V) x, whatever the storage."""
    if isinstance(cov, DiagonalCovariance):
        return cov.variances[:, :, None] * x[None]
    if isinstance(cov, EigenCovariance):
        rotated = cov.basis.T @ x  # (d, V)
        return jnp.einsum("dj,ij,jv->idv", cov.basis, cov.variances, rotated)
    return jnp.einsum("ide,ev->idv", cov.matrices, x)

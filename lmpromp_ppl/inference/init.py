r"""Initialisation of CAVI for the single-type LMProMP (thesis Sec. 4.1.1, last paragraph).

As in the thesis: the weights of each demonstration are fitted by (ridge)
regression on its observed entries, and PCA of these weights gives the offset
``b`` (the mean), the projection ``M`` (the first V principal directions scaled
by the square roots of their explained variances) and the control variables
``h`` (the scores divided by the same scales, so that they have unit variance as
under the prior with :math:`\gamma = 1`).  The precisions start at their
maximum-likelihood values given these means; the covariances of q start at the
closed-form updates of :mod:`lmpromp_ppl.inference.cavi` given the other factors.
A PRNG key perturbs ``M`` and ``h`` for restarts.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from sklearn.decomposition import PCA

from lmpromp_ppl.inference.cavi import (
    CaviData,
    CaviState,
    EigenCovariance,
    FullCovariance,
    SharedGram,
    _h_posterior,
    _w_posterior,
)
from lmpromp_ppl.models.hyper import Hyperparameters

__all__ = ["ridge_weights", "init_state"]


def ridge_weights(data: CaviData, ridge: float = 1e-4) -> np.ndarray:
    """Per-demonstration ridge regression of the weights on the observed entries.

    :math:`w_i = (\\Psi_i^T\\Psi_i + \\rho_i I)^{-1}\\Psi_i^T y_i` with
    :math:`\\rho_i` = ``ridge`` times the mean diagonal of :math:`\\Psi_i^T\\Psi_i`
    (relative, so it does not depend on the number of samples); the ridge keeps
    the weights of basis functions without observations (missing segments) at 0.

    Returns
    -------
    (L, d) numpy array
    """
    gram = data.gram
    if isinstance(gram, SharedGram):
        rho = ridge * jnp.mean(gram.eigvals)
        w = ((data.psi_t_y @ gram.basis) / (gram.eigvals + rho)) @ gram.basis.T
    else:
        d = data.psi_t_y.shape[1]
        rho = ridge * jnp.trace(gram.matrices, axis1=-2, axis2=-1) / d
        w = jnp.linalg.solve(
            gram.matrices + rho[:, None, None] * jnp.eye(d), data.psi_t_y[..., None]
        )[..., 0]
    return np.asarray(w)


def init_state(
    data: CaviData,
    hyper: Hyperparameters,
    key: Array | None = None,
    *,
    ridge: float = 1e-4,
    jitter: float = 0.5,
) -> CaviState:
    """Thesis initialisation: ridge weights, PCA for b, M and h, matching precisions.

    Parameters
    ----------
    data : prepared data (:func:`lmpromp_ppl.inference.cavi.prepare_cavi_data`)
    hyper : hyperparameters; ``latent_dim`` is V
    key : when given, perturb ``M`` (by ``jitter`` times its typical entry) and
        ``h`` (by ``jitter`` standard normal draws) for a restart
    ridge : relative ridge of :func:`ridge_weights`
    jitter : size of the perturbation

    Returns
    -------
    CaviState
        Uses :class:`~lmpromp_ppl.inference.cavi.EigenCovariance` for the
        weights when ``data`` is on the shared-design fast path.
    """
    W = ridge_weights(data, ridge)
    L, d = W.shape
    hyper.validate_for(d, L)
    V = hyper.latent_dim
    pca = PCA(n_components=V, svd_solver="full").fit(W)
    variance = np.maximum(pca.explained_variance_, 1e-10 * max(pca.explained_variance_.max(), 1e-300))
    scale = np.sqrt(variance)
    b = pca.mean_
    M = pca.components_.T * scale
    h = pca.transform(W) / scale
    if key is not None:
        k_M, k_h = jax.random.split(key)
        typical = np.sqrt(np.mean(M**2))
        M = M + jitter * typical * np.asarray(jax.random.normal(k_M, (d, V)))
        h = h + jitter * np.asarray(jax.random.normal(k_h, (L, V)))
    # precisions at their maximum-likelihood values given the means (clipped)
    centred = W - b
    residual = centred - h @ M.T
    floor = 1e-3 * np.mean(centred**2) + 1e-12
    alpha = 1.0 / max(np.mean(residual**2), floor)
    col_sq = np.sum(M**2, axis=0)
    lam = d / np.maximum(col_sq, 1e-8 * col_sq.max() + 1e-300)
    alpha_shape = hyper.a0 + 0.5 * d * L
    lam_shape = np.full(V, hyper.c0 + 0.5 * d)
    f64 = lambda x: jnp.asarray(x, jnp.float64)  # noqa: E731
    h_cov, M_var, w_cov = _covariances(
        data, f64(hyper.beta), f64(hyper.gamma), f64(alpha), f64(lam), f64(b), f64(M), f64(h)
    )
    return CaviState(
        w_mean=f64(W),
        w_cov=w_cov,
        h_mean=f64(h),
        h_cov=h_cov,
        b_mean=f64(b),
        b_var=f64(1.0 / (L * alpha + hyper.lambda0)),
        M_mean=f64(M),
        M_var=M_var,
        alpha_shape=f64(alpha_shape),
        alpha_rate=f64(alpha_shape / alpha),
        lam_shape=f64(lam_shape),
        lam_rate=f64(lam_shape / lam),
    )


@jax.jit
def _covariances(
    data: CaviData, beta: Array, gamma: Array, alpha: Array, lam: Array, b: Array, M: Array, h: Array
) -> tuple[Array, Array, FullCovariance | EigenCovariance]:
    """Covariances of q(h_i), q(m_v), q(w_i) by their updates given the means (E[M^T M] ~ M^T M)."""
    L = h.shape[0]
    weights = jnp.ones(L)
    _, h_cov = _h_posterior(weights, alpha, M.T @ M, M, jnp.zeros((L, M.shape[0])), gamma)
    S = jnp.sum(h_cov, axis=0) + h.T @ h
    M_var = 1.0 / (alpha * jnp.diagonal(S) + lam)
    _, w_cov = _w_posterior(data, beta, jnp.full((L,), alpha), alpha * (b + h @ M.T))
    return h_cov, M_var, w_cov

r"""Initialisation of CAVI (thesis Sec. 4.1.1, last paragraph; Sec. 4.2.1 for the mixture).

As in the thesis: the weights of each demonstration are fitted by (ridge)
regression on its observed entries, and PCA of these weights gives the offset
``b`` (the mean), the projection ``M`` (the first V principal directions scaled
by the square roots of their explained variances) and the control variables
``h`` (the scores divided by the same scales, so that they have unit variance as
under the prior with :math:`\gamma = 1`).  The precisions start at their
maximum-likelihood values given these means; the covariances of q start at the
closed-form updates (:mod:`.kernels`) given the other factors.  A PRNG key
perturbs ``M`` and ``h`` for restarts of the single type.

For the mixture :func:`init_mixture_state` clusters the ridge weights by
k-means (scikit-learn, seeded from the key) and runs the same PCA
initialisation within each cluster; the responsibilities start one-hot at the
k-means labels.  Every start is a :class:`~.state.CaviState` with the component axis.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from sklearn.cluster import KMeans
from sklearn.decomposition import PCA

from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference.cavi.data import CaviData, EigenCovariance, FullCovariance, SharedGram
from lmpromp_ppl.inference.cavi.kernels import h_posterior, w_posterior
from lmpromp_ppl.inference.cavi.state import CaviHyper, CaviState, check_family, lift_single_type
from lmpromp_ppl.models.hyper import Hyperparameters

__all__ = ["ridge_weights", "function_space", "init_state", "init_state_jax", "init_mixture_state", "beta_start"]


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


def function_space(data: CaviData, W: np.ndarray) -> np.ndarray:
    """Coordinates of the weights in which Euclidean distance is the distance of the fitted trajectories.

    :math:`f_i = \\operatorname{diag}(\\sqrt s)U^Tw_i` with :math:`\\bar G = U\\operatorname{diag}(s)U^T`
    the (mean) Gram matrix, so :math:`\\|f_i - f_j\\|^2 = (w_i - w_j)^T\\bar G(w_i - w_j)`.
    """
    gram = data.gram
    if isinstance(gram, SharedGram):
        s, U = np.asarray(gram.eigvals), np.asarray(gram.basis)
    else:
        s, U = np.linalg.eigh(np.mean(np.asarray(gram.matrices), axis=0))
    return (W @ U) * np.sqrt(np.maximum(s, 0.0))


def beta_start(data: CaviData, hyper: Hyperparameters) -> tuple[float, float] | None:
    """q(beta)'s start when beta is learned: shape :math:`\\beta_{a0} + n/2`, mean ``hyper.beta``; else None."""
    if not hyper.learn_beta:
        return None
    shape = hyper.beta_a0 + 0.5 * float(jnp.sum(data.num_obs))
    return shape, shape / hyper.beta


def init_state(
    data: CaviData,
    hyper: Hyperparameters,
    key: Array | None = None,
    *,
    family: str = "columnwise",
    ridge: float = 1e-4,
    jitter: float = 0.5,
) -> CaviState:
    """Thesis initialisation of the single type (K = 1): ridge weights, PCA for b, M and h, matching precisions.

    Parameters
    ----------
    data : prepared data (:func:`~.data.sufficient_statistics`)
    hyper : hyperparameters; ``latent_dim`` is V; ``learn_beta`` adds q(beta)
        (:func:`beta_start`)
    key : when given, perturb ``M`` (by ``jitter`` times its typical entry) and
        ``h`` (by ``jitter`` standard normal draws) for a restart
    family : ``"columnwise"`` or ``"rowwise"`` q(M) (a diagonal row covariance at the start)
    ridge : relative ridge of :func:`ridge_weights`
    jitter : size of the perturbation

    Returns
    -------
    CaviState
        K = 1, ``resp`` None; :class:`~.data.EigenCovariance` weights on the
        shared-design fast path.
    """
    check_family(family)
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
    fields = dict(
        w_mean=f64(W), w_cov=w_cov, h_mean=f64(h), h_cov=h_cov, b_mean=f64(b),
        b_var=f64(1.0 / (L * alpha + hyper.lambda0)), M_mean=f64(M), M_var=M_var,
        alpha_shape=f64(alpha_shape), alpha_rate=f64(alpha_shape / alpha),
        lam_shape=f64(lam_shape), lam_rate=f64(lam_shape / lam),
    )
    return lift_single_type(fields, family, beta_start(data, hyper))


def init_state_jax(data: CaviData, hyper: CaviHyper, latent_dim: int, ridge: float = 1e-4) -> CaviState:
    r"""The thesis initialisation of :func:`init_state` in pure JAX, traceable by ``jax.vmap`` (fixed beta).

    Same steps (Sec. 4.1.1: ridge weights, PCA for b, M and h, precisions at
    their maximum-likelihood values given the means, covariances by their
    updates), with the principal directions from ``eigh`` of the sample
    covariance instead of scikit-learn.  The signs of the principal directions
    may differ from scikit-learn's, a symmetry of the model
    (:math:`m_v, h_{v} \to -m_v, -h_{v}`).  No restart jitter.

    Parameters
    ----------
    data : prepared data on the shared-design fast path (:class:`~.data.SharedGram`)
    hyper : hyperparameter arrays (:func:`~.state.hyper_arrays`)
    latent_dim : V (static under ``jit``)
    ridge : relative ridge of :func:`ridge_weights`
    """
    gram = data.gram
    if not isinstance(gram, SharedGram):
        raise LmprompError("init_state_jax needs shared-design data (SharedGram)")
    rho = ridge * jnp.mean(gram.eigvals)
    W = ((data.psi_t_y @ gram.basis) / (gram.eigvals + rho)) @ gram.basis.T
    L, d = W.shape
    b = jnp.mean(W, axis=0)
    centred = W - b
    eigvals, vectors = jnp.linalg.eigh(centred.T @ centred / (L - 1))
    variance = eigvals[::-1][:latent_dim]
    components = vectors[:, ::-1][:, :latent_dim]
    variance = jnp.maximum(variance, 1e-10 * jnp.maximum(variance.max(), 1e-300))
    scale = jnp.sqrt(variance)
    M = components * scale
    h = (centred @ components) / scale
    residual = centred - h @ M.T
    floor = 1e-3 * jnp.mean(centred**2) + 1e-12
    alpha = 1.0 / jnp.maximum(jnp.mean(residual**2), floor)
    col_sq = jnp.sum(M**2, axis=0)
    lam = d / jnp.maximum(col_sq, 1e-8 * col_sq.max() + 1e-300)
    alpha_shape = hyper.a0 + 0.5 * d * L
    lam_shape = jnp.full((latent_dim,), hyper.c0 + 0.5 * d)
    h_cov, M_var, w_cov = _covariances(data, hyper.beta, hyper.gamma, alpha, lam, b, M, h)
    return lift_single_type(dict(
        w_mean=W, w_cov=w_cov, h_mean=h, h_cov=h_cov, b_mean=b,
        b_var=1.0 / (L * alpha + hyper.lambda0), M_mean=M, M_var=M_var,
        alpha_shape=alpha_shape, alpha_rate=alpha_shape / alpha,
        lam_shape=lam_shape, lam_rate=lam_shape / lam,
    ))


@jax.jit
def _covariances(
    data: CaviData, beta: Array, gamma: Array, alpha: Array, lam: Array, b: Array, M: Array, h: Array
) -> tuple[Array, Array, FullCovariance | EigenCovariance]:
    """Covariances of q(h_i), q(m_v), q(w_i) by their updates given the means (E[M^T M] ~ M^T M)."""
    L = h.shape[0]
    weights = jnp.ones(L)
    _, h_cov = h_posterior(weights, alpha, M.T @ M, M, jnp.zeros((L, M.shape[0])), gamma)
    S = jnp.sum(h_cov, axis=0) + h.T @ h
    M_var = 1.0 / (alpha * jnp.diagonal(S) + lam)
    _, w_cov = w_posterior(data, beta, jnp.full((L,), alpha), alpha * (b + h @ M.T))
    return h_cov, M_var, w_cov


def pca_start(W: np.ndarray, V: int, fallback: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PCA of the rows of ``W``: offset, projection and unit-variance scores (as :func:`init_state`).

    With at most V rows the principal directions are not determined; then the
    projection ``fallback`` (the PCA of all weights) is used and the scores are
    its least-squares coordinates.
    """
    n = W.shape[0]
    if n <= V and fallback is not None:
        b = W.mean(axis=0)
        h = np.linalg.lstsq(fallback, (W - b).T, rcond=None)[0].T
        return b, fallback, h
    pca = PCA(n_components=V, svd_solver="full").fit(W)
    variance = np.maximum(pca.explained_variance_, 1e-10 * max(pca.explained_variance_.max(), 1e-300))
    scale = np.sqrt(variance)
    return pca.mean_, pca.components_.T * scale, pca.transform(W) / scale


def init_mixture_state(
    data: CaviData,
    hyper: Hyperparameters,
    key: Array,
    *,
    family: str = "columnwise",
    ridge: float = 1e-4,
) -> CaviState:
    """k-means on the ridge weights, then PCA per cluster (Sec. 4.2.1).

    k-means measures distances between the fitted trajectories
    (:math:`\\|\\Psi(w_i - w_j)\\|`, :func:`function_space`) rather than between raw
    weights as the thesis does: with overlapping basis functions the ridge
    weights are dominated by noise in the directions the data barely determine,
    which hides the clusters from raw-weight k-means.

    Parameters
    ----------
    data : prepared data
    hyper : hyperparameters; K = ``num_components``, V = ``latent_dim``;
        ``learn_beta`` adds q(beta) (:func:`beta_start`)
    key : jax PRNG key; the k-means seed is drawn from it
    family : ``"columnwise"`` or ``"rowwise"`` q(M)
    ridge : relative ridge of :func:`ridge_weights`

    Returns
    -------
    CaviState
        A mixture state: every component active; ``resp`` one-hot at the k-means
        labels; the precisions at their maximum-likelihood values within each
        cluster and the covariances at their updates given the means.
    """
    check_family(family)
    W = ridge_weights(data, ridge)
    L, d = W.shape
    K, V = hyper.num_components, hyper.latent_dim
    hyper.validate_for(d, L)
    seed = int(jax.random.randint(key, (), 0, np.iinfo(np.int32).max))
    labels = KMeans(n_clusters=K, n_init=10, random_state=seed).fit_predict(function_space(data, W))
    _, global_M, _ = pca_start(W, V)
    b = np.zeros((K, d))
    M = np.zeros((K, d, V))
    h = np.zeros((L, K, V))
    alpha = np.zeros(K)
    lam = np.zeros((K, V))
    counts = np.zeros(K)
    floor = 1e-3 * np.mean((W - W.mean(axis=0)) ** 2) + 1e-12
    for k in range(K):
        members = np.flatnonzero(labels == k)
        counts[k] = members.size
        b[k], M[k], h[members, k] = pca_start(W[members], V, fallback=global_M)
        residual = W[members] - b[k] - h[members, k] @ M[k].T
        alpha[k] = 1.0 / max(np.mean(residual**2), floor)
        col_sq = np.sum(M[k] ** 2, axis=0)
        lam[k] = d / np.maximum(col_sq, 1e-8 * col_sq.max() + 1e-300)
    resp = np.eye(K)[labels]
    alpha_shape = hyper.a0 + 0.5 * d * counts
    lam_shape = np.full((K, V), hyper.c0 + 0.5 * d)
    f64 = lambda x: jnp.asarray(x, jnp.float64)  # noqa: E731
    h_cov, M_var, w_cov = _mixture_covariances(
        data, f64(hyper.beta), f64(hyper.gamma), f64(alpha), f64(lam), f64(M), f64(h), f64(resp),
        rowwise=family == "rowwise",
    )
    beta = beta_start(data, hyper)
    return CaviState(
        w_mean=f64(W),
        w_cov=w_cov,
        h_mean=f64(h),
        h_cov=h_cov,
        b_mean=f64(b),
        b_var=f64(1.0 / (counts * alpha + hyper.lambda0)),
        M_mean=f64(M),
        M_var=M_var,
        alpha_shape=f64(alpha_shape),
        alpha_rate=f64(alpha_shape / alpha),
        lam_shape=f64(lam_shape),
        lam_rate=f64(lam_shape / lam),
        resp=f64(resp),
        pi_conc=f64(hyper.kappa0 + counts),
        beta_shape=f64(1.0 if beta is None else beta[0]),
        beta_rate=f64(1.0 if beta is None else beta[1]),
        beta_learned=jnp.asarray(hyper.learn_beta),
        active=jnp.ones((K,), jnp.bool_),
    )


@partial(jax.jit, static_argnames="rowwise")
def _mixture_covariances(
    data: CaviData, beta: Array, gamma: Array, alpha: Array, lam: Array, M: Array, h: Array,
    resp: Array, rowwise: bool,
):
    """Covariances of q(h_ik), q(M_k), q(w_i) by their updates given the means (E[M^T M] ~ M^T M)."""
    L, K, _ = h.shape
    MtM = jnp.einsum("kdu,kdv->kuv", M, M)
    _, h_cov = jax.vmap(h_posterior, in_axes=(1, 0, 0, 0, None, None), out_axes=(1, 1))(
        resp, alpha, MtM, M, jnp.zeros((L, M.shape[1])), gamma
    )
    S = jnp.einsum("ik,ikuv->kuv", resp, h_cov + jnp.einsum("iku,ikv->ikuv", h, h))
    A = alpha[:, None, None] * S + jax.vmap(jnp.diag)(lam)
    if rowwise:
        M_var = jnp.linalg.inv(A)
        M_var = 0.5 * (M_var + jnp.swapaxes(M_var, -1, -2))
    else:
        M_var = 1.0 / jnp.diagonal(A, axis1=-2, axis2=-1)
    _, w_cov = w_posterior(data, beta, resp @ alpha, jnp.zeros((L, M.shape[1])))
    return h_cov, M_var, w_cov

r"""Exact Gaussian conditionals that restore the integrated-out sites after inference on a collapsed model.

:func:`sample_w_given_theta` draws ``w`` from :math:`p(\mathbf w | \theta, \mathbf y)`
for each posterior draw of the parameters (eqs. 3.2-3.3 and 4.6-4.7 in
precision form, :math:`d \times d` solves); :func:`sample_h_given_theta` does the
same for ``h`` given ``w``; :func:`draw_integrated_sites` does both for the
collapse choices of :mod:`lmpromp_ppl.models.registry`.  The collapsed models
themselves are in :mod:`lmpromp_ppl.models.collapsed`.
"""

from __future__ import annotations

import math
from typing import Mapping

import jax
import jax.numpy as jnp
from jax import Array
from jax.scipy.linalg import solve_triangular

from lmpromp_ppl.data.core import ModelData, demo_statistics
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.models.hyper import Hyperparameters
from lmpromp_ppl.models.lmpromp import MaskedObservations, masked_observations

__all__ = [
    "gaussian_conditional",
    "data_statistics",
    "offset_marginal",
    "sample_b_given_theta",
    "sample_w_given_theta",
    "sample_h_given_theta",
    "draw_integrated_sites",
    "woodbury_precision",
]

_LOG_2PI = math.log(2.0 * math.pi)


def gaussian_conditional(
    gram: Array,
    cross: Array,
    sq: Array,
    count: Array,
    noise_precision: Array,
    prior_mean: Array,
    prior_precision: Array,
    logdet_prior: Array | None = None,
) -> tuple[Array, Array, Array]:
    r"""Posterior and evidence of :math:`\mathbf x` in a linear-Gaussian model, from sufficient statistics.

    Model: :math:`\mathbf x \sim \mathcal N(\mathbf m, \mathbf P_0^{-1})`,
    :math:`\mathbf o \sim \mathcal N(\mathbf A\mathbf x, \nu^{-1}\mathbf I_n)`.
    Then :math:`\mathbf P = \mathbf P_0 + \nu\mathbf A^T\mathbf A`,
    :math:`\boldsymbol\mu = \mathbf P^{-1}(\mathbf P_0\mathbf m + \nu\mathbf A^T\mathbf o)`
    (eqs. 3.2-3.3 in precision form) and, with
    :math:`\mathbf u = \mathbf A^T(\mathbf o - \mathbf A\mathbf m)`,

    .. math::

        \log \mathcal N(\mathbf o | \mathbf A\mathbf m, \nu^{-1}\mathbf I + \mathbf A\mathbf P_0^{-1}\mathbf A^T)
        = -\tfrac n2\log 2\pi + \tfrac n2 \log\nu + \tfrac12\log|\mathbf P_0| - \tfrac12\log|\mathbf P|
        - \tfrac12\big(\nu\|\mathbf o - \mathbf A\mathbf m\|^2 - \nu^2\mathbf u^T\mathbf P^{-1}\mathbf u\big)

    (Woodbury identity and determinant lemma); only ``x``-sized solves.  All
    arguments broadcast over leading batch dimensions.

    Parameters
    ----------
    gram : (..., p, p) :math:`\mathbf A^T\mathbf A`
    cross : (..., p) :math:`\mathbf A^T\mathbf o`
    sq : (...,) :math:`\mathbf o^T\mathbf o`
    count : (...,) n, the number of observations
    noise_precision : (...,) :math:`\nu`
    prior_mean : (..., p) :math:`\mathbf m`
    prior_precision : (..., p, p) :math:`\mathbf P_0`
    logdet_prior : :math:`\log|\mathbf P_0|` when the caller has it (one prior
        shared by a batch needs one factorisation, not one per element)

    Returns
    -------
    mean : (..., p) posterior mean
    chol : (..., p, p) lower Cholesky factor of the posterior precision
    log_evidence : (...,) the log marginal density of the observations
    """
    nu = jnp.asarray(noise_precision)
    p = cross.shape[-1]
    batch = jnp.broadcast_shapes(
        gram.shape[:-2], cross.shape[:-1], jnp.shape(sq), jnp.shape(count), nu.shape,
        prior_mean.shape[:-1], prior_precision.shape[:-2],
    )
    gram = jnp.broadcast_to(gram, batch + (p, p))
    cross = jnp.broadcast_to(cross, batch + (p,))
    prior_mean = jnp.broadcast_to(prior_mean, batch + (p,))
    prior_precision = jnp.broadcast_to(prior_precision, batch + (p, p))
    nu = jnp.broadcast_to(nu, batch)
    precision = prior_precision + nu[..., None, None] * gram
    chol = jnp.linalg.cholesky(precision)
    rhs = jnp.einsum("...ij,...j->...i", prior_precision, prior_mean) + nu[..., None] * cross
    half = solve_triangular(chol, rhs[..., None], lower=True)
    mean = solve_triangular(jnp.swapaxes(chol, -1, -2), half, lower=False)[..., 0]

    u = cross - jnp.einsum("...ij,...j->...i", gram, prior_mean)
    v = solve_triangular(chol, u[..., None], lower=True)[..., 0]
    resid_sq = (
        sq
        - 2.0 * jnp.sum(prior_mean * cross, axis=-1)
        + jnp.einsum("...i,...ij,...j->...", prior_mean, gram, prior_mean)
    )
    if logdet_prior is None:
        logdet_prior = 2.0 * jnp.sum(
            jnp.log(jnp.diagonal(jnp.linalg.cholesky(prior_precision), axis1=-2, axis2=-1)), axis=-1
        )
    logdet_post = 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)
    log_evidence = (
        -0.5 * count * _LOG_2PI
        + 0.5 * count * jnp.log(nu)
        + 0.5 * (logdet_prior - logdet_post)
        - 0.5 * (nu * resid_sq - nu**2 * jnp.sum(v**2, axis=-1))
    )
    return mean, chol, log_evidence


def _draw(key: Array, mean: Array, chol: Array) -> Array:
    """A draw from N(mean, (chol chol^T)^-1)."""
    eps = jax.random.normal(key, mean.shape + (1,), dtype=mean.dtype)
    return mean + solve_triangular(jnp.swapaxes(chol, -1, -2), eps, lower=False)[..., 0]


def woodbury_precision(alpha: Array, M: Array, gamma: float) -> Array:
    r""":math:`(\alpha^{-1}\mathbf I_d + \gamma^{-1}\mathbf M\mathbf M^T)^{-1}
    = \alpha\mathbf I - \alpha^2\mathbf M(\gamma\mathbf I_V + \alpha\mathbf M^T\mathbf M)^{-1}\mathbf M^T`."""
    num_weights, num_latent = M.shape[-2:]
    a = alpha[..., None, None]
    inner = gamma * jnp.eye(num_latent) + a * jnp.swapaxes(M, -1, -2) @ M
    solved = jnp.linalg.solve(inner, jnp.swapaxes(M, -1, -2))
    return a * jnp.eye(num_weights) - a**2 * (M @ solved)


def _select(onehot: Array, x: Array, event_dims: int) -> Array:
    """Pick component ``z`` (one-hot over axis -1 of ``onehot``) of ``x`` (..., K, *event)."""
    expand = onehot.reshape(onehot.shape + (1,) * event_dims)
    return jnp.sum(expand * x, axis=-1 - event_dims)


def _infer_model(params: Mapping) -> str:
    if "mu_w" in params or "Sigma_w" in params:
        return "promp"
    if "pi" in params or "z" in params:
        return "mixture"
    return "lmpromp"


def _params_for_draws(
    params: Mapping, hyper: Hyperparameters, model: str, num_weights: int, num_demos: int
) -> tuple[tuple[int, ...], dict]:
    """Check parameter shapes; return the sample shape and flattened parameters."""
    K, V, d, L = hyper.num_components, hyper.latent_dim, num_weights, num_demos
    if model == "promp":
        event = {"mu_w": (d,)}
        if "Sigma_w" in params:
            event["Sigma_w"] = (d, d)
        else:
            event.update({"w_scale": (d,), "w_corr_chol": (d, d)})
    elif model == "lmpromp":
        event = {"b": (d,), "M": (d, V), "alpha": ()}
        if "h" in params:
            event["h"] = (L, V)
    elif model == "mixture":
        event = {"b": (K, d), "M": (K, d, V), "alpha": (K,)}
        event.update({"z": (L,)} if "z" in params else {"pi": (K,)})
        if "h" in params:
            event["h"] = (L, K, V)
    else:
        raise LmprompError(f"unknown model {model!r}; choose from 'promp', 'lmpromp', 'mixture'")
    if "beta" in params:
        event["beta"] = ()
    elif hyper.learn_beta:
        raise LmprompError("hyper.learn_beta is set but params has no 'beta'")
    missing = sorted(set(event) - set(params))
    if missing:
        raise LmprompError(f"params for model {model!r} lack {missing}")
    first = next(iter(event))
    first_value = jnp.asarray(params[first])
    sample_shape = first_value.shape[: first_value.ndim - len(event[first])]
    flat = {}
    for name, shape in event.items():
        value = jnp.asarray(params[name])
        if value.shape != sample_shape + shape:
            raise LmprompError(
                f"params[{name!r}] has shape {value.shape}, expected {sample_shape + shape} "
                f"(sample dims {sample_shape} + {shape})"
            )
        flat[name] = value.reshape((-1,) + shape)
    return sample_shape, flat


def data_statistics(data) -> tuple[Array, Array, Array, Array]:
    """Per demonstration: Psi^T Psi (L, d, d), Psi^T y (L, d), y^T y (L,), count (L,), over the observed entries.

    Of any form of model inputs: dense (checked by :func:`~lmpromp_ppl.models.lmpromp.masked_observations`),
    masked observations, compact (no dense design built) or the statistics themselves; computed by
    :func:`~lmpromp_ppl.data.core.demo_statistics`.
    """
    if isinstance(data, MaskedObservations):
        data = ModelData(data.psi, data.y, data.observed.astype(data.y.dtype))
    elif isinstance(data, ModelData):
        masked_observations(data)  # the shape and value checks, with their messages
    return tuple(demo_statistics(data))


def offset_marginal(
    stats: tuple[Array, Array, Array, Array], M: Array, alpha: Array, beta: Array, lambda0: float, gamma: float
) -> tuple[Array, Array, Array]:
    r"""The LMProMP with ``w``, ``h`` and ``b`` integrated out: :math:`p(\mathbf y | \mathbf M, \alpha, \beta)` and :math:`p(\mathbf b | \cdot)`.

    With :math:`\mathbf C = \alpha^{-1}\mathbf I + \gamma^{-1}\mathbf M\mathbf M^T`,
    :math:`\mathbf A = \mathbf C^{-1}` (:func:`woodbury_precision`) and, per demonstration,
    :math:`\mathbf K_i = \beta^{-1}\mathbf I + \Psi_i\mathbf C\Psi_i^T`, the weights
    :math:`\mathbf w_i \sim \mathcal N(\mathbf b, \mathbf C)` give
    :math:`\mathbf y_i | \mathbf b \sim \mathcal N(\Psi_i\mathbf b, \mathbf K_i)`, and with
    :math:`\mathbf b \sim \mathcal N(\mathbf 0, \lambda_0^{-1}\mathbf I)`

    .. math::

        \log p(\mathbf y | \mathbf M, \alpha, \beta) = \sum_i \log\mathcal N(\mathbf y_i | \mathbf 0, \mathbf K_i)
        + \tfrac d2\log\lambda_0 - \tfrac12\log|\mathbf P_b| + \tfrac12\mathbf g^T\mathbf P_b^{-1}\mathbf g,

    .. math::

        \mathbf P_b = \lambda_0\mathbf I + \sum_i\Psi_i^T\mathbf K_i^{-1}\Psi_i, \quad
        \mathbf g = \sum_i\Psi_i^T\mathbf K_i^{-1}\mathbf y_i, \quad
        \mathbf b | \mathbf y, \mathbf M, \alpha, \beta \sim \mathcal N(\mathbf P_b^{-1}\mathbf g, \mathbf P_b^{-1}).

    Both are computed in weight space, without an :math:`S \times S` matrix: with
    :math:`\mathbf P_i = \mathbf A + \beta\Psi_i^T\Psi_i` and the posterior mean
    :math:`\boldsymbol\mu_i = \mathbf P_i^{-1}\beta\Psi_i^T\mathbf y_i` of
    :math:`\mathbf w_i` under the prior :math:`\mathcal N(\mathbf 0, \mathbf C)`,
    :math:`\Psi_i^T\mathbf K_i^{-1}\Psi_i = \mathbf A - \mathbf A\mathbf P_i^{-1}\mathbf A`
    and :math:`\Psi_i^T\mathbf K_i^{-1}\mathbf y_i = \mathbf A\boldsymbol\mu_i` (Woodbury,
    no cancellation between terms of the size of :math:`\beta\Psi_i^T\Psi_i`).  Cost
    :math:`O(L d^3)` per evaluation.

    Parameters
    ----------
    stats : :func:`data_statistics` of the masked observations
    M : (d, V); alpha, beta : scalars; lambda0, gamma : prior precisions of ``b`` and ``h``

    Returns
    -------
    log_marginal : scalar
    mean : (d,) mean of :math:`p(\mathbf b | \cdot)`
    chol : (d, d) lower Cholesky factor of its precision :math:`\mathbf P_b`
    """
    gram, cross, sq, count = stats
    num_weights = cross.shape[-1]
    A = woodbury_precision(alpha, M, gamma)
    # per demonstration: P_i = A + beta G_i, mu_i = P_i^{-1} beta c_i and log N(y_i | 0, K_i)
    logdet_A = 2.0 * jnp.sum(jnp.log(jnp.diagonal(jnp.linalg.cholesky(A))))
    mean_w, chol_w, log_evidence = gaussian_conditional(
        gram, cross, sq, count, beta, jnp.zeros(num_weights), A, logdet_prior=logdet_A
    )
    # P_i^{-1} A for every demonstration, from the Cholesky factors of P_i
    half = solve_triangular(chol_w, jnp.broadcast_to(A, chol_w.shape), lower=True)
    P_inv_A = solve_triangular(jnp.swapaxes(chol_w, -1, -2), half, lower=False)
    precision = lambda0 * jnp.eye(num_weights) + mean_w.shape[0] * A - jnp.einsum("de,lef->df", A, P_inv_A)
    precision = 0.5 * (precision + precision.T)
    g = jnp.einsum("de,le->d", A, mean_w)
    chol = jnp.linalg.cholesky(precision)
    half_g = solve_triangular(chol, g[:, None], lower=True)[:, 0]
    mean = solve_triangular(chol.T, half_g[:, None], lower=False)[:, 0]
    log_marginal = (
        jnp.sum(log_evidence)
        + 0.5 * num_weights * jnp.log(lambda0)
        - jnp.sum(jnp.log(jnp.diagonal(chol)))
        + 0.5 * jnp.sum(half_g**2)
    )
    return log_marginal, mean, chol


def _b_one_draw(key: Array, theta: dict, stats, hyper: Hyperparameters) -> Array:
    """``b`` (d,) drawn from p(b | M, alpha, beta, y) for one parameter draw ``theta``."""
    beta = theta.get("beta", hyper.beta)
    _, mean, chol = offset_marginal(stats, theta["M"], theta["alpha"], beta, hyper.lambda0, hyper.gamma)
    return _draw(key, mean, chol)


def sample_b_given_theta(
    key: Array, data: ModelData, hyper: Hyperparameters, params: Mapping[str, Array]
) -> Array:
    r"""Draw ``b`` from :math:`p(\mathbf b | \mathbf M, \alpha, \beta, \mathbf y)` (:func:`offset_marginal`), one per draw.

    ``params`` holds ``M`` (..., d, V), ``alpha`` (...) and ``beta`` (...) when
    learned; returns (..., d).
    """
    stats = data_statistics(data)
    num_weights = stats[1].shape[-1]
    M = jnp.asarray(params["M"])
    sample_shape = M.shape[:-2]
    flat = {"M": M.reshape((-1,) + M.shape[-2:]),
            "alpha": jnp.asarray(params["alpha"]).reshape(-1)}
    if "beta" in params:
        flat["beta"] = jnp.asarray(params["beta"]).reshape(-1)
    elif hyper.learn_beta:
        raise LmprompError("hyper.learn_beta is set but params has no 'beta'")
    if M.shape[-2] != num_weights:
        raise LmprompError(f"params['M'] has {M.shape[-2]} rows, the data have {num_weights} weights")
    return _map_draws(lambda k, theta: _b_one_draw(k, theta, stats, hyper), key, flat, sample_shape)


def _w_one_draw(key: Array, theta: dict, stats, hyper: Hyperparameters, model: str) -> Array:
    """``w`` (L, d) drawn from p(w | theta, y) for one parameter draw ``theta``."""
    gram, cross, sq, count = stats
    num_demos, num_weights = cross.shape
    beta = theta.get("beta", hyper.beta)
    eye = jnp.eye(num_weights)
    if model == "promp":
        if "Sigma_w" in theta:
            tril = jnp.linalg.cholesky(theta["Sigma_w"])
        else:
            tril = theta["w_scale"][:, None] * theta["w_corr_chol"]
        inv_tril = solve_triangular(tril, eye, lower=True)
        prior_precision = inv_tril.T @ inv_tril
        mean, chol, _ = gaussian_conditional(
            gram, cross, sq, count, beta, theta["mu_w"], prior_precision
        )
        return _draw(key, mean, chol)

    b, M, alpha = theta["b"], theta["M"], theta["alpha"]
    if "h" in theta:
        # (L, d) or (L, K, d)
        if model == "mixture":
            prior_mean = b + jnp.einsum("kdv,lkv->lkd", M, theta["h"])
        else:
            prior_mean = b + theta["h"] @ M.T
        prior_precision = alpha[..., None, None] * eye
    else:
        prior_mean = jnp.broadcast_to(b, (num_demos,) + b.shape)
        prior_precision = woodbury_precision(alpha, M, hyper.gamma)
    if model == "lmpromp":
        mean, chol, _ = gaussian_conditional(
            gram, cross, sq, count, beta, prior_mean, prior_precision
        )
        return _draw(key, mean, chol)

    # mixture: every component at once, (L, K, ...)
    mean, chol, log_evidence = gaussian_conditional(
        gram[:, None], cross[:, None], sq[:, None], count[:, None], beta, prior_mean, prior_precision
    )
    key_z, key_w = jax.random.split(key)
    if "z" in theta:
        z = theta["z"]
    else:
        z = jax.random.categorical(key_z, jnp.log(theta["pi"]) + log_evidence, axis=-1)
    onehot = jax.nn.one_hot(z, alpha.shape[-1], dtype=mean.dtype)
    return _draw(key_w, _select(onehot, mean, 1), _select(onehot, chol, 2))


def _map_draws(fn, key: Array, flat: dict, sample_shape: tuple[int, ...]) -> Array:
    num_draws = math.prod(sample_shape)
    keys = jax.random.split(key, num_draws)
    out = jax.lax.map(lambda args: fn(*args), (keys, flat), batch_size=min(num_draws, 64))
    return out.reshape(sample_shape + out.shape[1:])


def sample_w_given_theta(
    key: Array,
    data: ModelData,
    hyper: Hyperparameters,
    params: Mapping[str, Array],
    *,
    model: str | None = None,
) -> Array:
    r"""Draw ``w`` from the exact conditional :math:`p(\mathbf w | \theta, \mathbf y)`, one per parameter draw.

    * ``lmpromp`` with ``h``: prior :math:`\mathcal N(\mathbf b + \mathbf M\mathbf h_i, \alpha^{-1}\mathbf I)`;
    * ``lmpromp`` with ``h`` collapsed: prior :math:`\mathcal N(\mathbf b, \alpha^{-1}\mathbf I + \gamma^{-1}\mathbf M\mathbf M^T)`
      (eq. 4.7 before conditioning), precision by Woodbury;
    * ``mixture``: ``z`` taken from ``params`` if present, else drawn from
      :math:`p(z_i = k | \theta, \mathbf y_i) \propto \pi_k\, p(\mathbf y_i | z_i = k, \theta)`
      (the responsibilities of Sec. 4.2.2), then ``w`` from component :math:`z_i`;
    * ``promp``: prior :math:`\mathcal N(\boldsymbol\mu_w, \boldsymbol\Sigma_w)` (eqs. 3.2-3.3).

    The posterior precision :math:`\mathbf P_0 + \beta\Psi_i^T\Psi_i` is
    factorised once per draw and demonstration (:math:`d \times d`); masked
    entries do not count.

    Parameters
    ----------
    key : PRNG key
    data : the model data the parameters were inferred from
    hyper : hyperparameters (``gamma``; ``beta`` unless ``params`` has it)
    params : site values with leading sample dims, e.g. ``(chain, draw, ...)``:
        ``b``, ``M``, ``alpha`` and optionally ``h`` (lmpromp); plus ``pi`` or ``z``
        (mixture); ``mu_w`` and ``Sigma_w`` or ``w_scale``/``w_corr_chol`` (promp);
        ``beta`` when learned.  Other entries are ignored.
    model : ``"lmpromp"``, ``"mixture"`` or ``"promp"``; inferred from the keys of
        ``params`` when None (``mu_w`` -> promp, ``pi``/``z`` -> mixture).

    Returns
    -------
    w : (*sample_shape, L, d)
    """
    stats = data_statistics(data)
    num_demos, num_weights = stats[1].shape
    model = _infer_model(params) if model is None else model
    sample_shape, flat = _params_for_draws(params, hyper, model, num_weights, num_demos)
    return _map_draws(
        lambda k, theta: _w_one_draw(k, theta, stats, hyper, model), key, flat, sample_shape
    )


def _h_one_draw(key: Array, theta: dict, hyper: Hyperparameters, model: str) -> Array:
    """``h`` drawn from p(h | w, theta) for one draw: precision gamma I + alpha M^T M."""
    w, b, M, alpha = theta["w"], theta["b"], theta["M"], theta["alpha"]
    num_demos, num_weights = w.shape
    num_latent = M.shape[-1]
    if model == "mixture":
        resid = w[:, None] - b  # (L, K, d)
        M_t = jnp.swapaxes(M, -1, -2)  # (K, V, d)
        gram = jnp.broadcast_to(M_t @ M, (num_demos,) + M.shape[:1] + (num_latent, num_latent))
        cross = jnp.einsum("kvd,lkd->lkv", M_t, resid)
        nu = jnp.broadcast_to(alpha, (num_demos, alpha.shape[0]))
    else:
        resid = w - b
        gram = jnp.broadcast_to(M.T @ M, (num_demos, num_latent, num_latent))
        cross = resid @ M
        nu = jnp.broadcast_to(alpha, (num_demos,))
    mean, chol, log_evidence = gaussian_conditional(
        gram,
        cross,
        jnp.sum(resid**2, axis=-1),
        jnp.full(nu.shape, float(num_weights)),
        nu,
        jnp.zeros(cross.shape),
        hyper.gamma * jnp.broadcast_to(jnp.eye(num_latent), gram.shape),
    )
    key_z, key_h, key_prior = jax.random.split(key, 3)
    h = _draw(key_h, mean, chol)
    if model == "lmpromp":
        return h
    if "z" in theta:
        z = theta["z"]
    else:
        # p(z_i = k | w_i) ∝ pi_k N(w_i | b_k, alpha_k^-1 I + gamma^-1 M_k M_k^T)
        z = jax.random.categorical(key_z, jnp.log(theta["pi"]) + log_evidence, axis=-1)
    onehot = jax.nn.one_hot(z, alpha.shape[-1], dtype=h.dtype)
    prior_draw = jax.random.normal(key_prior, h.shape, dtype=h.dtype) * hyper.gamma**-0.5
    return jnp.where(onehot[..., None] > 0, h, prior_draw)


def sample_h_given_theta(
    key: Array,
    hyper: Hyperparameters,
    params: Mapping[str, Array],
    *,
    model: str | None = None,
) -> Array:
    r"""Draw ``h`` from :math:`p(\mathbf h | \mathbf w, \theta)` after an ``h``-collapsed fit.

    For the LMProMP, :math:`\mathbf h_i | \mathbf w_i \sim \mathcal N(\boldsymbol\mu,
    (\gamma\mathbf I + \alpha\mathbf M^T\mathbf M)^{-1})` with
    :math:`\boldsymbol\mu = \alpha(\gamma\mathbf I + \alpha\mathbf M^T\mathbf M)^{-1}\mathbf M^T(\mathbf w_i - \mathbf b)`
    (the h-update of App. B.1 with point values).  For the mixture, ``z`` is
    taken from ``params`` or drawn from :math:`p(z_i = k | \mathbf w_i, \theta) \propto
    \pi_k\,\mathcal N(\mathbf w_i | \mathbf b_k, \alpha_k^{-1}\mathbf I + \gamma^{-1}\mathbf M_k\mathbf M_k^T)`;
    :math:`\mathbf h_{i z_i}` comes from the conditional above and the other
    components' :math:`\mathbf h_{ik}` from their prior :math:`\mathcal N(\mathbf 0, \gamma^{-1}\mathbf I)`.

    Parameters
    ----------
    key : PRNG key
    hyper : hyperparameters (``gamma``)
    params : ``w`` (*sample, L, d), e.g. from :func:`sample_w_given_theta`, with
        ``b``, ``M``, ``alpha`` (and ``pi`` or ``z`` for the mixture) with the
        same leading sample dims
    model : ``"lmpromp"`` or ``"mixture"``; inferred from ``params`` when None

    Returns
    -------
    h : (*sample, L, V) or (*sample, L, K, V)
    """
    if "w" not in params:
        raise LmprompError("sample_h_given_theta needs 'w' in params")
    model = _infer_model(params) if model is None else model
    if model not in ("lmpromp", "mixture"):
        raise LmprompError(f"sample_h_given_theta is for 'lmpromp' or 'mixture', not {model!r}")
    reduced = {k: v for k, v in params.items() if k not in ("h", "w")}
    w = jnp.asarray(params["w"])
    num_demos, num_weights = w.shape[-2:]
    sample_shape, flat = _params_for_draws(reduced, hyper, model, num_weights, num_demos)
    if w.shape != sample_shape + (num_demos, num_weights):
        raise LmprompError(
            f"params['w'] has shape {w.shape}, expected {sample_shape + (num_demos, num_weights)}"
        )
    flat["w"] = w.reshape((-1, num_demos, num_weights))
    return _map_draws(lambda k, theta: _h_one_draw(k, theta, hyper, model), key, flat, sample_shape)


def draw_integrated_sites(model_name: str, collapse: str, key, data: ModelData,
                          hyper: Hyperparameters, params: dict) -> dict:
    r"""Draw the integrated-out sites for a batch of posterior draws.

    Parameters
    ----------
    model_name, collapse : model and collapse specification (``"w"``, ``"wh"`` or ``"whb"``)
    key : PRNG key
    data : model inputs: dense, compact or :class:`~lmpromp_ppl.data.core.DemoStatistics`
    hyper : hyperparameters
    params : site name -> (N, ...) constrained draws of the sampled (and fixed) sites

    Returns
    -------
    dict with ``w`` (N, L, d) drawn from :math:`p(\mathbf w_i | \theta, \mathbf y_i)`,
    and, when ``collapse`` is ``"wh"`` or ``"whb"``, ``h`` (N, L, [K,] V) drawn from
    :math:`p(\mathbf h_i | \mathbf w_i, \theta)`, so that ``(w, h)`` is a draw of
    their joint conditional; with ``"whb"``, ``b`` (N, d) is drawn first from
    :math:`p(\mathbf b | \mathbf M, \alpha, \beta, \mathbf y)` and the others given it.
    """
    key_w, key_h = jax.random.split(key)
    out = {}
    if collapse == "whb":
        out["b"] = sample_b_given_theta(jax.random.fold_in(key, 2), data, hyper, params)
        params = dict(params, b=out["b"])
    w = sample_w_given_theta(key_w, data, hyper, params, model=model_name)
    out["w"] = w
    if collapse in ("wh", "whb"):
        out["h"] = sample_h_given_theta(key_h, hyper, dict(params, w=w), model=model_name)
    return out

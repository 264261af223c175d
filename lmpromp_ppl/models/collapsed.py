r"""Collapsed models: the weights ``w`` (and optionally ``h``) integrated out analytically.

Integrating :math:`\mathbf w_i \sim \mathcal N(\mathbf m_i, \mathbf C)` out of
:math:`\mathbf y_i \sim \mathcal N(\Psi_i \mathbf w_i, \beta^{-1}\mathbf I)` gives

.. math::

    \mathbf y_i \sim \mathcal N(\Psi_i \mathbf m_i,\; \beta^{-1}\mathbf I_S + \Psi_i \mathbf C \Psi_i^T),

the marginal the thesis writes for the ProMP in Sec. 3.1 (where a "+" between
the two covariance terms is missing) and for the LMProMP in the derivation of
eqs. 4.4-4.7 (matrix :math:`A`; the thesis writes :math:`\gamma\mathbf I_V` for
the covariance of :math:`\mathbf h`, which under its prior
:math:`\mathcal N(\mathbf 0, \gamma^{-1}\mathbf I_V)` is :math:`\gamma^{-1}\mathbf I_V`;
the two agree at the thesis's :math:`\gamma = 1`).  :math:`\mathbf C` is
always low rank plus the diagonal noise, so the site ``y`` is a NumPyro
:class:`~numpyro.distributions.LowRankMultivariateNormal` (Woodbury identity and
matrix determinant lemma, cost :math:`O(S r^2)` with rank ``r``), never a
dense :math:`S \times S` covariance:

* LMProMP (eq. 4.1), ``h`` kept: loc :math:`\Psi_i(\mathbf b + \mathbf M\mathbf h_i)`,
  ``cov_factor`` :math:`\alpha^{-1/2}\Psi_i` (rank d);
* LMProMP, ``h`` collapsed: loc :math:`\Psi_i\mathbf b`, ``cov_factor``
  :math:`\Psi_i[\alpha^{-1/2}\mathbf I_d, \gamma^{-1/2}\mathbf M]` (rank d + V);
* LMProMP, ``h`` and the offset ``b`` collapsed (:func:`lmpromp_offset_collapsed_model`):
  ``b`` couples all demonstrations, so the marginal is a factor computed in
  weight space (:func:`lmpromp_ppl.models.conditionals.offset_marginal`, :math:`O(Ld^3)`);
* mixture (eq. 4.8): the same per component k with :math:`\mathbf b_k, \mathbf M_k, \alpha_k`,
  ``z`` summed out (:class:`~numpyro.distributions.MixtureSameFamily`);
* ProMP (eq. 3.1): loc :math:`\Psi_i\boldsymbol\mu_w`, ``cov_factor``
  :math:`\Psi_i\mathbf L_\Sigma` (rank d),

with ``cov_diag`` = :math:`\beta^{-1}`.

**Shared design** (:class:`~lmpromp_ppl.data.core.SharedDesign`).  When every
demonstration has the same fully observed design :math:`\Psi`, the LMProMP and
the mixture (``h`` kept or collapsed) compute the same marginal from sufficient
statistics in the eigenbasis :math:`\Psi^T\Psi = \mathbf U\mathrm{diag}(\mathbf g)\mathbf U^T`
(:func:`shared_log_evidence`): O(L d V) per evaluation, no factorisation larger
than V x V, and the site ``y`` is a ``numpyro.factor`` per demonstration (inside the
``demo`` plate) instead of a ``LowRankMultivariateNormal``.  Its gradient costs
NUTS and SVI a fraction of the dense form's (``benchmarks/README.md``).  A masked entry has a zero row of
:math:`\Psi_i` and ``y = 0`` (:func:`~lmpromp_ppl.models.lmpromp.masked_observations`),
so it is independent of the rest and contributes exactly
:math:`\log \mathcal N(0 | 0, \beta^{-1})`; a ``numpyro.factor`` named
``y_missing`` removes that, so the density equals the one over observed entries
only (when ``observed=False`` there is nothing to remove and no factor).

**Designs that differ** (:class:`~lmpromp_ppl.data.core.DemoStatistics`: demonstrations of
different lengths or phases, missing values).  The same marginals follow from per-demonstration
statistics :math:`\mathbf G_i = \Psi_i^T\Psi_i`, :math:`\Psi_i^T\mathbf y_i`, :math:`\mathbf y_i^T\mathbf y_i`
and the count of observed entries (:func:`statistics_log_evidence`, through
:func:`~lmpromp_ppl.models.conditionals.gaussian_conditional`: one d x d factorisation per
demonstration, O(L d^3), instead of the S-sized low-rank form, O(L S (d + V)^2)); masked entries
simply do not count, so there is no ``y_missing`` factor.  The ProMP collapsed over ``w`` and the
offset-collapsed LMProMP take them too; the full mixture and the full ProMP keep the dense form.

After inference on a collapsed model, :mod:`lmpromp_ppl.models.conditionals`
restores ``w`` (and ``h``) by drawing them from their exact Gaussian conditionals.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpyro
import numpyro.distributions as dist
from jax import Array
from jax.scipy.linalg import solve_triangular

from lmpromp_ppl.data.core import DemoStatistics, ModelData, SharedDesign
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.models.conditionals import data_statistics, gaussian_conditional, offset_marginal
from lmpromp_ppl.models.hyper import Hyperparameters
from lmpromp_ppl.models.lmpromp import MaskedObservations, global_priors, observation_precision, masked_observations
from lmpromp_ppl.models.mixture import component_priors
from lmpromp_ppl.models.promp import promp_weight_prior

__all__ = [
    "shared_log_evidence",
    "statistics_log_evidence",
    "lmpromp_collapsed_model",
    "lmpromp_offset_collapsed_model",
    "mixture_collapsed_model",
    "promp_collapsed_model",
]

_LOG_2PI = math.log(2.0 * math.pi)


# --------------------------------------------------------------------------- models
def _observe_collapsed(
    prepared: MaskedObservations, y_dist: dist.Distribution, beta, observed: bool
) -> None:
    """Site ``y`` (inside the ``demo`` plate) plus the ``y_missing`` correction."""
    numpyro.sample("y", y_dist, obs=prepared.y if observed else None)
    if observed:
        # each masked entry contributed log N(0 | 0, 1/beta); remove it
        numpyro.factor(
            "y_missing", -prepared.num_missing * 0.5 * (jnp.log(beta) - _LOG_2PI)
        )


def _cov_diag(beta, shape) -> Array:
    return jnp.broadcast_to(1.0 / jnp.asarray(beta)[..., None], shape)


def shared_log_evidence(
    stats: SharedDesign, b: Array, M: Array, alpha: Array, beta: Array, gamma: float, h: Array | None = None
) -> Array:
    r"""Per demonstration, :math:`\log p(\mathbf y_i | \theta)` with ``w`` (and, when ``h`` is None, ``h``) integrated out.

    One component: :math:`\mathbf w_i \sim \mathcal N(\mathbf m_i, \mathbf A^{-1})` with
    :math:`\mathbf m_i = \mathbf b + \mathbf M\mathbf h_i`, :math:`\mathbf A = \alpha\mathbf I`
    (``h`` given), or :math:`\mathbf m_i = \mathbf b`,
    :math:`\mathbf A = (\alpha^{-1}\mathbf I + \gamma^{-1}\mathbf M\mathbf M^T)^{-1}`
    (``h`` integrated out), and :math:`\mathbf y_i \sim \mathcal N(\Psi\mathbf w_i, \beta^{-1}\mathbf I_n)`.
    With :math:`\mathbf u_i = \Psi^T(\mathbf y_i - \Psi\mathbf m_i)` and :math:`\mathbf P = \mathbf A + \beta\Psi^T\Psi`
    (:func:`~lmpromp_ppl.models.conditionals.gaussian_conditional`),

    .. math::

        \log p(\mathbf y_i | \theta) = -\tfrac n2\log 2\pi + \tfrac n2\log\beta
        + \tfrac12(\log|\mathbf A| - \log|\mathbf P|)
        - \tfrac\beta2\|\mathbf y_i - \Psi\mathbf m_i\|^2 + \tfrac{\beta^2}2\mathbf u_i^T\mathbf P^{-1}\mathbf u_i .

    In the eigenbasis (primes: rotated by :math:`\mathbf U^T`), with
    :math:`\mathbf D = \mathrm{diag}(\alpha + \beta\mathbf g)`: given ``h``, :math:`\mathbf P' = \mathbf D`
    and :math:`\log|\mathbf A| - \log|\mathbf P| = d\log\alpha - \log|\mathbf D|`.  With ``h``
    integrated out, :math:`\mathbf A' = \alpha\mathbf I - \mathbf X\mathbf S^{-1}\mathbf X^T`
    (Woodbury) with :math:`\mathbf X = \alpha\mathbf M'`, :math:`\mathbf S = \gamma\mathbf I_V + \alpha\mathbf M^T\mathbf M`,
    so :math:`\mathbf P' = \mathbf D - \mathbf X\mathbf S^{-1}\mathbf X^T`; with the Schur complement
    :math:`\mathbf Q = \mathbf S - \mathbf X^T\mathbf D^{-1}\mathbf X` (V x V),
    :math:`\mathbf P'^{-1} = \mathbf D^{-1} + \mathbf D^{-1}\mathbf X\mathbf Q^{-1}\mathbf X^T\mathbf D^{-1}`,
    :math:`\log|\mathbf P| = \log|\mathbf D| + \log|\mathbf Q| - \log|\mathbf S|` and
    :math:`\log|\mathbf A| = d\log\alpha + V\log\gamma - \log|\mathbf S|`, so :math:`\mathbf S` cancels:
    :math:`\log|\mathbf A| - \log|\mathbf P| = d\log\alpha + V\log\gamma - \log|\mathbf D| - \log|\mathbf Q|`.
    Finally :math:`\|\mathbf y_i - \Psi\mathbf m_i\|^2 = \mathbf y_i^T\mathbf y_i - 2\mathbf m_i'^T\mathbf c_i'
    + \mathbf m_i'^T\mathrm{diag}(\mathbf g)\mathbf m_i'` and :math:`\mathbf u_i' = \mathbf c_i' - \mathbf g\circ\mathbf m_i'`.
    Cost O(L d V + d^2 V) (the rotation of M); with ``h`` integrated out every term that touches
    the statistics is a product of ``cross`` with a vector or a d x V matrix, so a ``vmap`` over draws
    turns it into one matrix product against all draws.

    Parameters
    ----------
    stats : the shared design's statistics
    b : (d,), M : (d, V), alpha, beta : scalars, gamma : prior precision of ``h``
    h : (L, V), or None to integrate ``h`` out

    Returns
    -------
    (L,) log densities
    """
    rotation, g, cross, sq, count = stats
    num_weights = g.shape[0]
    M_r = rotation.T @ M
    b_r = rotation.T @ b
    diag = alpha + beta * g
    inv = 1.0 / diag
    if h is None:
        # mean b' for every demonstration; each term below is a product of the statistics
        # (cross, L x d) with a vector or a d x V matrix, so under vmap over draws it is one
        # matrix product against every draw (no L x d intermediate per draw).
        num_latent = M.shape[-1]
        X = alpha * M_r
        S = gamma * jnp.eye(num_latent) + alpha * (M.T @ M)
        Q = S - X.T @ (X * inv[:, None])
        chol_q = jnp.linalg.cholesky(0.5 * (Q + Q.T))
        logdet = (num_weights * jnp.log(alpha) + num_latent * math.log(gamma) - jnp.sum(jnp.log(diag))
                  - 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol_q))))
        shift = g * b_r  # u_i = cross_i - shift
        # u_i^T D^-1 u_i
        quad = (cross**2) @ inv - 2.0 * (cross @ (shift * inv)) + jnp.sum(shift**2 * inv)
        # |L_Q^-1 X^T D^-1 u_i|^2 with the factor folded into the d x V matrix
        fold = solve_triangular(chol_q, (X * inv[:, None]).T, lower=True).T
        low = cross @ fold - shift @ fold
        quad = quad + jnp.sum(low**2, axis=-1)
        residual = sq - 2.0 * (cross @ b_r) + jnp.sum(g * b_r**2)
    else:
        mean = b_r[None, :] + h @ M_r.T
        logdet = num_weights * jnp.log(alpha) - jnp.sum(jnp.log(diag))
        u = cross - g * mean
        quad = jnp.sum(u * u * inv, axis=-1)
        residual = sq - 2.0 * jnp.sum(mean * cross, axis=-1) + jnp.sum(g * mean**2, axis=-1)
    return (0.5 * count * (jnp.log(beta) - _LOG_2PI) + 0.5 * logdet
            - 0.5 * beta * residual + 0.5 * beta**2 * quad)


def statistics_log_evidence(
    stats: DemoStatistics, b: Array, M: Array, alpha: Array, beta: Array, gamma: float, h: Array | None = None
) -> Array:
    r"""Per demonstration, :math:`\log p(\mathbf y_i | \theta)` of :func:`shared_log_evidence` for designs that
    differ between demonstrations, from :class:`~lmpromp_ppl.data.core.DemoStatistics`.

    The prior of :math:`\mathbf w_i` is :math:`\mathcal N(\mathbf b + \mathbf M\mathbf h_i, \alpha^{-1}\mathbf I)`
    (``h`` given; :math:`\log|\mathbf A| = d\log\alpha`) or :math:`\mathcal N(\mathbf b, \alpha^{-1}\mathbf I +
    \gamma^{-1}\mathbf M\mathbf M^T)` (``h`` integrated out; precision by Woodbury and
    :math:`\log|\mathbf A| = d\log\alpha - \log|\mathbf I_V + (\alpha/\gamma)\mathbf M^T\mathbf M|` by the
    determinant lemma); :func:`~lmpromp_ppl.models.conditionals.gaussian_conditional` gives the
    evidence with one d x d factorisation per demonstration, O(L d^3).
    """
    num_weights, num_latent = M.shape
    if h is None:
        mean = jnp.broadcast_to(b, (stats.num_demos, num_weights))
        inner = jnp.eye(num_latent) + (alpha / gamma) * (M.T @ M)
        precision = alpha * jnp.eye(num_weights) - alpha**2 * (M @ jnp.linalg.solve(gamma * inner, M.T))
        logdet = num_weights * jnp.log(alpha) - 2.0 * jnp.sum(jnp.log(jnp.diagonal(jnp.linalg.cholesky(inner))))
    else:
        mean = b + h @ M.T
        precision = alpha * jnp.eye(num_weights)
        logdet = num_weights * jnp.log(alpha)
    _, _, log_evidence = gaussian_conditional(stats.gram, stats.cross, stats.sq, stats.count, beta, mean,
                                              precision, logdet)
    return log_evidence


def _shared_inputs(data: SharedDesign | DemoStatistics, hyper: Hyperparameters, observed: bool) -> int:
    if not observed:
        raise LmprompError("simulating demonstrations needs their design: pass ModelData or PhaseData, "
                           f"not {type(data).__name__} statistics")
    hyper.validate_for(data.num_weights)
    return data.num_weights


def lmpromp_collapsed_model(
    data: ModelData, hyper: Hyperparameters, collapse_h: bool = False, observed: bool = True
) -> None:
    r"""The LMProMP (eq. 4.1) with ``w`` (and, if ``collapse_h``, ``h``) integrated out.

    .. math::

        \mathbf y_i \sim \mathcal N\big(\Psi_i(\mathbf b + \mathbf M \mathbf h_i),\,
        \beta^{-1}\mathbf I + \alpha^{-1}\Psi_i\Psi_i^T\big)
        \quad\text{or}\quad
        \mathcal N\big(\Psi_i \mathbf b,\, \beta^{-1}\mathbf I
        + \Psi_i(\alpha^{-1}\mathbf I + \gamma^{-1}\mathbf M\mathbf M^T)\Psi_i^T\big).

    Sites: ``b``, ``lam``, ``M``, ``alpha``, ``beta`` (when learned), ``h``
    (unless ``collapse_h``), ``y`` and the factor ``y_missing``.
    """
    num_latent = hyper.latent_dim
    if isinstance(data, (SharedDesign, DemoStatistics)):
        evidence = shared_log_evidence if isinstance(data, SharedDesign) else statistics_log_evidence
        b, lam, M, alpha, beta = global_priors(hyper, _shared_inputs(data, hyper, observed))
        with numpyro.plate("demo", data.num_demos):
            h = None if collapse_h else numpyro.sample(
                "h", dist.Normal(0.0, hyper.gamma**-0.5).expand([num_latent]).to_event(1)
            )
            numpyro.factor("y", evidence(data, b, M, alpha, beta, hyper.gamma, h))
        return
    prepared = masked_observations(data)
    num_demos, size, num_weights = prepared.psi.shape
    hyper.validate_for(num_weights)

    b, lam, M, alpha, beta = global_priors(hyper, num_weights)
    psi = prepared.psi

    with numpyro.plate("demo", num_demos):
        factor_w = psi * jnp.sqrt(1.0 / alpha)
        if collapse_h:
            loc = psi @ b
            factor_h = (psi @ M) * hyper.gamma**-0.5
            cov_factor = jnp.concatenate([factor_w, factor_h], axis=-1)
        else:
            h = numpyro.sample(
                "h", dist.Normal(0.0, hyper.gamma**-0.5).expand([num_latent]).to_event(1)
            )
            loc = jnp.einsum("lsd,ld->ls", psi, b + h @ M.T)
            cov_factor = factor_w
        y_dist = dist.LowRankMultivariateNormal(
            loc, cov_factor, _cov_diag(beta, (num_demos, size))
        )
        _observe_collapsed(prepared, y_dist, beta, observed)


def lmpromp_offset_collapsed_model(data: ModelData, hyper: Hyperparameters, observed: bool = True) -> None:
    r"""The LMProMP (eq. 4.1) with ``w``, ``h`` and the offset ``b`` integrated out.

    :math:`p(\mathbf y | \mathbf M, \alpha, \beta) = \int \mathcal N(\mathbf b | \mathbf 0, \lambda_0^{-1}\mathbf I)
    \prod_i \mathcal N(\mathbf y_i | \Psi_i\mathbf b, \beta^{-1}\mathbf I + \Psi_i\mathbf C\Psi_i^T)\,d\mathbf b`,
    :math:`\mathbf C = \alpha^{-1}\mathbf I + \gamma^{-1}\mathbf M\mathbf M^T`, over the observed
    entries only (:func:`~lmpromp_ppl.models.conditionals.offset_marginal`).  Sites: ``lam``,
    ``M``, ``alpha``, ``beta`` (when learned) and the factor ``y``.  The offset is a
    posterior-correlated direction of every other site (its spread is :math:`\mathbf C / L`),
    so sampling it costs NUTS most of its tree depth; integrated out, it is drawn afterwards
    from :math:`p(\mathbf b | \mathbf M, \alpha, \beta, \mathbf y)`.  With ``observed=False``
    (simulation) this is :func:`lmpromp_collapsed_model` with ``h`` collapsed, which samples ``b``.
    """
    if not observed:
        lmpromp_collapsed_model(data, hyper, collapse_h=True, observed=False)
        return
    stats = data_statistics(data)
    num_weights = stats[1].shape[-1]
    hyper.validate_for(num_weights)
    _, _, M, alpha, beta = global_priors(hyper, num_weights, offset=False)
    log_marginal, _, _ = offset_marginal(stats, M, alpha, beta, hyper.lambda0, hyper.gamma)
    numpyro.factor("y", log_marginal)


def mixture_collapsed_model(
    data: ModelData, hyper: Hyperparameters, collapse_h: bool = False, observed: bool = True
) -> None:
    r"""The LMProMP mixture (eq. 4.8) with ``w`` (and optionally ``h``) and ``z`` integrated out.

    .. math::

        p(\mathbf y_i | \theta) = \sum_{k=1}^K \pi_k\,
        \mathcal N\big(\mathbf y_i | \Psi_i(\mathbf b_k + \mathbf M_k\mathbf h_{ik}),
        \beta^{-1}\mathbf I + \alpha_k^{-1}\Psi_i\Psi_i^T\big)

    (with ``collapse_h``: loc :math:`\Psi_i\mathbf b_k` and covariance
    :math:`\beta^{-1}\mathbf I + \Psi_i(\alpha_k^{-1}\mathbf I + \gamma^{-1}\mathbf M_k\mathbf M_k^T)\Psi_i^T`).
    Sites: ``pi``, ``b``, ``lam``, ``M``, ``alpha``, ``beta`` (when learned), ``h``
    (L, K, V) unless ``collapse_h``, ``y`` and the factor ``y_missing``.
    """
    num_components, num_latent = hyper.num_components, hyper.latent_dim
    if isinstance(data, (SharedDesign, DemoStatistics)):
        evidence = shared_log_evidence if isinstance(data, SharedDesign) else statistics_log_evidence
        pi, b, _, M, alpha = component_priors(hyper, _shared_inputs(data, hyper, observed))
        beta = observation_precision(hyper)
        with numpyro.plate("demo", data.num_demos):
            h = None if collapse_h else numpyro.sample(
                "h", dist.Normal(0.0, hyper.gamma**-0.5).expand([num_components, num_latent]).to_event(2),
            )
            per_component = jax.vmap(
                lambda b_k, M_k, alpha_k, h_k: evidence(data, b_k, M_k, alpha_k, beta, hyper.gamma, h_k),
                in_axes=(0, 0, 0, None if h is None else 1), out_axes=1,
            )(b, M, alpha, h)
            # log-softmax as MixtureSameFamily normalises its mixing weights (the same gradient in pi)
            numpyro.factor("y", jax.nn.logsumexp(jax.nn.log_softmax(jnp.log(pi)) + per_component, axis=-1))
        return
    prepared = masked_observations(data)
    num_demos, size, num_weights = prepared.psi.shape
    hyper.validate_for(num_weights)

    pi, b, _, M, alpha = component_priors(hyper, num_weights)
    beta = observation_precision(hyper)
    psi = prepared.psi

    with numpyro.plate("demo", num_demos):
        # (L, K, S, d)
        factor_w = psi[:, None] * jnp.sqrt(1.0 / alpha)[:, None, None]
        if collapse_h:
            loc = jnp.einsum("lsd,kd->lks", psi, b)
            factor_h = jnp.einsum("lsd,kdv->lksv", psi, M) * hyper.gamma**-0.5
            cov_factor = jnp.concatenate([factor_w, factor_h], axis=-1)
        else:
            h = numpyro.sample(
                "h",
                dist.Normal(0.0, hyper.gamma**-0.5).expand([num_components, num_latent]).to_event(2),
            )
            mean_w = b + jnp.einsum("kdv,lkv->lkd", M, h)
            loc = jnp.einsum("lsd,lkd->lks", psi, mean_w)
            cov_factor = factor_w
        components = dist.LowRankMultivariateNormal(
            loc, cov_factor, _cov_diag(beta, (num_demos, num_components, size))
        )
        y_dist = dist.MixtureSameFamily(
            dist.Categorical(probs=jnp.broadcast_to(pi, (num_demos, num_components))),
            components,
        )
        _observe_collapsed(prepared, y_dist, beta, observed)


def promp_collapsed_model(
    data: ModelData, hyper: Hyperparameters, observed: bool = True
) -> None:
    r"""The ProMP baseline (eq. 3.1) with ``w`` integrated out (Sec. 3.1):

    :math:`\mathbf y_i \sim \mathcal N(\Psi_i\boldsymbol\mu_w,\, \beta^{-1}\mathbf I + \Psi_i\boldsymbol\Sigma_w\Psi_i^T)`
    with ``cov_factor`` :math:`\Psi_i \mathbf L_\Sigma`.  Sites: ``mu_w``,
    ``w_scale``, ``w_corr_chol``, ``Sigma_w``, ``beta`` (when learned), ``y``,
    ``y_missing``.
    """
    if isinstance(data, DemoStatistics):
        if not observed:
            raise LmprompError("simulating demonstrations needs their design: pass ModelData or PhaseData, "
                               "not DemoStatistics")
        if data.num_weights < 2:
            raise LmprompError(f"the ProMP baseline needs at least 2 weights, got d={data.num_weights}")
        mu_w, scale_tril = promp_weight_prior(hyper, data.num_weights)
        beta = observation_precision(hyper)
        # through Sigma_w = L L^T, as the dense form reads L (its gradient off the support included)
        chol = jnp.linalg.cholesky(scale_tril @ scale_tril.T)
        inv_tril = solve_triangular(chol, jnp.eye(data.num_weights), lower=True)
        logdet = -2.0 * jnp.sum(jnp.log(jnp.diagonal(chol)))
        with numpyro.plate("demo", data.num_demos):
            _, _, log_evidence = gaussian_conditional(data.gram, data.cross, data.sq, data.count, beta, mu_w,
                                                      inv_tril.T @ inv_tril, logdet)
            numpyro.factor("y", log_evidence)
        return
    prepared = masked_observations(data)
    num_demos, size, num_weights = prepared.psi.shape
    if num_weights < 2:
        raise LmprompError(f"the ProMP baseline needs at least 2 weights, got d={num_weights}")
    mu_w, scale_tril = promp_weight_prior(hyper, num_weights)
    beta = observation_precision(hyper)
    psi = prepared.psi
    with numpyro.plate("demo", num_demos):
        y_dist = dist.LowRankMultivariateNormal(
            psi @ mu_w, psi @ scale_tril, _cov_diag(beta, (num_demos, size))
        )
        _observe_collapsed(prepared, y_dist, beta, observed)

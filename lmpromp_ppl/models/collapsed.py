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

with ``cov_diag`` = :math:`\beta^{-1}`.  A masked entry has a zero row of
:math:`\Psi_i` and ``y = 0`` (:func:`~lmpromp_ppl.models.lmpromp.masked_observations`),
so it is independent of the rest and contributes exactly
:math:`\log \mathcal N(0 | 0, \beta^{-1})`; a ``numpyro.factor`` named
``y_missing`` removes that, so the density equals the one over observed entries
only (when ``observed=False`` there is nothing to remove and no factor).

After inference on a collapsed model, :mod:`lmpromp_ppl.models.conditionals`
restores ``w`` (and ``h``) by drawing them from their exact Gaussian conditionals.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpyro
import numpyro.distributions as dist
from jax import Array

from lmpromp_ppl.data.core import ModelData
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.models.conditionals import data_statistics, offset_marginal
from lmpromp_ppl.models.hyper import Hyperparameters
from lmpromp_ppl.models.lmpromp import MaskedObservations, global_priors, observation_precision, masked_observations
from lmpromp_ppl.models.mixture import component_priors
from lmpromp_ppl.models.promp import promp_weight_prior

__all__ = [
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
    prepared = masked_observations(data)
    num_demos, size, num_weights = prepared.psi.shape
    hyper.validate_for(num_weights)
    num_latent = hyper.latent_dim

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
    prepared = masked_observations(data)
    num_weights = prepared.psi.shape[-1]
    hyper.validate_for(num_weights)
    _, _, M, alpha, beta = global_priors(hyper, num_weights, offset=False)
    log_marginal, _, _ = offset_marginal(data_statistics(prepared), M, alpha, beta, hyper.lambda0, hyper.gamma)
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
    prepared = masked_observations(data)
    num_demos, size, num_weights = prepared.psi.shape
    hyper.validate_for(num_weights)
    num_components, num_latent = hyper.num_components, hyper.latent_dim

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

r"""The ProMP baseline (thesis Sec. 3.1, eq. 3.1); its classical estimate (Sec. 3.1.1) is
:func:`lmpromp_ppl.inference.classical.classical_promp`.

Bayesian ProMP: a Gaussian weight prior with unknown mean and full covariance,

.. math::

    \boldsymbol\mu_w &\sim \mathcal N(\mathbf 0, \lambda_0^{-1} \mathbf I_d), \qquad
    \boldsymbol\Sigma_w = \mathrm{diag}(\boldsymbol\sigma)\, \mathbf L_\Omega
    \mathbf L_\Omega^T \mathrm{diag}(\boldsymbol\sigma), \qquad
    \mathbf L_\Omega \sim \mathrm{LKJCholesky}(d, \eta), \qquad
    \sigma_j \sim \mathcal N^+(0, s^2), \\
    \mathbf w_i &\sim \mathcal N(\boldsymbol\mu_w, \boldsymbol\Sigma_w) \quad \text{(eq. 3.1)},
    \qquad \mathbf y_i \sim \mathcal N(\Psi_i \mathbf w_i, \beta^{-1} \mathbf I_S).

The thesis estimates :math:`\boldsymbol\mu_w, \boldsymbol\Sigma_w` by maximum
likelihood (EM) or by the sample moments of per-demonstration least-squares
weights; a fully Bayesian treatment needs a proper prior on the covariance so
that NUTS can run, hence LKJ-Cholesky with half-normal scales.

Scale choice: on data standardised per DoF (unit variance over all samples)
the normalised basis functions sum to one, so a weight is roughly a local
trajectory value and its spread across demonstrations is at most about 1.
``hyper.promp_scale = 1`` puts the prior median of each weight's s.d. at 0.67
and 99 % of its mass below 2.6; ``hyper.lkj_concentration = 2`` mildly favours
weak correlations (eta = 1 would be uniform over correlation matrices).  The
mean uses the offset prior of the LMProMP (precision ``lambda0``) so that
``mu_w`` and ``b`` are comparable.

Sites: ``mu_w`` (d,), ``w_scale`` (d,), ``w_corr_chol`` (d, d), deterministic
``Sigma_w`` (d, d), ``beta`` () when learned, ``w`` (L, d), ``y`` (L, S).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpyro
import numpyro.distributions as dist
from jax import Array

from lmpromp_ppl.data.core import ModelData
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.models.hyper import Hyperparameters
from lmpromp_ppl.models.lmpromp import masked_observations, observation_precision, observe_y

__all__ = ["promp_model", "promp_weight_prior"]


def promp_weight_prior(hyper: Hyperparameters, num_weights: int) -> tuple[Array, Array]:
    """Sample ``mu_w``, ``w_scale``, ``w_corr_chol``; record ``Sigma_w``.

    Returns
    -------
    mu_w : (d,) prior mean of the weights
    scale_tril : (d, d) lower Cholesky factor of ``Sigma_w``
    """
    mu_w = numpyro.sample(
        "mu_w", dist.Normal(0.0, hyper.lambda0**-0.5).expand([num_weights]).to_event(1)
    )
    w_scale = numpyro.sample(
        "w_scale", dist.HalfNormal(hyper.promp_scale).expand([num_weights]).to_event(1)
    )
    w_corr_chol = numpyro.sample(
        "w_corr_chol", dist.LKJCholesky(num_weights, hyper.lkj_concentration)
    )
    scale_tril = w_scale[..., :, None] * w_corr_chol
    numpyro.deterministic("Sigma_w", scale_tril @ jnp.swapaxes(scale_tril, -1, -2))
    return mu_w, scale_tril


def promp_model(data: ModelData, hyper: Hyperparameters, observed: bool = True) -> None:
    r"""NumPyro model of the Bayesian ProMP baseline (eq. 3.1, proper LKJ prior).

    Parameters
    ----------
    data : padded model inputs ``(psi (L, S, d), y (L, S), mask (L, S))``
    hyper : hyperparameters (uses ``lambda0``, ``promp_scale``,
        ``lkj_concentration``, ``beta`` / ``learn_beta``)
    observed : condition on ``data.y`` (True) or sample ``y`` (prior predictive)
    """
    prepared = masked_observations(data)
    num_demos, _, num_weights = prepared.psi.shape
    if num_weights < 2:
        raise LmprompError(f"the ProMP baseline needs at least 2 weights, got d={num_weights}")
    mu_w, scale_tril = promp_weight_prior(hyper, num_weights)
    beta = observation_precision(hyper)
    with numpyro.plate("demo", num_demos):
        w = numpyro.sample("w", dist.MultivariateNormal(mu_w, scale_tril=scale_tril))
        observe_y(prepared, w, beta, observed)

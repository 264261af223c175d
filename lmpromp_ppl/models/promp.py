r"""The ProMP baseline (thesis Sec. 3.1, eq. 3.1) and its classical estimate (Sec. 3.1.1).

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

import numpy as np
import jax.numpy as jnp
import numpyro
import numpyro.distributions as dist
from jax import Array

from lmpromp_ppl.basis import DEFAULT_WIDTH
from lmpromp_ppl.data.core import Demonstrations, ModelData, model_data
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.models.hyper import Hyperparameters
from lmpromp_ppl.models.lmpromp import observation_precision, observe_y, prepare_data

__all__ = ["promp_model", "promp_weight_prior", "classical_promp"]


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
    prepared = prepare_data(data)
    num_demos, _, num_weights = prepared.psi.shape
    if num_weights < 2:
        raise LmprompError(f"the ProMP baseline needs at least 2 weights, got d={num_weights}")
    mu_w, scale_tril = promp_weight_prior(hyper, num_weights)
    beta = observation_precision(hyper)
    with numpyro.plate("demo", num_demos):
        w = numpyro.sample("w", dist.MultivariateNormal(mu_w, scale_tril=scale_tril))
        observe_y(prepared, w, beta, observed)


def classical_promp(
    demos: ModelData | Demonstrations,
    num_basis: int | None = None,
    width: float = DEFAULT_WIDTH,
    ridge: float = 1e-6,
    shrinkage: str | float = "ledoit-wolf",
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""Classical ProMP estimate (Sec. 3.1.1): per-demonstration ridge fit, then moments.

    For each demonstration :math:`\hat{\mathbf w}_i = (\Psi_i^T \Psi_i + \rho \mathbf I)^{-1}
    \Psi_i^T \mathbf y_i` over its observed entries (the thesis's least squares with
    a ridge :math:`\rho` for numerical safety); :math:`\boldsymbol\mu_w` is their
    mean and :math:`\boldsymbol\Sigma_w` a shrunk sample covariance.

    Parameters
    ----------
    demos : padded :class:`ModelData`, or :class:`Demonstrations` (then ``num_basis``
        is required and the design matrices are built with ``width``)
    num_basis, width : basis of :func:`lmpromp_ppl.data.core.model_data`
    ridge : :math:`\rho`, added to the diagonal of :math:`\Psi_i^T \Psi_i` (absolute)
    shrinkage : ``"ledoit-wolf"`` (scikit-learn's Ledoit-Wolf estimate, which
        normalises by L), or a number :math:`s \in [0, 1]`: the unbiased sample
        covariance :math:`\mathbf C` shrunk toward a scaled identity,
        :math:`(1 - s)\mathbf C + s\,\frac{\mathrm{tr}\,\mathbf C}{d}\mathbf I`
        (``0`` gives the plain sample covariance of the thesis)

    Returns
    -------
    mu_w : (d,), Sigma_w : (d, d), w_hat : (L, d)
    """
    if isinstance(demos, Demonstrations):
        if num_basis is None:
            raise LmprompError("classical_promp needs num_basis when given Demonstrations")
        demos = model_data(demos, num_basis, width)
    prepared = prepare_data(demos)
    if not ridge >= 0:
        raise LmprompError(f"ridge must be non-negative, got {ridge}")
    psi = np.asarray(prepared.psi)
    y = np.asarray(prepared.y)
    num_demos, _, num_weights = psi.shape
    if num_demos < 2:
        raise LmprompError(f"classical_promp needs at least 2 demonstrations, got {num_demos}")
    gram = np.einsum("lsd,lse->lde", psi, psi) + ridge * np.eye(num_weights)
    try:
        w_hat = np.linalg.solve(gram, np.einsum("lsd,ls->ld", psi, y)[..., None])[..., 0]
    except np.linalg.LinAlgError:
        raise LmprompError(
            "a demonstration's least-squares problem is singular; increase ridge"
        ) from None
    mu_w = w_hat.mean(axis=0)
    if isinstance(shrinkage, str):
        if shrinkage != "ledoit-wolf":
            raise LmprompError(f"unknown shrinkage {shrinkage!r}; use 'ledoit-wolf' or a number in [0, 1]")
        from sklearn.covariance import LedoitWolf

        sigma_w = LedoitWolf(assume_centered=False).fit(w_hat).covariance_
    else:
        s = float(shrinkage)
        if not 0.0 <= s <= 1.0:
            raise LmprompError(f"shrinkage must be in [0, 1], got {shrinkage}")
        sample = np.cov(w_hat, rowvar=False).reshape(num_weights, num_weights)
        target = np.trace(sample) / num_weights * np.eye(num_weights)
        sigma_w = (1.0 - s) * sample + s * target
    return mu_w, sigma_w, w_hat

r"""The classical ProMP estimator (thesis Sec. 3.1.1): least-squares weights per demonstration, then moments.

Not a Bayesian engine: the baseline the thesis compares the LMProMP with, and a
fast reference in the benchmarks.  (The Bayesian ProMP is
:func:`lmpromp_ppl.models.promp.promp_model`, run by NUTS and SVI.)
"""

from __future__ import annotations

import numpy as np

from lmpromp_ppl.basis import DEFAULT_WIDTH
from lmpromp_ppl.data.core import Demonstrations, ModelData
from lmpromp_ppl.data.prepared import prepare_dataset
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.models.lmpromp import masked_observations

__all__ = ["classical_promp"]


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
        demos = prepare_dataset(demos, num_basis, standardise=False, width=width).model_data
    prepared = masked_observations(demos)
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

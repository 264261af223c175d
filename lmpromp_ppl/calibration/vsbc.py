r"""Variational simulation-based calibration (VSBC, Yao et al. 2018, Algorithm 2).

For each simulated dataset j and scalar i, :math:`p_{ij} = \Pr_q(\theta_i < \tilde\theta_{ij})`
is the probability under the fitted approximation q that the scalar lies below
its true value.  When the point estimates of q are unbiased on average over
the prior, the distribution of :math:`p_{i\cdot}` is symmetric about 1/2, which
is tested with a two-sample Kolmogorov-Smirnov test of :math:`p_{i\cdot}`
against :math:`1 - p_{i\cdot}`.  Unlike SBC, VSBC ignores the width of q: it
checks the marginal point estimates only.

:func:`vsbc_probabilities` and :func:`vsbc_test` compute exactly the
statistic of numpyro's :func:`numpyro.infer.calibration.vsbc_diagnostic`
(Monte Carlo :math:`p_{ij}` as the fraction of draws strictly below the truth;
``scipy.stats.ks_2samp(p, 1 - p, method="asymp")``), so that CAVI and the
SVI engines of :mod:`.sbc` are judged alike; :func:`numpyro_vsbc` runs
numpyro's function itself on the LMProMP with w and h integrated out
(:func:`lmpromp_ppl.models.collapsed.lmpromp_collapsed_model`) or the ProMP
with w integrated out, with an ``AutoNormal`` guide.

References
----------
Yao, Y., Vehtari, A., Simpson, D. and Gelman, A. (2018). Yes, but did it work?
Evaluating variational inference. ICML.
"""

from __future__ import annotations

from functools import partial
from typing import Any

import jax
import numpy as np

from lmpromp_ppl.errors import LmprompError

__all__ = ["vsbc_probabilities", "vsbc_test", "numpyro_vsbc"]


def vsbc_probabilities(truth: np.ndarray, draws: np.ndarray) -> np.ndarray:
    """:math:`p = \\Pr_q(\\theta < \\tilde\\theta)`: fraction of ``draws`` (N, k) strictly below ``truth`` (k,)."""
    truth, draws = np.asarray(truth, dtype=float), np.asarray(draws, dtype=float)
    if draws.ndim != 2 or truth.shape != draws.shape[1:]:
        raise LmprompError(f"draws must be (N, k) and truth (k,), got {draws.shape} and {truth.shape}")
    return np.mean(draws < truth, axis=0)


def vsbc_test(probabilities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """KS statistic and p-value of :math:`p_{\\cdot i}` against :math:`1 - p_{\\cdot i}` per column of (R, k)."""
    from scipy.stats import ks_2samp

    p = np.asarray(probabilities, dtype=float)
    if p.ndim != 2 or p.shape[0] < 2:
        raise LmprompError(f"probabilities must be (replicates >= 2, k), got {p.shape}")
    stats, pvalues = np.empty(p.shape[1]), np.empty(p.shape[1])
    for i in range(p.shape[1]):
        stats[i], pvalues[i] = ks_2samp(p[:, i], 1.0 - p[:, i], method="asymp")
    return stats, pvalues


def numpyro_vsbc(
    model_name: str,
    data,
    hyper,
    key: jax.Array,
    *,
    num_simulations: int = 20,
    num_svi_steps: int = 2000,
    num_samples: int = 200,
    learning_rate: float = 0.01,
) -> dict[str, Any]:
    """numpyro's ``vsbc_diagnostic`` on the problem's collapsed model with an AutoNormal guide.

    Parameters
    ----------
    model_name : ``"lmpromp"`` or ``"promp"`` (the SBC problem's model)
    data : the problem's design (:func:`lmpromp_ppl.calibration.sbc.design`), :class:`ModelData`
    hyper : the problem's hyperparameters (the SIMULATION prior)
    key : PRNG key
    num_simulations, num_svi_steps, num_samples : as in ``vsbc_diagnostic``
        (a fixed number of Adam steps per simulated dataset)
    learning_rate : Adam step size

    Returns
    -------
    ``{"probabilities": {site: (R, ...) list}, "ks_stats": {...}, "ks_pvalues": {...}}``
    for the sampled sites (``b``, ``M``, ``alpha``, ``lam`` for the LMProMP;
    ``mu_w``, ``w_scale``, ``w_corr_chol`` for the ProMP), as JSON-able lists.
    """
    from numpyro.infer import Trace_ELBO
    from numpyro.infer.autoguide import AutoNormal
    from numpyro.infer.calibration import vsbc_diagnostic
    from numpyro.optim import Adam

    from lmpromp_ppl.data.core import ModelData
    from lmpromp_ppl.models.collapsed import lmpromp_collapsed_model, promp_collapsed_model

    if model_name == "lmpromp":
        model = partial(lmpromp_collapsed_model, collapse_h=True)
    else:
        model = promp_collapsed_model

    def simulated_data_to_args(sim_data, data, hyper, observed=True):
        y = sim_data.get("y")
        if y is None:
            return (data, hyper), {"observed": False}
        return (ModelData(data.psi, y, data.mask), hyper), {"observed": True}

    if jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)  # numpyro's diagnostic splits raw uint32 keys
    result = vsbc_diagnostic(
        key, model, AutoNormal(model), Adam(learning_rate), Trace_ELBO(), data, hyper,
        observed_sites=["y"], simulated_data_to_args=simulated_data_to_args,
        num_simulations=int(num_simulations), num_svi_steps=int(num_svi_steps), num_samples=int(num_samples),
    )
    as_list = lambda d: {k: np.asarray(v).tolist() for k, v in d.items()}  # noqa: E731
    return {"probabilities": as_list(result.probabilities), "ks_stats": as_list(result.ks_stats),
            "ks_pvalues": as_list(result.ks_pvalues)}

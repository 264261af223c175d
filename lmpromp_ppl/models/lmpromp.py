r"""The Latent-Manifold ProMP for a single movement type (thesis Sec. 4.1, eq. 4.1).

Generative model, for demonstrations :math:`i = 1, \dots, L` (precisions
throughout, Gamma is shape/rate):

.. math::

    \mathbf b &\sim \mathcal N(\mathbf 0, \lambda_0^{-1} \mathbf I_d), \qquad
    \lambda_v \sim \Gamma(c_0, d_0), \qquad
    \mathbf m_v \sim \mathcal N(\mathbf 0, \lambda_v^{-1} \mathbf I_d), \qquad
    \alpha \sim \Gamma(a_0, b_0), \\
    \mathbf h_i &\sim \mathcal N(\mathbf 0, \gamma^{-1} \mathbf I_V), \qquad
    \mathbf w_i \sim \mathcal N(\mathbf b + \mathbf M \mathbf h_i, \alpha^{-1} \mathbf I_d)
    \quad \text{(eq. 4.1)}, \qquad
    \mathbf y_i \sim \mathcal N(\Psi_i \mathbf w_i, \beta^{-1} \mathbf I_S),

with :math:`\beta \sim \Gamma(\beta_{a0}, \beta_{b0})` when
``hyper.learn_beta`` and the fixed ``hyper.beta`` otherwise (the thesis keeps
:math:`\beta` fixed, Sec. 4.1).

Sites and shapes (docs/cli.md): ``b`` (d,), ``lam`` (V,), ``M``
(d, V), ``alpha`` (), ``beta`` () when learned, ``h`` (L, V), ``w`` (L, d),
``y`` (L, S).  Entries with ``mask == 0`` (padding or missing values) do not
contribute to the density.  On the statistics forms of the data
(:class:`~lmpromp_ppl.data.core.SharedDesign`, :class:`~lmpromp_ppl.data.core.DemoStatistics`,
chosen by :func:`lmpromp_ppl.models.registry.model_inputs`) ``y`` is a ``numpyro.factor``
per demonstration with the same value (:func:`shared_log_likelihood`, :func:`statistics_log_likelihood`).

This module also holds the data checks shared by every model of
:mod:`lmpromp_ppl.models`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import jax
import jax.numpy as jnp
import numpyro
import numpyro.distributions as dist
from jax import Array

from lmpromp_ppl.data.core import DemoStatistics, ModelData, PhaseData, SharedDesign
from lmpromp_ppl.errors import DataError
from lmpromp_ppl.models.hyper import Hyperparameters

_LOG_2PI = math.log(2.0 * math.pi)

__all__ = [
    "lmpromp_model", "MaskedObservations", "masked_observations", "check_observations", "observation_precision",
    "observe_y", "global_priors",
    "shared_log_likelihood", "statistics_log_likelihood",
]


class MaskedObservations(NamedTuple):
    """Model inputs with masked entries neutralised.

    Attributes
    ----------
    psi : (L, S, d) design matrices with the rows of masked entries set to 0
    y : (L, S) observations with masked entries set to 0
    observed : (L, S) boolean, True where an entry is observed
    num_missing : (L,) number of masked entries per demonstration
    """

    psi: Array
    y: Array
    observed: Array
    num_missing: Array


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _check_observed_values(mask, y) -> np.ndarray:
    """The value checks of concrete observations and their mask (any shape); the mask as numpy."""
    m = np.asarray(mask)
    if not np.all((m == 0) | (m == 1)):
        raise DataError("mask must contain only 0 and 1")
    if not np.all(np.isfinite(np.asarray(y)[m == 1])):
        raise DataError("observed entries of y contain NaN or inf")
    return m


def check_observations(data: ModelData | PhaseData) -> None:
    """The checks of :func:`masked_observations` on concrete model inputs, without building a dense design
    for :class:`~lmpromp_ppl.data.core.PhaseData` (raises :class:`~lmpromp_ppl.errors.DataError`)."""
    if not isinstance(data, PhaseData):
        masked_observations(data)
        return
    _check_observed_values(data.observed, data.values)
    if not np.all(np.isfinite(np.asarray(data.phi))):
        raise DataError("the basis at the demonstrations' phases contains NaN or inf")


def masked_observations(data: ModelData) -> MaskedObservations:
    """Check the shapes (and, for concrete arrays, the values) of ``data``.

    Masked entries (``mask == 0``) get ``y = 0`` and a zero design-matrix row,
    whatever they held (padding, NaN for a missing value), so that they cannot
    leak into a density or its gradient.

    Raises
    ------
    DataError
        if the shapes disagree, the mask is not 0/1, or an observed entry is
        not finite.
    """
    if isinstance(data, PhaseData):  # the compact form of the one data path: its dense view
        data = data.dense()
    if not isinstance(data, tuple) or len(data) != 3:
        raise DataError("model data must be a ModelData (psi, y, mask) or a PhaseData")
    psi, y, mask = (jnp.asarray(a) for a in data)
    if psi.ndim != 3:
        raise DataError(f"psi must have shape (L, S, d), got {psi.shape}")
    if y.shape != psi.shape[:2] or mask.shape != psi.shape[:2]:
        raise DataError(
            f"y {y.shape} and mask {mask.shape} must have shape (L, S) = {psi.shape[:2]}"
        )
    if all(_is_concrete(a) for a in (psi, y, mask)):
        m = _check_observed_values(mask, y)
        if not np.all(np.isfinite(np.asarray(psi)[m == 1])):
            raise DataError("design-matrix rows of observed entries contain NaN or inf")
    observed = mask > 0
    psi = jnp.where(observed[..., None], psi, 0.0)
    y = jnp.where(observed, y, 0.0)
    num_missing = jnp.sum(~observed, axis=-1)
    return MaskedObservations(psi, y, observed, num_missing)


def observation_precision(hyper: Hyperparameters) -> Array | float:
    """``beta``: a ``Gamma(beta_a0, beta_b0)`` site when learned, else the fixed value."""
    if hyper.learn_beta:
        return numpyro.sample("beta", dist.Gamma(hyper.beta_a0, hyper.beta_b0))
    return hyper.beta


def observe_y(prepared: MaskedObservations, w: Array, beta, observed: bool) -> Array:
    r"""Site ``y``: :math:`\mathcal N(\Psi_i \mathbf w_i, \beta^{-1} \mathbf I)` over observed entries.

    Must be called inside the ``demo`` plate; ``w`` is (L, d).
    """
    loc = jnp.einsum("lsd,ld->ls", prepared.psi, w)
    noise = dist.Normal(loc, jnp.sqrt(1.0 / beta)).mask(prepared.observed).to_event(1)
    return numpyro.sample("y", noise, obs=prepared.y if observed else None)


def lmpromp_model(data: ModelData, hyper: Hyperparameters, observed: bool = True) -> None:
    r"""NumPyro model of the LMProMP, eq. 4.1 with the priors of Sec. 4.1.

    Parameters
    ----------
    data : padded model inputs ``(psi (L, S, d), y (L, S), mask (L, S))``
    hyper : hyperparameters (precisions; Gamma shape/rate)
    observed : condition on ``data.y`` (True) or sample ``y`` (prior predictive)
    """
    statistics = isinstance(data, (SharedDesign, DemoStatistics))
    if statistics and not observed:
        raise DataError("simulating demonstrations needs their design: pass ModelData or PhaseData")
    prepared = None if statistics else masked_observations(data)
    num_demos, num_weights = (data.num_demos, data.num_weights) if statistics else prepared.psi.shape[::2]
    hyper.validate_for(num_weights)
    num_latent = hyper.latent_dim

    b, lam, M, alpha, beta = global_priors(hyper, num_weights)

    with numpyro.plate("demo", num_demos):
        h = numpyro.sample(
            "h", dist.Normal(0.0, hyper.gamma**-0.5).expand([num_latent]).to_event(1)
        )
        w = numpyro.sample(
            "w", dist.Normal(b + h @ M.T, jnp.sqrt(1.0 / alpha)).to_event(1)
        )
        if isinstance(data, SharedDesign):
            numpyro.factor("y", shared_log_likelihood(data, w, beta))
        elif statistics:
            numpyro.factor("y", statistics_log_likelihood(data, w, beta))
        else:
            observe_y(prepared, w, beta, observed)


def shared_log_likelihood(stats: SharedDesign, w: Array, beta) -> Array:
    r"""Per demonstration :math:`\log\mathcal N(\mathbf y_i | \Psi\mathbf w_i, \beta^{-1}\mathbf I_n)` from shared-design statistics.

    :math:`\|\mathbf y_i - \Psi\mathbf w_i\|^2 = \mathbf y_i^T\mathbf y_i - 2\mathbf w_i'^T\mathbf c_i'
    + \mathbf w_i'^T\mathrm{diag}(\mathbf g)\mathbf w_i'` with :math:`\mathbf w_i' = \mathbf U^T\mathbf w_i`
    (:class:`~lmpromp_ppl.data.core.SharedDesign`); ``w`` is (L, d), the result (L,).
    """
    rotated = w @ stats.rotation
    residual = stats.sq - 2.0 * jnp.sum(rotated * stats.cross, axis=-1) + jnp.sum(stats.eig * rotated**2, axis=-1)
    return 0.5 * stats.count * (jnp.log(beta) - _LOG_2PI) - 0.5 * beta * residual


def statistics_log_likelihood(stats: DemoStatistics, w: Array, beta) -> Array:
    r"""Per demonstration :math:`\log\mathcal N(\mathbf y_i | \Psi_i\mathbf w_i, \beta^{-1}\mathbf I)` over the
    observed entries, from :class:`~lmpromp_ppl.data.core.DemoStatistics`:
    :math:`\|\mathbf y_i - \Psi_i\mathbf w_i\|^2 = \mathbf y_i^T\mathbf y_i - 2\mathbf w_i^T\mathbf c_i
    + \mathbf w_i^T\mathbf G_i\mathbf w_i`; ``w`` is (L, d), the result (L,)."""
    residual = stats.sq - 2.0 * jnp.sum(w * stats.cross, axis=-1) + jnp.einsum("li,lij,lj->l", w, stats.gram, w)
    return 0.5 * stats.count * (jnp.log(beta) - _LOG_2PI) - 0.5 * beta * residual


def global_priors(hyper: Hyperparameters, num_weights: int, offset: bool = True):
    r"""The global sites of eq. 4.1 and Sec. 4.1, shared by the full and collapsed forms.

    :math:`b \sim N(0, \lambda_0^{-1} I_d)`, :math:`\lambda_v \sim \Gamma(c_0, d_0)`,
    column :math:`m_v \sim N(0, \lambda_v^{-1} I_d)`, :math:`\alpha \sim \Gamma(a_0, b_0)`,
    and :math:`\beta` (sampled only when learned).  Returns ``(b, lam, M, alpha, beta)``;
    without ``offset`` the site ``b`` is left out (integrated out by the caller) and ``b`` is None.
    """
    num_latent = hyper.latent_dim
    b = None
    if offset:
        b = numpyro.sample(
            "b", dist.Normal(0.0, hyper.lambda0**-0.5).expand([num_weights]).to_event(1)
        )
    lam = numpyro.sample("lam", dist.Gamma(hyper.c0, hyper.d0).expand([num_latent]).to_event(1))
    # column v of M has precision lam[v]
    M = numpyro.sample(
        "M",
        dist.Normal(0.0, jnp.broadcast_to(lam**-0.5, (num_weights, num_latent))).to_event(2),
    )
    alpha = numpyro.sample("alpha", dist.Gamma(hyper.a0, hyper.b0))
    return b, lam, M, alpha, observation_precision(hyper)

r"""Importance sampling of the global quantities with the linear-response Gaussian as proposal.

With :math:`\theta = (b, M, \alpha, \lambda, \beta)` drawn from the linear-response
Gaussian :math:`q_{LR}` (:mod:`.linear_response`, precisions on the log scale) and the
local variables drawn from their exact conditional :math:`p(w, h \mid \theta, y)`, the
importance ratio of the pair is

.. math::

    \frac{p(\theta, w, h, y)}{q_{LR}(\theta)\,p(w, h \mid \theta, y)} = \frac{p(\theta, y)}{q_{LR}(\theta)},

the ratio on the LMProMP with w and h integrated out
(:func:`lmpromp_ppl.models.collapsed.lmpromp_collapsed_model`, ``collapse_h=True``;
the same reduction as for the SVI guides of the collapsed model).  Its space has
:math:`d(V + 1) + V + 1` dimensions, not :math:`L(d + V)` more, so its Pareto
:math:`\hat k` (:func:`lmpromp_ppl.inference.psis.psis`) can be small where the k-hat of
any factorised q over every site cannot.  When :math:`\hat k` <
:data:`~lmpromp_ppl.inference.psis.KHAT_RESAMPLE`, draws are resampled by the
smoothed weights (sampling-importance-resampling), then the locals are drawn from
their exact conditionals (:func:`lmpromp_ppl.models.conditionals.draw_integrated_sites`).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from numpyro.infer.util import log_density

from lmpromp_ppl.data.core import DemoStatistics
from lmpromp_ppl.inference.cavi.linear_response import LinearResponse, gaussian_draws, log_q_globals, split_quantities
from lmpromp_ppl.inference.psis import KHAT_RESAMPLE, psis
from lmpromp_ppl.models.collapsed import lmpromp_collapsed_model
from lmpromp_ppl.models.conditionals import draw_integrated_sites
from lmpromp_ppl.models.hyper import Hyperparameters

__all__ = ["global_draws", "global_log_ratios", "importance_draws", "resamples", "resample_pool", "POOL"]

#: Proposals drawn for one importance-resampled set of draws (at least four per draw kept).
POOL = 4000


def global_draws(key: Array, lr: LinearResponse, num_draws: int, learned: bool, d: int, V: int) -> dict:
    """``num_draws`` draws of the global sites from the linear-response Gaussian."""
    return split_quantities(gaussian_draws(key, lr, num_draws), lr.basis, d, V, learned)


def resamples(mode: str, khat: float | None) -> bool:
    """Whether draws are importance-resampled: ``mode`` ``"auto"`` and k-hat below :data:`KHAT_RESAMPLE`."""
    return mode == "auto" and khat is not None and khat < KHAT_RESAMPLE


def resample_pool(key: Array, pool: dict, log_weights: np.ndarray, num_draws: int) -> dict:
    """``num_draws`` members of ``pool`` (site -> (S, ...)) drawn with replacement by the normalised weights."""
    size = next(iter(pool.values())).shape[0]
    index = jax.random.choice(key, size, (int(num_draws),), p=jnp.exp(jnp.asarray(log_weights)))
    return {k: v[index] for k, v in pool.items()}


@partial(jax.jit, static_argnames=("num_draws", "learned", "d", "V", "hyper"))
def _ratios(key, lr, inputs, hyper: Hyperparameters, num_draws: int, learned: bool, d: int, V: int):
    g = gaussian_draws(key, lr, num_draws)
    draws = split_quantities(g, lr.basis, d, V, learned)
    log_p = jax.vmap(lambda p: log_density(lmpromp_collapsed_model, (inputs, hyper), {"collapse_h": True}, p)[0])(
        draws)
    return g, draws, log_p - log_q_globals(lr, draws)


def global_log_ratios(key: Array, lr: LinearResponse, inputs, hyper: Hyperparameters, num_draws: int,
                      learned: bool) -> tuple[dict, np.ndarray]:
    """Global draws from :math:`q_{LR}` and their log ratios :math:`\\log p(\\theta, y) - \\log q_{LR}(\\theta)`.

    ``inputs`` are the collapsed model's inputs (:func:`lmpromp_ppl.models.registry.model_inputs`
    with ``"wh"``); ``hyper`` the fit's hyperparameters.
    """
    d = lr.basis.shape[0]
    V = (lr.mean.shape[0] - d - 1 - int(learned)) // (d + 1)
    _, draws, ratios = _ratios(key, lr, inputs, hyper, int(num_draws), bool(learned), d, V)
    return draws, np.asarray(ratios)


def importance_draws(key: Array, lr: LinearResponse, inputs, hyper: Hyperparameters, num_draws: int,
                     learned: bool, data, pool: int = POOL) -> tuple[dict, float | None, str]:
    """``num_draws`` importance-resampled draws of every site, the pool's k-hat and a note.

    ``inputs`` as for :func:`global_log_ratios`; ``data`` the model inputs of the fit, from
    which the locals' conditionals are formed.

    ``max(pool, 4 num_draws)`` proposals are weighted by PSIS and resampled with
    replacement; ``w`` and ``h`` are then drawn from their exact conditionals given each
    resampled :math:`\\theta`.  When the weights cannot be formed the draws are the
    proposals themselves and the note says why.
    """
    k_pool, k_pick, k_local = jax.random.split(key, 3)
    size = max(int(pool), 4 * int(num_draws))
    draws, ratios = global_log_ratios(k_pool, lr, inputs, hyper, size, learned)
    log_weights, khat, note = psis(ratios)
    if log_weights is None:
        picked = {k: v[: int(num_draws)] for k, v in draws.items()}
    else:
        picked = resample_pool(k_pick, draws, log_weights, num_draws)
    local_inputs = inputs if isinstance(inputs, DemoStatistics) else data
    picked.update(draw_integrated_sites("lmpromp", "wh", k_local, local_inputs, hyper, picked))
    return picked, khat, note

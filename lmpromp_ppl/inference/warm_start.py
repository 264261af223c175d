r"""Starting NUTS from the CAVI posterior (``fit_nuts(..., init="cavi")``).

NUTS started uniformly in (-2, 2) on the unconstrained scale spends the
start of its warm-up walking to the typical set: ``alpha`` and ``lam`` start
near 1 where the posterior puts them at 10^1-10^3.  CAVI finds the posterior
mode region in about a second, so :func:`cavi_start` draws one start per chain
from its posterior q, as Pathfinder does for Stan (Zhang, Carpenter, Gelman
and Vehtari 2022, "Pathfinder: parallel quasi-Newton variational inference",
JMLR 23): the chains begin in the typical set, at different points, so the
split R-hat still compares chains that did not start together.  The draws
cover those of ``b``, ``M``, ``alpha``, ``lam`` and a learned ``beta`` of the
single-type LMProMP that NUTS samples (``b`` is left out when it is integrated
out; ``h`` and ``w``, when sampled, start from their own uniform draws).  Measured against the uniform start in the module
docstring of :mod:`lmpromp_ppl.inference.nuts`: with two chains it made no
consistent difference to R-hat or ESS after 500 warm-up steps; with the four
chains of today's default a uniform start let one chain of the synthetic
example stall (153 divergent transitions, R-hat 1.054, key 1) where the CAVI
start gives none, so ``init="auto"`` (the default) uses it for the single-type LMProMP.
"""

from __future__ import annotations

import jax
import numpy as np

from lmpromp_ppl.data.core import ModelData
from lmpromp_ppl.models.hyper import Hyperparameters

__all__ = ["START_SITES", "WARM_START_MODELS", "cavi_start"]

#: The sites a start covers.
START_SITES = ("b", "M", "alpha", "lam", "beta")

#: Models for which a CAVI start exists.
WARM_START_MODELS = ("lmpromp",)

#: The starts are the first draws of this many from q: the number a fit's posterior draws default to
#: (:meth:`lmpromp_ppl.results.FitResult.posterior_draws`), so that a CAVI fit after a NUTS fit on the
#: same data (``lmpromp compare``) reuses the compiled sampler instead of compiling one per count.
SHARED_DRAWS = 1000


def cavi_start(
    model_name: str, data: ModelData, hyper: Hyperparameters, key: jax.Array, num_chains: int,
    sites: tuple[str, ...] = START_SITES,
) -> tuple[dict[str, np.ndarray], dict]:
    """One start per chain drawn from the CAVI posterior of the same model and hyperparameters.

    Parameters
    ----------
    model_name : ``"lmpromp"`` (see :data:`WARM_START_MODELS`)
    data : padded model inputs
    hyper : the hyperparameters NUTS samples under (CAVI is fitted with the same)
    key : PRNG key of the CAVI fit and of the draws
    num_chains : number of starts
    sites : the sites to start (those NUTS samples: without ``b`` when it is integrated out)

    Returns
    -------
    (starts, info): site name -> (num_chains, ...) constrained values, and
    ``{"seconds", "elbo", "iterations"}`` of the CAVI fit.
    """
    import time
    import warnings

    from lmpromp_ppl._keys import typed_key
    from lmpromp_ppl.errors import ConvergenceWarning, LmprompError
    from lmpromp_ppl.inference import cavi

    if model_name not in WARM_START_MODELS:
        raise LmprompError(f"a CAVI start exists for {list(WARM_START_MODELS)}, not for {model_name!r}")
    fit_key, draw_key = jax.random.split(key)
    start = time.perf_counter()
    with warnings.catch_warnings():
        # a start only has to be in the typical set, not at the converged optimum
        warnings.simplefilter("ignore", ConvergenceWarning)
        res = cavi.fit(data, hyper, fit_key)  # the CAVI engine's settings: its compiled program is shared
    # a typed key, as FitResult.posterior_draws passes: one compiled sampler for both
    draws = cavi.sample_q(typed_key(draw_key), res.state, max(num_chains, SHARED_DRAWS))
    draws = {k: v[:num_chains] for k, v in draws.items()}
    sites = [s for s in sites if s in draws and (s != "beta" or hyper.learn_beta)]
    starts = {s: np.asarray(draws[s], dtype=np.float64) for s in sites}
    info = {"seconds": time.perf_counter() - start, "elbo": float(res.elbo), "iterations": int(res.iterations)}
    return starts, info

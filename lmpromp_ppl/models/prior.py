r"""Prior and prior-predictive simulation of the ProMP, LMProMP and mixture models.

Both functions run the model of :func:`lmpromp_ppl.models.get_model` with
``observed=False`` under :class:`numpyro.infer.Predictive`.  The mixture is run
in its explicit form (``marginalize=False``) so that the draws carry the
assignments ``z`` (the movement type of each simulated demonstration).

Near-improper hyperparameters are refused.  A Gamma prior on a precision whose
10 % quantile lies below :data:`MIN_PRECISION_QUANTILE` (= 1e-6, i.e. a
standard deviation above 1000 in units of the standardised data for at least
10 % of the draws) makes simulated weights meaningless: the thesis default
``a0 = b0 = 1e-5`` puts essentially all of alpha's prior mass near 0 (Sec. 4.1
uses it as an uninformative prior for variational inference, where the data
dominate), and even PROPER's ``a0 = b0 = 1e-2`` has a 10 % quantile near 1e-98.
Use :data:`~lmpromp_ppl.models.hyper.SIMULATION` (``preset("simulation")``).
"""

from __future__ import annotations

from functools import partial

import jax.numpy as jnp
from jax import Array
from numpyro.infer import Predictive
from scipy import stats

from lmpromp_ppl.data.core import ModelData
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.models.hyper import Hyperparameters
from lmpromp_ppl.models.lmpromp import lmpromp_model, masked_observations
from lmpromp_ppl.models.mixture import mixture_model
from lmpromp_ppl.models.promp import promp_model

__all__ = ["sample_prior", "sample_prior_predictive", "check_simulable", "MIN_PRECISION_QUANTILE"]

MIN_PRECISION_QUANTILE = 1e-6
_SIMULATION_MODELS = {
    "promp": promp_model,
    "lmpromp": lmpromp_model,
    "mixture": partial(mixture_model, marginalize=False),
}


def check_simulable(model_name: str, hyper: Hyperparameters) -> None:
    """Refuse Gamma priors on precisions that make prior simulation meaningless.

    Raises
    ------
    LmprompError
        if the 10 % quantile of the prior of ``alpha`` (a0, b0), ``lam``
        (c0, d0; not for ``promp``) or a learned ``beta`` is below
        :data:`MIN_PRECISION_QUANTILE`, or the model name is unknown.
    """
    if model_name not in _SIMULATION_MODELS:
        raise LmprompError(
            f"unknown model {model_name!r}; choose from {sorted(_SIMULATION_MODELS)}"
        )
    priors = []
    if model_name != "promp":
        priors += [("alpha", "a0", "b0"), ("lam", "c0", "d0")]
    if hyper.learn_beta:
        priors.append(("beta", "beta_a0", "beta_b0"))
    for site, shape_name, rate_name in priors:
        shape, rate = getattr(hyper, shape_name), getattr(hyper, rate_name)
        quantile = stats.gamma.ppf(0.1, shape, scale=1.0 / rate)
        if not quantile >= MIN_PRECISION_QUANTILE:
            raise LmprompError(
                f"prior simulation is meaningless with {shape_name}={shape:g}, {rate_name}={rate:g}: "
                f"10% of the prior draws of the precision {site} lie below {quantile:.3g} "
                f"(standard deviation above {MIN_PRECISION_QUANTILE ** -0.5:g}); "
                f"use preset('simulation') or a larger shape {shape_name}"
            )


def sample_prior_predictive(
    model_name: str, key: Array, data: ModelData, hyper: Hyperparameters, num_samples: int
) -> dict[str, Array]:
    """Draws of every site, ``y`` included, from the prior of ``model_name``.

    Parameters
    ----------
    model_name : ``"promp"``, ``"lmpromp"`` or ``"mixture"``
    key : PRNG key
    data : model data; only the design matrices and the mask are used
    hyper : hyperparameters (see :func:`check_simulable`)
    num_samples : number of draws

    Returns
    -------
    dict of site name -> array with a leading ``num_samples`` dim; ``y`` is
    (num_samples, L, S) with masked entries set to 0, as in :class:`ModelData`.
    """
    check_simulable(model_name, hyper)
    if isinstance(num_samples, bool) or int(num_samples) != num_samples or num_samples < 1:
        raise LmprompError(f"num_samples must be a positive integer, got {num_samples!r}")
    prepared = masked_observations(data)
    model = _SIMULATION_MODELS[model_name]
    predictive = Predictive(model, num_samples=int(num_samples))
    draws = predictive(key, data, hyper, observed=False)
    draws = {name: jnp.asarray(value) for name, value in draws.items()}
    draws["y"] = jnp.where(prepared.observed, draws["y"], 0.0)
    return draws


def sample_prior(
    model_name: str, key: Array, data: ModelData, hyper: Hyperparameters, num_samples: int
) -> dict[str, Array]:
    """Draws of the latent sites (``w`` included, ``y`` excluded) from the prior.

    Same arguments as :func:`sample_prior_predictive`.
    """
    draws = sample_prior_predictive(model_name, key, data, hyper, num_samples)
    del draws["y"]
    return draws

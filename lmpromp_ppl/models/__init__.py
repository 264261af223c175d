"""Model declarations (NumPyro) and hyperparameters.

Every engine runs on these declarations: the registry
(:mod:`lmpromp_ppl.models.registry`) maps the model names of docs/cli.md
(``"promp"``, ``"lmpromp"``, ``"mixture"``) to the NumPyro model functions,
full or collapsed.
"""

from __future__ import annotations

from lmpromp_ppl.models.hyper import PROPER, SIMULATION, THESIS, Hyperparameters, preset
from lmpromp_ppl.models.lmpromp import lmpromp_model
from lmpromp_ppl.models.mixture import mixture_model
from lmpromp_ppl.models.promp import promp_model
from lmpromp_ppl.models.collapsed import (
    lmpromp_collapsed_model,
    mixture_collapsed_model,
    promp_collapsed_model,
)
from lmpromp_ppl.models.conditionals import sample_h_given_theta, sample_w_given_theta
from lmpromp_ppl.models.prior import sample_prior, sample_prior_predictive
from lmpromp_ppl.models.registry import (
    COLLAPSE_CHOICES,
    MODEL_NAMES,
    check_model,
    get_model,
    model_function,
    resolve_collapse,
)

__all__ = [
    "Hyperparameters",
    "THESIS",
    "PROPER",
    "SIMULATION",
    "preset",
    "MODEL_NAMES",
    "COLLAPSE_CHOICES",
    "check_model",
    "resolve_collapse",
    "model_function",
    "get_model",
    "promp_model",
    "lmpromp_model",
    "mixture_model",
    "promp_collapsed_model",
    "lmpromp_collapsed_model",
    "mixture_collapsed_model",
    "sample_w_given_theta",
    "sample_h_given_theta",
    "sample_prior",
    "sample_prior_predictive",
]

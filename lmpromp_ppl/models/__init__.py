"""Model declarations (NumPyro) and hyperparameters.

Every engine runs on these declarations: :func:`get_model` maps the model
names of docs/cli.md (``"promp"``, ``"lmpromp"``, ``"mixture"``)
to the NumPyro model functions, full or collapsed.
"""

from __future__ import annotations

import inspect
from functools import partial
from typing import Callable

from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.models.hyper import PROPER, SIMULATION, THESIS, Hyperparameters, preset
from lmpromp_ppl.models.lmpromp import lmpromp_model
from lmpromp_ppl.models.mixture import mixture_model
from lmpromp_ppl.models.promp import classical_promp, promp_model
from lmpromp_ppl.models.collapsed import (
    lmpromp_collapsed_model,
    mixture_collapsed_model,
    promp_collapsed_model,
    sample_h_given_theta,
    sample_w_given_theta,
)
from lmpromp_ppl.models.prior import sample_prior, sample_prior_predictive

__all__ = [
    "Hyperparameters",
    "THESIS",
    "PROPER",
    "SIMULATION",
    "preset",
    "MODEL_NAMES",
    "get_model",
    "promp_model",
    "lmpromp_model",
    "mixture_model",
    "promp_collapsed_model",
    "lmpromp_collapsed_model",
    "mixture_collapsed_model",
    "classical_promp",
    "sample_w_given_theta",
    "sample_h_given_theta",
    "sample_prior",
    "sample_prior_predictive",
]

MODEL_NAMES = ("promp", "lmpromp", "mixture")
_ALIASES = {"lmpromp_mixture": "mixture"}
_FULL = {"promp": promp_model, "lmpromp": lmpromp_model, "mixture": mixture_model}
_COLLAPSED = {
    "promp": promp_collapsed_model,
    "lmpromp": lmpromp_collapsed_model,
    "mixture": mixture_collapsed_model,
}


def get_model(name: str, collapsed: bool = False, **options) -> Callable[..., None]:
    """The NumPyro model called ``name``, to be called as ``model(data, hyper, ...)``.

    Parameters
    ----------
    name : ``"promp"``, ``"lmpromp"`` or ``"mixture"`` (alias ``"lmpromp_mixture"``)
    collapsed : the variant with ``w`` integrated out (:mod:`lmpromp_ppl.models.collapsed`)
    **options : keyword arguments bound to the model, e.g. ``marginalize=False``
        (full mixture) or ``collapse_h=True`` (collapsed lmpromp / mixture)

    Raises
    ------
    LmprompError
        for an unknown name or option.
    """
    key = _ALIASES.get(name, name)
    if key not in _FULL:
        raise LmprompError(f"unknown model {name!r}; choose from {list(MODEL_NAMES)}")
    model = (_COLLAPSED if collapsed else _FULL)[key]
    accepted = set(inspect.signature(model).parameters) - {"data", "hyper", "observed"}
    unknown = sorted(set(options) - accepted)
    if unknown:
        raise LmprompError(
            f"model {name!r} (collapsed={collapsed}) takes no option {unknown}; it takes {sorted(accepted)}"
        )
    return partial(model, **options) if options else model

"""The one registry of model declarations: names, collapse choices and the NumPyro functions.

Every engine finds its model here.  ``collapsed`` has one spelling per
choice: ``"none"`` (the full model), ``"w"`` (weights integrated out), ``"wh"``
(weights and control variables integrated out), ``"whb"`` (the LMProMP with the
offset ``b`` integrated out as well; not for the mixture, whose offsets are
tied to the summed-out assignments) and ``"auto"`` (the measured reliable
choice for NUTS: ``"wh"`` for the LMProMP and the mixture, ``"w"`` for the
ProMP, which has no ``h``; :mod:`lmpromp_ppl.inference.nuts` gives the
measurements).
"""

from __future__ import annotations

import inspect
from functools import partial
from typing import Callable

import jax
import numpy as np
from numpyro import handlers

from lmpromp_ppl.data.core import (
    DemoStatistics,
    ModelData,
    PhaseData,
    SharedDesign,
    as_float64,
    demo_statistics,
    shared_design,
)
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.models.collapsed import (
    lmpromp_collapsed_model,
    lmpromp_offset_collapsed_model,
    mixture_collapsed_model,
    promp_collapsed_model,
)
from lmpromp_ppl.models.lmpromp import check_observations, lmpromp_model
from lmpromp_ppl.models.mixture import mixture_model
from lmpromp_ppl.models.promp import promp_model

__all__ = [
    "MODEL_NAMES", "COLLAPSE_CHOICES", "check_model", "resolve_collapse", "model_function", "model_inputs", "get_model",
    "site_shapes", "STATISTICS_FORMS",
]

#: The models of docs/cli.md.
MODEL_NAMES = ("promp", "lmpromp", "mixture")
#: The values of ``collapsed``.
COLLAPSE_CHOICES = ("auto", "none", "w", "wh", "whb")

_ALIASES = {"lmpromp_mixture": "mixture"}
_FULL = {"promp": promp_model, "lmpromp": lmpromp_model, "mixture": mixture_model}
_COLLAPSED = {
    "promp": promp_collapsed_model,
    "lmpromp": lmpromp_collapsed_model,
    "mixture": mixture_collapsed_model,
}


def check_model(name: str) -> str:
    """The model's name (aliases resolved); an unknown one is a :class:`LmprompError`."""
    key = _ALIASES.get(name, name)
    if key not in _FULL:
        raise LmprompError(f"unknown model {name!r}; choose from {list(MODEL_NAMES)}")
    return key


def resolve_collapse(model_name: str, collapsed: str) -> str:
    """``collapsed`` resolved for ``model_name``: ``"none"``, ``"w"``, ``"wh"`` or ``"whb"`` (``"auto"`` chosen)."""
    model_name = check_model(model_name)
    if collapsed not in COLLAPSE_CHOICES:
        raise LmprompError(f"collapsed must be one of {list(COLLAPSE_CHOICES)}, got {collapsed!r}")
    if collapsed == "auto":
        return "w" if model_name == "promp" else "wh"
    if collapsed in ("wh", "whb") and model_name == "promp":
        raise LmprompError("the ProMP model has no control variables h; use collapsed='w'")
    if collapsed == "whb" and model_name == "mixture":
        raise LmprompError("the mixture's offsets b_k cannot be integrated out with the assignments; use collapsed='wh'")
    return collapsed


def model_function(model_name: str, collapsed: str) -> Callable[..., None]:
    """The NumPyro model ``model(data, hyper)`` for a model name and collapse choice.

    The full mixture is the one with the assignments summed out (``marginalize=True``);
    the collapsed models are in :mod:`lmpromp_ppl.models.collapsed`.
    """
    model_name = check_model(model_name)
    collapse = resolve_collapse(model_name, collapsed)
    if collapse == "none":
        if model_name == "mixture":
            return partial(mixture_model, marginalize=True)
        return _FULL[model_name]
    if model_name == "promp":
        return promp_collapsed_model
    if collapse == "whb":
        return lmpromp_offset_collapsed_model
    return partial(_COLLAPSED[model_name], collapse_h=collapse == "wh")


def model_inputs(model_name: str, collapsed: str,
                 data: ModelData | PhaseData) -> ModelData | SharedDesign | DemoStatistics:
    """The form of concrete model inputs that the declaration evaluates fastest, as float64.

    The full LMProMP and the collapsed LMProMP and mixture (``"w"``, ``"wh"``) take the
    :class:`~lmpromp_ppl.data.core.SharedDesign` statistics when every
    demonstration has the same fully observed design (O(L d V) per evaluation);
    otherwise the pairs of :data:`STATISTICS_FORMS` take the per-demonstration
    :class:`~lmpromp_ppl.data.core.DemoStatistics` (O(L d^2) memory, built from the compact inputs
    without the dense design), and the rest the dense :class:`~lmpromp_ppl.data.core.ModelData`.
    Every form gives the same log density (``tests/test_data_compact.py``).
    Call it once, outside compiled code (the check looks at the values).
    """
    model_name = check_model(model_name)
    collapse = resolve_collapse(model_name, collapsed)
    data = as_float64(data)
    if (model_name in ("lmpromp", "mixture") and collapse in ("w", "wh")) or (model_name, collapse) == ("lmpromp", "none"):
        shared = shared_design(data)
        if shared is not None:
            return shared
    if (model_name, collapse) in STATISTICS_FORMS:
        check_observations(data)
        return demo_statistics(data)
    return data.dense()


#: (model, collapse) pairs whose declaration evaluates :class:`~lmpromp_ppl.data.core.DemoStatistics`
#: when the demonstrations do not share one design (every observed-data density but the full mixture's and
#: the full ProMP's, whose observation sites need the design).
STATISTICS_FORMS = frozenset({("lmpromp", "none"), ("lmpromp", "w"), ("lmpromp", "wh"), ("lmpromp", "whb"),
                              ("mixture", "w"), ("mixture", "wh"), ("promp", "w")})


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
    key = check_model(name)
    model = (_COLLAPSED if collapsed else _FULL)[key]
    accepted = set(inspect.signature(model).parameters) - {"data", "hyper", "observed"}
    unknown = sorted(set(options) - accepted)
    if unknown:
        raise LmprompError(
            f"model {name!r} (collapsed={collapsed}) takes no option {unknown}; it takes {sorted(accepted)}"
        )
    return partial(model, **options) if options else model


def site_shapes(model: Callable[..., None], *args, deterministic: bool = False) -> dict[str, tuple[int, ...]]:
    """The shape of every latent site of ``model(*args)`` (and of its deterministic sites, on request).

    Traced abstractly (``jax.eval_shape``: nothing evaluated, nothing compiled);
    where tracing fails, the model runs once on the concrete arguments so that
    its own shape and value errors surface with their messages.
    """
    def values(*model_args):
        trace = handlers.trace(handlers.seed(model, 0)).get_trace(*model_args)
        return {n: s["value"] for n, s in trace.items()
                if (s["type"] == "sample" and not s["is_observed"]) or (deterministic and s["type"] == "deterministic")}

    # the array leaves of the arguments enter as abstract values (the rest, e.g. hyperparameters, as they are)
    leaves, treedef = jax.tree.flatten(args)
    is_array = [isinstance(x, (jax.Array, np.ndarray)) for x in leaves]

    def abstract_values(*arrays):
        it = iter(arrays)
        return values(*jax.tree.unflatten(treedef, [next(it) if a else x for x, a in zip(leaves, is_array)]))

    try:
        out = jax.eval_shape(abstract_values, *[x for x, a in zip(leaves, is_array) if a])
    except Exception:  # noqa: BLE001 - run concretely for the model's own message
        out = values(*args)
    return {k: tuple(np.shape(v)) for k, v in out.items()}

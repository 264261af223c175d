"""The one registry of engines: names, which models each runs, and the options each takes.

The API (:func:`lmpromp_ppl.fit`), the CLI, ``compare``, calibration, the
reproduction and the benchmarks read the engine lists and the valid
(model, engine) pairs from here; :func:`check_fit` refuses a bad request with
one clear :class:`~lmpromp_ppl.errors.LmprompError` before any work is done,
and :func:`run_engine` is the one dispatch from an engine's name to its run.
"""

from __future__ import annotations

from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.models.registry import MODEL_NAMES, check_model

__all__ = [
    "ENGINES",
    "SVI_ENGINES",
    "ENGINE_MODELS",
    "ENGINE_OPTIONS",
    "MIXTURE_OPTIONS",
    "check_engine",
    "check_pair",
    "check_fit",
    "engines_for",
    "guide_of",
    "run_engine",
]

#: Every engine, in the order of docs/cli.md.
ENGINES = ("cavi", "cavi_lr", "svi_meanfield", "svi_autonormal", "svi_lowrank", "nuts")
#: The SVI engines (``svi_<guide>``).
SVI_ENGINES = ("svi_meanfield", "svi_autonormal", "svi_lowrank")

#: The models each engine runs.  CAVI's updates are derived for the LMProMP and its
#: mixture; its joint local family and linear response (``cavi_lr``) for the single type;
#: the meanfield guide has the factors of the single-type CAVI family.
ENGINE_MODELS = {
    "cavi": ("lmpromp", "mixture"),
    "cavi_lr": ("lmpromp",),
    "svi_meanfield": ("lmpromp",),
    "svi_autonormal": MODEL_NAMES,
    "svi_lowrank": MODEL_NAMES,
    "nuts": MODEL_NAMES,
}

#: Options each engine accepts through ``fit(..., **options)``.
ENGINE_OPTIONS = {
    "cavi": frozenset({"tol", "max_iter", "num_restarts", "family", "search", "max_moves", "accelerate"}),
    "cavi_lr": frozenset({"tol", "max_iter", "num_restarts", "family", "accelerate", "resample", "refresh"}),
    "nuts": frozenset({"num_chains", "num_warmup", "num_samples", "target_accept", "max_tree_depth",
                       "collapsed", "dense_mass", "init"}),
    "svi": frozenset({"num_steps", "learning_rate", "learning_rate_decay", "num_particles", "rank", "stop_tol",
                      "window", "plateau_reductions", "plateau_factor"}),
}

#: CAVI options of the mixture only: the split-and-merge search (:mod:`lmpromp_ppl.inference.cavi.search`).
MIXTURE_OPTIONS = frozenset({"search", "max_moves"})


def check_engine(engine: str) -> str:
    """The engine's name; an unknown one is a :class:`LmprompError`."""
    if engine not in ENGINES:
        raise LmprompError(f"unknown engine {engine!r}; choose from {', '.join(ENGINES)}")
    return engine


_DISPLAY = {"cavi": "CAVI", "cavi_lr": "CAVI with linear response", "nuts": "NUTS"}


def check_pair(model: str, engine: str) -> None:
    """Refuse a model the engine does not run."""
    model = check_model(model)
    check_engine(engine)
    offered = ENGINE_MODELS[engine]
    if model not in offered:
        plural = "s" if len(offered) > 1 else ""
        raise LmprompError(f"{_DISPLAY.get(engine, engine)} is offered for the {' and '.join(offered)} "
                           f"model{plural}, not for {model}")


def engines_for(model: str) -> tuple[str, ...]:
    """The engines that run ``model``, in the order of :data:`ENGINES`."""
    model = check_model(model)
    return tuple(e for e in ENGINES if model in ENGINE_MODELS[e])


def guide_of(engine: str) -> str:
    """The SVI guide of an ``svi_<guide>`` engine."""
    if engine not in SVI_ENGINES:
        raise LmprompError(f"{engine!r} is not an SVI engine; choose from {', '.join(SVI_ENGINES)}")
    return engine.removeprefix("svi_")


def check_fit(model: str, engine: str, options: dict) -> None:
    """Refuse, before any work, an invalid pair or an option the engine (or model) does not take."""
    check_pair(model, engine)
    allowed = ENGINE_OPTIONS[engine if engine in ENGINE_OPTIONS else engine.split("_")[0]]
    unknown = sorted(set(options) - allowed)
    if unknown:
        raise LmprompError(f"engine {engine} does not take option(s) {', '.join(unknown)}; "
                           f"it takes {', '.join(sorted(allowed))}")
    mixture_only = sorted(set(options) & MIXTURE_OPTIONS)
    if model != "mixture" and mixture_only:
        raise LmprompError(f"option(s) {', '.join(mixture_only)} apply to the mixture model only")
    if "resample" in options:
        from lmpromp_ppl.inference.cavi import RESAMPLE_CHOICES

        if options["resample"] not in RESAMPLE_CHOICES:
            raise LmprompError(f"unknown resample {options['resample']!r}; choose from {list(RESAMPLE_CHOICES)}")
    if "refresh" in options:
        from lmpromp_ppl.inference.refresh import check_refresh

        check_refresh(options["refresh"])
    if "search" in options:
        from lmpromp_ppl.inference.cavi import SEARCHES

        if options["search"] not in SEARCHES:
            raise LmprompError(f"unknown search {options['search']!r}; choose from {list(SEARCHES)}")


def run_engine(engine: str, model: str, data, hyper, key, *, progress=False, **options):
    """Run ``engine`` on ``model`` and prepared model inputs; the engine's own result.

    ``cavi`` -> :class:`~lmpromp_ppl.inference.cavi.CaviFit` (:func:`lmpromp_ppl.inference.cavi.fit`),
    ``cavi_lr`` -> :class:`~lmpromp_ppl.inference.cavi.CaviLrFit` (:func:`lmpromp_ppl.inference.cavi.fit_lr`),
    ``nuts`` -> :class:`~lmpromp_ppl.inference.nuts.NutsResult`,
    ``svi_<guide>`` -> :class:`~lmpromp_ppl.inference.svi.SviResult`.  The pair is
    checked first (:func:`check_pair`); ``options`` go to the engine.
    """
    check_pair(model, engine)
    if engine == "cavi":
        from lmpromp_ppl.inference import cavi

        return cavi.fit(data, hyper, key, mixture=model == "mixture", progress=progress, **options)
    if engine == "cavi_lr":
        from lmpromp_ppl.inference import cavi

        return cavi.fit_lr(data, hyper, key, progress=progress, **options)
    if engine == "nuts":
        from lmpromp_ppl.inference.nuts import fit_nuts

        return fit_nuts(model, data, hyper, key, progress=progress, **options)
    from lmpromp_ppl.inference.svi import fit_svi

    return fit_svi(model, data, hyper, key, guide=guide_of(engine), progress=progress, **options)

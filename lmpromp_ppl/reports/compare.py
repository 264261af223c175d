r"""``compare``: fit one model with several engines and report how far each VI engine is from NUTS.

Every engine runs with one shared :class:`~lmpromp_ppl.models.hyper.Hyperparameters`
(the ``proper`` preset by default), so all of them approximate the same
posterior.  NUTS is the reference.  Before any metric:

1. a common reference frame is built from the NUTS draws
   (:func:`lmpromp_ppl.diagnostics.alignment.build_reference`): mixture
   components are relabelled and ``M`` is Procrustes-aligned;
2. every engine's draws are put in that frame
   (:func:`~lmpromp_ppl.diagnostics.alignment.align_draws`) and reduced to
   identifiable quantities
   (:func:`~lmpromp_ppl.quantities.identifiable_quantities`);
3. each VI engine is compared with NUTS per quantity
   (:mod:`lmpromp_ppl.diagnostics.metrics`), its Pareto k-hat is computed,
   and the reliability of NUTS itself is checked.

Files (docs/cli.md): ``report.md``, ``report.html`` (self-contained),
``metrics.json``, PNG figures, and ``<engine>/posterior.nc`` with
``<engine>/summary.json`` for each engine.  The posterior files are written
like every saved fit (:meth:`lmpromp_ppl.results.FitResult.save`: float64,
zlib-compressed) with the draws thinned to :data:`REPORT_DRAW_BYTES`, so that
a report stays small; the metrics use every draw, and CAVI's file holds the
variational parameters, from which q can be re-sampled.
"""

from __future__ import annotations

import json
import sys
import time
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np

from lmpromp_ppl.errors import ConvergenceWarning, LmprompError
from lmpromp_ppl.inference.registry import ENGINES, SVI_ENGINES, check_pair, engines_for

__all__ = ["QUANTITIES", "EXTRA_QUANTITIES", "DEFAULT_ENGINES", "expand_engines", "compute_metrics", "compare"]

#: Quantities of ``vs_nuts`` in ``metrics.json`` (docs/cli.md).
QUANTITIES = ("b", "alpha", "lam", "gram_eig", "pred_mean", "w")
#: Further identifiable quantities compared in ``vs_nuts_extra``.
EXTRA_QUANTITIES = ("pred_sd", "projector", "M_aligned", "mu_w")
#: Quantities entering the joint distances (the global, low-dimensional ones).
JOINT_QUANTITIES = ("b", "alpha", "lam", "gram_eig", "mu_w")
#: Quantities whose R-hat and ESS judge the reference.
RELIABILITY_QUANTITIES = ("b", "alpha", "lam", "gram_eig", "pred_mean", "pred_sd", "w", "mu_w")
#: Bound (bytes before compression) on the posterior draws each engine's posterior.nc keeps.
REPORT_DRAW_BYTES = 100_000


#: The default engine list of ``compare``: every engine offered for the model.
DEFAULT_ENGINES = "auto"


def expand_engines(engines: str | Sequence[str], model: str) -> list[str]:
    """Engine names from ``"cavi,svi,nuts"``: ``svi`` means every SVI guide offered for ``model``;
    ``auto`` (:data:`DEFAULT_ENGINES`) every engine offered for ``model`` (``cavi_lr`` for the LMProMP).

    NUTS is required (it is the reference) and put first; duplicates are dropped.
    """
    if isinstance(engines, str) and engines.strip() == "auto":
        engines = list(engines_for(model))
    items = [e.strip() for e in (engines.split(",") if isinstance(engines, str) else engines)]
    items = [e for e in items if e]
    out: list[str] = []
    for e in items:
        if e == "svi":
            out += [s for s in SVI_ENGINES if s in engines_for(model)]
        elif e in ENGINES:
            out.append(e)
        else:
            raise LmprompError(f"unknown engine {e!r}; choose from svi, {', '.join(ENGINES)}")
    if "nuts" not in out:
        raise LmprompError("--engines must include nuts: it is the reference the other engines are compared with")
    for e in out:
        check_pair(model, e)
    if len(out) < 2:
        raise LmprompError("--engines needs at least one engine besides nuts to compare")
    unique = list(dict.fromkeys(out))
    return ["nuts"] + [e for e in unique if e != "nuts"]


def _merge(x: np.ndarray) -> np.ndarray:
    """(chain, draw, ...) -> (chain * draw, ...)."""
    x = np.asarray(x)
    return x.reshape((-1,) + x.shape[2:])


def _engine_quantities(result, reference, rank, num_draws, key):
    from lmpromp_ppl.diagnostics.alignment import align_draws
    from lmpromp_ppl.quantities import derived_quantities, identifiable_quantities

    draws = result.posterior_draws(num_draws, key)
    derived = derived_quantities(result.model, draws, num_dofs=result.num_dofs, num_basis=result.num_basis,
                                 gamma=result.hyper.gamma, scaling=result.scaling, width=result.width)
    aligned = align_draws(result.model, draws, reference)
    return identifiable_quantities(result.model, aligned, derived, rank=rank), aligned, derived["phase"]


def _importance_programs(results: dict, num_draws: int) -> dict:
    """The SVI engines' importance-ratio programs for the k-hat, compiled side by side (a compare report
    waited for them one after the other): engine name -> (executable, context)."""
    from lmpromp_ppl.inference.compiled import compile_side_by_side

    lowered = {name: r.state.importance_program(num_draws) for name, r in results.items()
               if name.startswith("svi_") and hasattr(r.state, "importance_program")}
    executables = compile_side_by_side([program for program, _ in lowered.values()])
    return {name: (exe, context) for (name, (_, context)), exe in zip(lowered.items(), executables)}


def compute_metrics(results: dict, data, *, num_draws: int = 1000, seed: int = 0) -> tuple[dict, dict]:
    """Metrics of every VI result against the ``"nuts"`` result, and the details the report plots.

    Parameters
    ----------
    results : engine name -> :class:`~lmpromp_ppl.results.FitResult` (must hold ``"nuts"``)
    data : the :class:`~lmpromp_ppl.data.ModelData` the engines were fitted to
    num_draws : draws from each q
    seed : seeds the draws from q, the k-hat particles and the joint distances

    Returns
    -------
    engines : ``{name: {...}}`` as in ``metrics.json`` (docs/cli.md)
    details : per-engine identifiable draws (sample dims merged), per-element
        comparisons, reference reliability and the latent coordinates, for figures
    """
    import jax

    from lmpromp_ppl.diagnostics.alignment import build_reference
    from lmpromp_ppl.diagnostics.metrics import (
        compare_marginals,
        engine_khat,
        reference_marginals,
        joint_divergences,
        reference_reliability,
        summarise_comparison,
    )
    from lmpromp_ppl.quantities import active_rank, gram_eigenvalues

    if "nuts" not in results:
        raise LmprompError("compute_metrics needs a 'nuts' result as the reference")
    nuts = results["nuts"]
    key = jax.random.key(seed)
    reference = build_reference(nuts.model, nuts.posterior_draws())
    rank = active_rank(gram_eigenvalues(nuts.posterior_draws()["M"])) if "M" in nuts.posterior_draws() else None
    quantities, aligned, phase = {}, {}, None
    for i, (name, result) in enumerate(results.items()):
        q, a, phase = _engine_quantities(result, reference, rank, num_draws, jax.random.fold_in(key, i))
        quantities[name], aligned[name] = q, a

    ref_q = quantities["nuts"]
    reliability = reference_reliability({k: v for k, v in ref_q.items() if k in RELIABILITY_QUANTITIES},
                                        nuts.summary.get("divergences"))
    engines = {"nuts": {
        "seconds": nuts.summary.get("seconds"),
        "compile_seconds": nuts.summary.get("compile_seconds"),
        **{k: reliability[k] for k in ("rhat_max", "ess_bulk_min", "ess_tail_min", "divergences")},
        "reliability_problems": reliability["problems"],
    }}
    comparisons = {}
    ref_flat = {k: _merge(v) for k, v in ref_q.items()}
    programs = _importance_programs(results, num_draws)
    # the reference's marginals sorted once, for every engine
    ref_columns = {k: v.reshape(v.shape[0], -1) for k, v in ref_flat.items()}
    ref_marginals = {k: reference_marginals(v) for k, v in ref_columns.items()}
    for i, (name, result) in enumerate(results.items()):
        if name == "nuts":
            continue
        q_flat = {k: _merge(v) for k, v in quantities[name].items()}
        comp = {k: compare_marginals(q_flat[k].reshape(q_flat[k].shape[0], -1), ref_columns[k],
                                     reference=ref_marginals[k])
                for k in ref_flat if k in q_flat}
        comparisons[name] = comp
        khat = engine_khat(result, data, jax.random.fold_in(key, 1000 + i), num_draws, programs.get(name))
        engines[name] = {
            "seconds": result.summary.get("seconds"),
            "compile_seconds": result.summary.get("compile_seconds"),
            "elbo": result.summary.get("elbo"),
            "iterations": result.summary.get("iterations"),
            "converged": result.summary.get("converged"),
            "psis_khat": khat["psis_khat"],
            "psis_khat_numpyro": khat["psis_khat_numpyro"],
            "psis_khat_note": khat["note"],
            "vs_nuts": {k: summarise_comparison(comp[k]) for k in QUANTITIES if k in comp},
            "vs_nuts_extra": {k: summarise_comparison(comp[k]) for k in EXTRA_QUANTITIES if k in comp},
            "joint": joint_divergences({k: q_flat[k] for k in JOINT_QUANTITIES if k in q_flat},
                                       {k: ref_flat[k] for k in JOINT_QUANTITIES if k in ref_flat}, seed=seed),
        }
    details = {
        "quantities": {n: {k: _merge(v) for k, v in q.items()} for n, q in quantities.items()},
        "aligned": {n: {k: _merge(v) for k, v in a.items()} for n, a in aligned.items()},
        "comparisons": comparisons,
        "reliability": reliability,
        "rank": rank,
        "phase": phase,
    }
    return engines, details


def _options(engine: str, num_chains, num_warmup, num_samples, svi_steps) -> dict:
    if engine == "nuts":
        opts = {"num_chains": num_chains, "num_warmup": num_warmup, "num_samples": num_samples}
    elif engine.startswith("svi_"):
        opts = {"num_steps": svi_steps}
    else:
        opts = {}
    return {k: v for k, v in opts.items() if v is not None}


def compare(
    dataset,
    model: str = "lmpromp",
    engines: str | Sequence[str] = DEFAULT_ENGINES,
    *,
    out_dir: str | Path,
    latent_dim: int | None = None,
    num_components: int | None = None,
    num_basis: int | str | None = None,
    preset_name: str = "proper",
    num_chains: int | None = None,
    num_warmup: int | None = None,
    num_samples: int | None = None,
    svi_steps: int | None = None,
    num_draws: int = 1000,
    seed: int = 0,
    force: bool = False,
    progress: bool = True,
) -> dict:
    """Run ``engines`` on ``dataset`` with one shared set of hyperparameters and write the report.

    Parameters
    ----------
    dataset : a dataset string (``"lasa:GShape?every=20"``, ``"synthetic:latent?L=8"``, a file) or
        :class:`~lmpromp_ppl.data.Demonstrations`
    model : ``"lmpromp"``, ``"mixture"`` or ``"promp"``
    engines : comma-separated names or a list; ``svi`` means every SVI guide; must include ``nuts``;
        ``"auto"`` (default) is every engine offered for ``model``
    out_dir : output directory (refused when it exists and is not empty, unless ``force``)
    latent_dim, num_components : override the preset's V and K
    num_basis : basis functions per DoF (J), or ``"auto"``: chosen once by the
        bound (:func:`lmpromp_ppl.select_num_basis`) and shared by every engine;
        default ``"auto"`` for the mixture, ``DEFAULT_NUM_BASIS`` otherwise (as :func:`lmpromp_ppl.fit`)
    preset_name : hyperparameter preset shared by every engine (default ``proper``)
    num_chains, num_warmup, num_samples : NUTS settings (engine defaults when None)
    svi_steps : maximum SVI steps (engine default when None)
    num_draws : draws compared per VI engine (at most 1000 recommended); the saved
        files keep fewer (:data:`REPORT_DRAW_BYTES`)
    seed : seeds every engine and every diagnostic
    force : overwrite the files of an existing report
    progress : print progress to stderr

    Returns
    -------
    dict
        The content of ``metrics.json``.
    """
    from lmpromp_ppl.api import MODELS, fit, resolve_num_basis, select_num_basis
    from lmpromp_ppl.data import prepare_dataset
    from lmpromp_ppl.outputs import claim_out_dir
    from lmpromp_ppl.models.hyper import preset
    from lmpromp_ppl.reports.report import write_report
    from lmpromp_ppl.results import to_json_value

    if model not in MODELS:
        raise LmprompError(f"unknown model {model!r}; choose from {', '.join(MODELS)}")
    names = expand_engines(engines, model)
    if not (isinstance(num_draws, int) and 100 <= num_draws <= 100_000):
        raise LmprompError(f"num_draws must be an integer in [100, 100000], got {num_draws!r}")
    changes = {}
    if latent_dim is not None:
        changes["latent_dim"] = latent_dim
    if num_components is not None:
        changes["num_components"] = num_components
    hyper = preset(preset_name, **changes)

    def say(msg: str) -> None:
        if progress:
            print(f"lmpromp compare: {msg}", file=sys.stderr, flush=True)

    num_basis = resolve_num_basis(num_basis, model)
    if num_basis == "auto":
        say("choosing the number of basis functions by the bound ...")
        prepared = select_num_basis(dataset, hyper=hyper, seed=seed)["prepared"]
        num_basis = prepared.num_basis
        say(f"J = {num_basis}")
    else:
        prepared = prepare_dataset(dataset, num_basis)  # the one data path: every engine and diagnostic reads it
    spec, raw, mdata = prepared.spec, prepared.raw, prepared.model_data
    hyper.validate_for(mdata.num_weights, mdata.num_demos)
    out = claim_out_dir(Path(out_dir), force)

    results, engine_warnings = {}, {}
    for i, name in enumerate(names):
        say(f"[{i + 1}/{len(names)}] fitting {model} with {name} ...")
        start = time.perf_counter()
        # a convergence warning is part of the comparison: keep it for the report
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", ConvergenceWarning)
            results[name] = fit(prepared, model=model, engine=name, hyper=hyper, seed=seed, progress=progress,
                                **_options(name, num_chains, num_warmup, num_samples, svi_steps))
        engine_warnings[name] = []
        for w in caught:
            if issubclass(w.category, ConvergenceWarning):
                engine_warnings[name].append(str(w.message))
                say(f"warning: {w.message}")
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        say(f"[{i + 1}/{len(names)}] {name} done in {time.perf_counter() - start:.1f} s")
    say("computing diagnostics (alignment, metrics, Pareto k-hat) ...")
    engine_metrics, details = compute_metrics(results, mdata, num_draws=num_draws, seed=seed)
    for name, messages in engine_warnings.items():
        engine_metrics[name]["warnings"] = messages
        # plain-word degeneracy warnings (lmpromp_ppl.diagnostics.degeneracy), convergence said above
        engine_metrics[name]["degeneracy"] = [
            w for w in results[name].summary.get("warnings", []) if not w.startswith("not converged")
        ]
    metrics = to_json_value({
        "dataset": spec,
        "model": model,
        "hyperparameters": hyper.to_dict(),
        "preset": preset_name,
        "num_basis": num_basis,
        "seed": seed,
        "engines": engine_metrics,
    })
    say("writing posteriors, figures and the report ...")
    for name, result in results.items():
        result.save(out / name, force=True, num_draws=num_draws, max_draw_bytes=REPORT_DRAW_BYTES)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, allow_nan=False) + "\n")
    write_report(out, metrics, results, details, raw)
    return metrics  # the caller prints the final line (where the report is)

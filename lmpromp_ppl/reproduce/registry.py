"""The experiment registry: run an experiment and write its JSON, report section and figure."""

from __future__ import annotations

import importlib
import json
import time
from pathlib import Path
from typing import Callable, Sequence

import jax

from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.reproduce._common import Context, ExperimentOutput
from lmpromp_ppl.reproduce.report import write_claims
from lmpromp_ppl.results import to_json_value

__all__ = ["EXPERIMENTS", "experiment_function", "run_experiment", "run_many"]

#: Experiment name -> (module, thesis reference, title), in the order ``all`` runs them.
EXPERIMENTS: dict[str, tuple[str, str, str]] = {
    "priors": ("priors", "Sec. 5.1, Fig. 5.3", "Prior distributions on four clusters"),
    "noise": ("noise", "Sec. 5.2, Fig. 5.5A", "Prediction under observation noise and with few demonstrations"),
    "sparsity": ("sparsity", "Sec. 5.2, Fig. 5.5B", "Prediction from sparse observations"),
    "beta": ("beta", "Sec. 5.3, Fig. 5.6A", "Model complexity over beta"),
    "c0": ("c0", "Sec. 5.3, Fig. 5.6B", "Stability over the hyper-prior c0"),
    "semantics": ("semantics", "Sec. 5.3, Fig. 5.7", "Semantics of the latent dimensions"),
    "latent-analysis": ("latent_analysis", "Sec. 5.3, Fig. 5.8", "Latent coordinates of GunPoint (the golf study)"),
    "bimodal": ("bimodal", "Sec. 5.4, Figs. 5.9, 5.10", "Bimodal movements: ProMP vs mixture"),
}


def experiment_function(name: str) -> Callable[[Context], ExperimentOutput]:
    """The ``run`` function of experiment ``name``."""
    if name not in EXPERIMENTS:
        raise LmprompError(f"unknown experiment {name!r}; choose from {', '.join(EXPERIMENTS)} or all")
    return importlib.import_module(f"lmpromp_ppl.reproduce.{EXPERIMENTS[name][0]}").run


def run_experiment(name: str, context: Context) -> dict:
    """Run experiment ``name`` into ``context.out``; returns the JSON document written to ``NAME.json``.

    The document holds ``experiment``, ``thesis``, ``title``, ``quick``,
    ``seed``, ``seconds``, ``sizes``, ``claims`` (list of dicts), ``figures``
    and ``numbers``.  NaN and inf become ``null`` (:func:`lmpromp_ppl.results.to_json_value`).
    """
    run = experiment_function(name)
    start = time.perf_counter()
    output = run(context)
    seconds = time.perf_counter() - start
    _, thesis, title = EXPERIMENTS[name]
    document = to_json_value({
        "experiment": name,
        "thesis": thesis,
        "title": title,
        "quick": context.quick,
        "seed": context.seed,
        "preset": context.settings.name,
        "num_basis_scale": context.settings.basis_scale,
        "width": context.settings.width,
        "seconds": seconds,
        "jax_backend": jax.default_backend(),
        "sizes": output.sizes,
        "claims": [c.to_dict() for c in output.claims],
        "figures": output.figures,
        "numbers": output.numbers,
    })
    out = Path(context.out)
    (out / f"{name}.json").write_text(json.dumps(document, indent=1, allow_nan=False) + "\n")
    figures = "\n\n".join(f"![{name}]({f})" for f in output.figures[:1])
    (out / f"{name}.md").write_text(
        f"## {title} ({thesis})\n\n{figures}\n\n{output.section}\n\n"
        f"Sizes: `{json.dumps(document['sizes'])}`; {seconds:.0f} s"
        f"{' (quick mode)' if context.quick else ''}.\n"
    )
    return document


def run_many(names: Sequence[str], context: Context, echo: Callable[[str], None] | None = None) -> list[dict]:
    """Run several experiments in order, then rebuild ``claims.md`` and ``report.md``."""
    documents = []
    for name in names:
        if echo is not None:
            echo(f"reproduce {name} ...")
        documents.append(run_experiment(name, context))
        if echo is not None:
            echo(f"  {name}: {documents[-1]['seconds']:.0f} s")
    write_claims(Path(context.out))
    return documents

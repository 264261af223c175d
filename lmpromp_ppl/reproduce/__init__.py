"""Reproductions of the thesis's experiments (Sec. 5) on LASA, GunPoint and synthetic data.

``lmpromp reproduce NAME --out DIR`` runs one experiment (or ``all``); each
writes ``DIR/NAME.json`` (finite numbers, the claims it tests and the sizes
used), ``DIR/NAME.md`` (its report section) and its PNG figure(s), and
``DIR/claims.md`` / ``DIR/report.md`` are rebuilt from every ``*.json`` in DIR.

Experiments (:data:`EXPERIMENTS`): ``priors`` (Fig. 5.3), ``noise`` and
``sparsity`` (Fig. 5.5), ``beta`` (Fig. 5.6A), ``c0`` (Fig. 5.6B),
``semantics`` (Fig. 5.7), ``latent-analysis`` (Fig. 5.8), ``bimodal``
(Figs. 5.9, 5.10).
"""

from lmpromp_ppl.reproduce._common import VERDICTS, Claim, Context, ExperimentOutput
from lmpromp_ppl.reproduce.registry import EXPERIMENTS, run_experiment, run_many
from lmpromp_ppl.reproduce.report import write_claims

__all__ = [
    "EXPERIMENTS",
    "VERDICTS",
    "Claim",
    "Context",
    "ExperimentOutput",
    "run_experiment",
    "run_many",
    "write_claims",
]

"""Engine-comparison reports: ``lmpromp compare`` (docs/cli.md, "Files written").

:func:`compare` fits one model with several engines under one set of
hyperparameters, compares every VI engine with NUTS on identifiable
quantities (:mod:`lmpromp_ppl.diagnostics`) and writes ``report.md``, a
self-contained ``report.html``, PNG figures, ``metrics.json`` and each
engine's ``<engine>/posterior.nc``.
"""

from lmpromp_ppl.reports.compare import QUANTITIES, compare, compute_metrics, expand_engines

__all__ = ["compare", "compute_metrics", "expand_engines", "QUANTITIES"]

r"""Benchmarks: speed and scale of every engine, side by side in one process.

``lmpromp bench --out FILE.json`` (:mod:`lmpromp_ppl.cli.bench`) calls
:func:`run_benchmark`, which fits the same model to the same data with every
engine and writes one JSON document (layout in ``benchmarks/README.md``):

* **CAVI** (:mod:`lmpromp_ppl.inference.cavi`, the single type for K = 1 and
  the mixture when K > 1): compilation time and
  time to convergence separately, iterations, and the cost of one sweep
  measured over a fixed number of sweeps, its floating-point operations
  (XLA's compiled cost analysis) and the achieved rate;
* **SVI** with the ``svi_meanfield`` and ``svi_autonormal`` guides of
  :mod:`lmpromp_ppl.inference.svi`: time and steps until the ELBO gap to the
  CAVI optimum falls below 1 % of :math:`\mathcal L_\text{CAVI} - \mathcal L_\text{init}`
  (:math:`\mathcal L_\text{init}` is the ELBO of CAVI's starting point, the
  thesis initialisation of Sec. 4.1.1, so that both guides chase the same
  absolute target), or the best gap within a stated budget.  The meanfield
  guide is in CAVI's family (thesis eq. 4.3): its parameters are mapped to a
  CAVI state and the closed-form bound is evaluated exactly.  The autonormal
  guide is not (it lives on the model collapsed over ``w``): its ELBO is a
  Monte Carlo estimate, ``-loss`` averaged over many particles, which bounds
  the same evidence :math:`\log p(\mathbf y)` and may therefore exceed the
  CAVI optimum (a negative gap);
* **NUTS** (:func:`lmpromp_ppl.inference.nuts.fit_nuts`, its reliable default
  parametrisation: collapsed over ``w``, non-centred ``M``): wall time, the
  smallest bulk ESS over the identifiable quantities (``b``, ``alpha``, sorted
  ``lam`` and the eigenvalues of :math:`MM^T`) and the time per effective draw;
* **batch fitting**: CAVI vectorised over many datasets with ``jax.vmap``
  (:func:`lmpromp_ppl.inference.cavi.fit_cavi_batched`, initialisation included);
* **ProMP baseline**: the classical ProMP estimate
  (:func:`lmpromp_ppl.inference.classical.classical_promp`) against
  ``movement_primitives``' ``ProMP.imitate`` on LASA (optional ``bench`` extra);
* **goals** (the issue's targets) with the measured figure and whether each is met.

Every engine runs on the same data (standardised synthetic latent-manifold
demonstrations, thesis eq. 4.1) and the same model with the ``proper``
hyperparameter preset (NUTS cannot explore the nearly improper thesis preset).
No number produced here is asserted by a test.
"""

from lmpromp_ppl.bench.config import (
    DEFAULT_ROW,
    GOAL_ROW_NAME,
    SCALING_ROWS,
    BenchConfig,
    NutsSettings,
    RowSpec,
    SviSettings,
    row_hyper,
)
from lmpromp_ppl.bench.data import row_demonstrations, shared_cavi_data
from lmpromp_ppl.bench.engines import bench_batch, bench_cavi, bench_nuts, bench_promp_baseline, bench_svi
from lmpromp_ppl.bench.machine import machine_info, matmul_rate
from lmpromp_ppl.bench.report import evaluate_goals, format_table
from lmpromp_ppl.bench.run import run_benchmark

__all__ = [
    "RowSpec", "SviSettings", "NutsSettings", "BenchConfig", "DEFAULT_ROW", "SCALING_ROWS", "GOAL_ROW_NAME",
    "row_hyper", "row_demonstrations", "shared_cavi_data", "matmul_rate", "machine_info", "bench_cavi",
    "bench_svi", "bench_nuts", "bench_batch", "bench_promp_baseline", "evaluate_goals", "run_benchmark",
    "format_table",
]

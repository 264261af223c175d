"""Calibration at scale: simulation-based calibration (SBC, VSBC) of every engine, and sweeps on Dask.

* :mod:`.sbc`: simulate from the prior, fit, rank identifiable scalars, test uniformity;
* :mod:`.vsbc`: the VSBC symmetry statistic of Yao et al. (2018) and numpyro's ``vsbc_diagnostic``;
* :mod:`.sweep`: grids of CAVI fits scored on held-out demonstrations;
* :mod:`.runner`: tasks through ``dask.distributed``, one result file per task (resumable);
* :mod:`.report`: PIT-ECDF figures, the uniformity table and ``calibration.json``.
"""

from lmpromp_ppl.calibration.runner import TaskRun, run_tasks
from lmpromp_ppl.calibration.sbc import SbcProblem, sbc_tasks, summarize
from lmpromp_ppl.calibration.sweep import sweep_table, sweep_tasks

__all__ = ["SbcProblem", "sbc_tasks", "summarize", "sweep_tasks", "sweep_table", "run_tasks", "TaskRun"]

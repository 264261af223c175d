"""Benchmark settings: the rows (problem sizes), the engines' budgets and the run configuration."""

from __future__ import annotations

import sys
from dataclasses import dataclass

from lmpromp_ppl.models.hyper import Hyperparameters, preset

__all__ = [
    "RowSpec", "SviSettings", "NutsSettings", "BenchConfig", "DEFAULT_ROW", "SCALING_ROWS", "GOAL_ROW_NAME",
    "row_hyper", "log",
]

GOAL_ROW_NAME = "L1000_d420_V10"


# --------------------------------------------------------------------------- settings
@dataclass(frozen=True)
class RowSpec:
    """One problem of the benchmark table.

    Attributes
    ----------
    name : row name (``default`` for the default problem)
    L, D, J, V, K : demonstrations, DoF, basis functions per DoF, latent dimension, components
    T : samples per demonstration
    seed : seed of the synthetic data
    engines : engines run besides CAVI (a subset of ``svi_meanfield``,
        ``svi_autonormal``, ``nuts``); the others are reported as not run
    """

    name: str
    L: int
    D: int
    J: int
    V: int
    K: int = 1
    T: int = 50
    seed: int = 0
    engines: tuple[str, ...] = ()

    @property
    def d(self) -> int:
        """Weight dimension D * J."""
        return self.D * self.J


@dataclass(frozen=True)
class SviSettings:
    """Budget and settings of the SVI rows.

    Attributes
    ----------
    learning_rate : Adam step size (``fit_svi``'s default)
    check_every : steps between two ELBO evaluations (the resolution of ``steps``)
    max_steps : step budget
    budget_s : optimisation-time budget in seconds (ELBO evaluations not counted)
    mc_particles : particles of the Monte Carlo ELBO of the autonormal guide
    relative_gap : the target, a fraction of ELBO_CAVI - ELBO_init
    """

    learning_rate: float = 0.01
    check_every: int = 100
    max_steps: int = 20000
    budget_s: float = 20.0
    mc_particles: int = 1000
    relative_gap: float = 0.01


@dataclass(frozen=True)
class NutsSettings:
    """Chains, warm-up and draws of the NUTS rows (``fit_nuts``'s defaults)."""

    num_chains: int = 2
    num_warmup: int = 500
    num_samples: int = 500


@dataclass(frozen=True)
class BenchConfig:
    """Everything :func:`run_benchmark` needs.

    Attributes
    ----------
    rows : problems to run
    tol, max_iter : CAVI stopping rule (relative ELBO change) and sweep limit
    timing_sweeps : sweeps of the fixed-length run that measures the cost of one sweep
    cavi_budget_s : when ``max_iter`` sweeps would take longer than this, the CAVI fit
        runs in chunks and stops at this time (reported as ``stopped: "time budget"``)
    repeats : repetitions of each timed CAVI run (the minimum is reported)
    svi, nuts : engine settings
    batch_size : datasets of the batch row (0 skips it)
    batch_row : problem of the batch row
    baseline_dataset : dataset of the ProMP baseline ("" skips it)
    baseline_num_basis : basis functions per DoF of both ProMP fits
    matmul_size : size n of the n x n float64 matrix product that measures the machine's rate
    seed : seed of every PRNG key
    progress : print one line per finished engine to stderr
    """

    rows: tuple[RowSpec, ...]
    tol: float = 1e-8
    max_iter: int = 2000
    timing_sweeps: int = 50
    repeats: int = 3
    cavi_budget_s: float = 60.0
    svi: SviSettings = SviSettings()
    nuts: NutsSettings = NutsSettings()
    batch_size: int = 1000
    batch_row: RowSpec | None = None
    baseline_dataset: str = "lasa:GShape"
    baseline_num_basis: int = 10
    matmul_size: int = 2000
    seed: int = 0
    progress: bool = True


_ALL = ("svi_meanfield", "svi_autonormal", "nuts")
_SVI_ONLY = ("svi_meanfield", "svi_autonormal")

#: The default problem of the issue: every engine.
DEFAULT_ROW = RowSpec("default", L=20, D=2, J=10, V=3, engines=_ALL)

#: Scaling rows: L in {10, 100, 1000, 10000}, d = D*J in {120, 420}, V in {2, 10}, K = 3,
#: and the goal problem L = 1000, d = 420, V = 10.  NUTS runs on the default row only
#: (it needs minutes there); SVI on the default row and L = 100, each guide within
#: its budget (:class:`SviSettings`).
SCALING_ROWS = (
    RowSpec("L10", L=10, D=2, J=10, V=3),
    RowSpec("L100", L=100, D=2, J=10, V=3, engines=_SVI_ONLY),
    RowSpec("L1000", L=1000, D=2, J=10, V=3),
    RowSpec("L10000", L=10000, D=2, J=10, V=3),
    RowSpec("d120", L=20, D=6, J=20, V=3),
    RowSpec("d420", L=20, D=7, J=60, V=3, T=120),
    RowSpec("V2", L=20, D=2, J=10, V=2),
    RowSpec("V10", L=20, D=2, J=10, V=10),
    RowSpec("K3", L=21, D=2, J=10, V=3, K=3),
    RowSpec(GOAL_ROW_NAME, L=1000, D=7, J=60, V=10, T=120),
)


def row_hyper(row: RowSpec) -> Hyperparameters:
    """The row's hyperparameters: the ``proper`` preset with a fixed beta (the batched CAVI and the
    committed figures use the thesis's fixed noise)."""
    return preset("proper", latent_dim=row.V, num_components=row.K, learn_beta=False)


def log(config: BenchConfig, message: str) -> None:
    """One progress line on stderr when the run shows progress (``--quiet`` silences it)."""
    if config.progress:
        print(f"bench: {message}", file=sys.stderr, flush=True)

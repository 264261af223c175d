"""Shared machinery of the reproduction experiments (thesis Sec. 5).

Every experiment is a function ``run(context) -> ExperimentOutput``; the
registry (:mod:`lmpromp_ppl.reproduce`) writes its numbers (``NAME.json``), its
figure (``NAME.png``, drawn by the experiment into ``context.out``) and its
report section (``NAME.md``), and rebuilds ``claims.md`` from every JSON in the
output directory.

Fits go straight to the CAVI engine with one iteration budget
(:data:`MAX_ITER`) and ``shared_psi=False`` everywhere, so that every fit of
the same (L, S, d, V, K) shares one compiled loop whatever the hyperparameters,
noise level or observation mask (sparser observations are masked entries, not
a new shape).
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import jax
import numpy as np

from lmpromp_ppl._progress import show_progress_bars
from lmpromp_ppl.data.core import Demonstrations, ModelData, PhaseData, Scaling
from lmpromp_ppl.data.prepared import prepare_dataset
from lmpromp_ppl.errors import ConvergenceWarning, EngineDivergedError, LmprompError
from lmpromp_ppl.basis import DEFAULT_NUM_BASIS, DEFAULT_WIDTH, THESIS_WIDTH
from lmpromp_ppl.models.hyper import DEFAULT, THESIS, Hyperparameters

__all__ = [
    "MAX_ITER",
    "TOL",
    "VERDICTS",
    "SETTINGS",
    "Settings",
    "Context",
    "Claim",
    "ExperimentOutput",
    "FitOutcome",
    "fit_lmpromp",
    "fit_mixture",
    "fit_promp",
    "mean_se",
    "format_mean_se",
    "standardised_model_data",
    "time_mask",
    "progress_bar",
    "matplotlib_figure",
    "save_figure",
]

#: CAVI sweeps per fit (one value everywhere so that compiled loops are shared).
MAX_ITER = 1000
#: Relative ELBO change at which CAVI stops.
TOL = 1e-6
#: The verdicts of ``claims.md``.
VERDICTS = ("holds", "holds partly", "does not hold")


@dataclass(frozen=True)
class Settings:
    """The hyperparameters and basis that a reproduction runs with.

    Attributes
    ----------
    name : ``"thesis"`` (the thesis's values, J = 10 and width 2, as its
        experiments used) or ``"default"`` (the library's defaults,
        docs/defaults.md: learned ``beta``, twice the basis functions, width 1)
    hyper : the hyperparameters every experiment starts from (it changes
        only the ones it studies, e.g. ``beta`` or ``c0``)
    width : basis width
    basis_scale : factor on each experiment's thesis-sized J
    """

    name: str
    hyper: Hyperparameters
    width: float
    basis_scale: int

    def num_basis(self, thesis_num_basis: int) -> int:
        """J for an experiment that uses ``thesis_num_basis`` under the thesis's settings."""
        return self.basis_scale * int(thesis_num_basis)


#: ``lmpromp reproduce --preset``: the thesis's settings, or the library's defaults.
SETTINGS = {
    "thesis": Settings("thesis", THESIS, THESIS_WIDTH, 1),
    "default": Settings("default", DEFAULT, DEFAULT_WIDTH, DEFAULT_NUM_BASIS // 10),
}


@dataclass(frozen=True)
class Context:
    """How an experiment runs.

    Attributes
    ----------
    out : output directory (exists)
    quick : tiny sizes for the test suite (a few seconds per experiment)
    seed : seeds every random choice
    progress : show progress bars
    settings : hyperparameters and basis (:data:`SETTINGS`; the thesis's by default)
    """

    out: Path
    quick: bool = False
    seed: int = 0
    progress: bool = True
    settings: Settings = SETTINGS["thesis"]


@dataclass(frozen=True)
class Claim:
    """One claim of the thesis and what the reproduction measured.

    Attributes
    ----------
    claim : the claim, in a sentence
    thesis : where the thesis makes it (section, figure)
    measured : what we measured (numbers with uncertainty)
    verdict : one of :data:`VERDICTS`
    """

    claim: str
    thesis: str
    measured: str
    verdict: str

    def __post_init__(self):
        if self.verdict not in VERDICTS:
            raise LmprompError(f"verdict must be one of {VERDICTS}, got {self.verdict!r}")

    def to_dict(self) -> dict:
        return {"claim": self.claim, "thesis": self.thesis, "measured": self.measured, "verdict": self.verdict}


@dataclass
class ExperimentOutput:
    """What an experiment hands back to the registry.

    Attributes
    ----------
    numbers : nested dict of the measured numbers (JSON-able after
        :func:`lmpromp_ppl.results.to_json_value`)
    section : markdown report section (without the figure link; the registry adds it)
    claims : the thesis claims this experiment tests
    sizes : the sizes used (dataset subsets, folds), stated in claims.md
    figures : file names (relative to the output directory) of the figures drawn
    """

    numbers: dict
    section: str
    claims: list[Claim]
    sizes: dict
    figures: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class FitOutcome:
    """Point estimates of a fit and whether it went well.

    Attributes
    ----------
    params : posterior means with the site names of docs/cli.md
    converged : CAVI met the tolerance within :data:`MAX_ITER` sweeps (True for the ProMP)
    finite : every parameter and the ELBO are finite (False when CAVI diverged)
    state : the engine's state (None for the ProMP)
    """

    params: dict
    converged: bool
    finite: bool
    state: object = None


def _finite(params: dict) -> bool:
    return all(bool(np.all(np.isfinite(np.asarray(v)))) for v in params.values())


def _cavi(data: ModelData, hyper: Hyperparameters, seed: int, restarts: int, mixture: bool) -> FitOutcome:
    from lmpromp_ppl.inference import cavi
    from lmpromp_ppl.inference.registry import run_engine

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        try:
            result = run_engine(
                "cavi", "mixture" if mixture else "lmpromp", data, hyper, jax.random.key(seed), tol=TOL,
                max_iter=MAX_ITER, num_restarts=restarts, shared_psi=False,
            )
        except EngineDivergedError:
            return FitOutcome({}, False, False)
    params = {k: np.asarray(v) for k, v in cavi.point_estimate(result.state).items()}
    finite = _finite(params) and math.isfinite(result.elbo)
    return FitOutcome(params, bool(result.converged), finite, result.state)


def fit_lmpromp(data: ModelData, hyper: Hyperparameters, seed: int = 0) -> FitOutcome:
    """Single-type LMProMP by CAVI (Sec. 4.1); a learned beta when ``hyper.learn_beta``."""
    return _cavi(data, hyper.replace(num_components=1), seed, 1, mixture=False)


def fit_mixture(data: ModelData, hyper: Hyperparameters, seed: int = 0, restarts: int = 2) -> FitOutcome:
    """Mixture of LMProMPs by CAVI (Sec. 4.2), k-means initialisation, best of ``restarts``.

    ``params`` holds ``pi`` (K,), ``b`` (K, d), ``M`` (K, d, V), ``alpha`` (K,)
    with removed components at ``pi = 0``.
    """
    return _cavi(data, hyper, seed, restarts, mixture=True)


def fit_promp(data: ModelData) -> FitOutcome:
    """Classical ProMP (Sec. 3.1.1): ridge weights per demonstration, Ledoit-Wolf covariance.

    The shrunk covariance is a stronger baseline than the thesis's sample
    covariance, which is singular when there are fewer demonstrations than weights.
    """
    from lmpromp_ppl.inference.classical import classical_promp

    mu_w, sigma_w, _ = classical_promp(data, ridge=1e-6)
    params = {"mu_w": np.asarray(mu_w), "Sigma_w": np.asarray(sigma_w)}
    return FitOutcome(params, True, _finite(params))


def mean_se(values: Sequence[float]) -> tuple[float, float]:
    """Mean and standard error (sample s.d. / sqrt(n)) of finite values; se 0 for one value."""
    x = np.asarray([v for v in values if v is not None and math.isfinite(v)], dtype=float)
    if x.size == 0:
        return float("nan"), float("nan")
    se = float(x.std(ddof=1) / math.sqrt(x.size)) if x.size > 1 else 0.0
    return float(x.mean()), se


def format_mean_se(values: Sequence[float], digits: int = 3) -> str:
    """``mean ± se`` with ``digits`` significant digits."""
    mean, se = mean_se(values)
    return f"{mean:.{digits}g} ± {se:.2g}"


def time_mask(num_times: int, num_dofs: int, keep: np.ndarray) -> np.ndarray:
    """(T * D,) 0/1 mask in the time-major row order of :mod:`lmpromp_ppl.basis` from a (T,) bool ``keep``."""
    return np.repeat(np.asarray(keep, dtype=float), num_dofs)


def standardised_model_data(
    demos: Demonstrations, num_basis: int, keep: np.ndarray | None = None, *, width: float
) -> tuple[PhaseData, Scaling, Demonstrations]:
    """Standardise ``demos`` on themselves and build the model inputs with basis width ``width``.

    ``keep`` (T,) bool marks the time samples that are observed (same for every
    demonstration; the others are masked, keeping the array shapes).
    """
    prepared = prepare_dataset(demos, num_basis, width=width)
    data = prepared.model_data
    if keep is not None:
        row = time_mask(demos.lengths[0], demos.num_dofs, keep)
        data = data._replace(observed=data.observed * row.reshape(data.observed.shape[1:])[None])
    return data, prepared.scaling, prepared.scaled


class progress_bar:
    """A tqdm bar when ``enabled`` and stderr is a terminal, a no-op otherwise
    (``with progress_bar(n, desc, on) as bar: bar.update()``)."""

    def __init__(self, total: int, description: str, enabled: bool):
        self._bar = None
        if show_progress_bars(enabled):
            from tqdm.auto import tqdm

            self._bar = tqdm(total=total, desc=description, leave=False)
        self._start = time.perf_counter()

    def __enter__(self) -> "progress_bar":
        return self

    def update(self, n: int = 1) -> None:
        if self._bar is not None:
            self._bar.update(n)

    def __exit__(self, *exc) -> None:
        if self._bar is not None:
            self._bar.close()


def matplotlib_figure(nrows: int, ncols: int, size: tuple[float, float]):
    """A new figure (Agg canvas, no pyplot state: the user's backend is left alone) and its axes grid."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size)
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    return fig, axes


def save_figure(fig, path: Path) -> None:
    """Save ``fig`` as PNG."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)


"""lmpromp-ppl: Latent-Manifold Probabilistic Movement Primitives in NumPyro.

Importing the package switches JAX to float64 (:mod:`lmpromp_ppl._config`).

>>> import lmpromp_ppl as lp
>>> result = lp.fit("lasa:GShape?every=20", model="lmpromp", engine="cavi")  # doctest: +SKIP
"""

from lmpromp_ppl import _config  # noqa: F401  (float64, before anything else)
from lmpromp_ppl import data
from lmpromp_ppl.api import ENGINES, MODELS, calibrate_timing, fit, select_num_basis
from lmpromp_ppl.data.prepared import PreparedDataset, prepare_dataset
from lmpromp_ppl.models.hyper import DEFAULT, PROPER, THESIS, Hyperparameters, preset
from lmpromp_ppl.results import FitResult, load

__version__ = "0.1.0"

__all__ = [
    "__version__",
    "data",
    "fit",
    "prepare_dataset",
    "PreparedDataset",
    "select_num_basis",
    "calibrate_timing",
    "load",
    "FitResult",
    "Hyperparameters",
    "THESIS",
    "DEFAULT",
    "PROPER",
    "preset",
    "MODELS",
    "ENGINES",
]

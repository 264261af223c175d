"""lmpromp-ppl: Latent-Manifold Probabilistic Movement Primitives in NumPyro.

Importing the package switches JAX to float64 (:mod:`lmpromp_ppl._config`).
"""

from lmpromp_ppl import _config  # noqa: F401  (float64, before anything else)

__version__ = "0.1.0"

__all__ = ["__version__"]

"""Model declarations (NumPyro) and hyperparameters."""

from lmpromp_ppl.models.hyper import PROPER, THESIS, Hyperparameters, preset

__all__ = ["Hyperparameters", "THESIS", "PROPER", "preset"]

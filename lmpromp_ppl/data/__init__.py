"""Demonstration data: the :class:`Demonstrations` type, loaders and files."""

from lmpromp_ppl.data.core import Demonstrations, ModelData, Scaling, model_data, standardize

__all__ = ["Demonstrations", "ModelData", "Scaling", "model_data", "standardize"]

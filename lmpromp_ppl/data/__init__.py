"""Demonstration data: the :class:`Demonstrations` type, loaders and files."""

from lmpromp_ppl.data.core import (
    DemoStatistics,
    Demonstrations,
    ModelData,
    PhaseData,
    Scaling,
    SharedDesign,
    as_float64,
    model_data,
    demo_statistics,
    shared_design,
    standardise,
)
from lmpromp_ppl.data.files import load_csv, load_npz, save_csv, save_npz
from lmpromp_ppl.data.lasa import lasa_shapes, load_lasa
from lmpromp_ppl.data.prepared import PreparedDataset, load_demonstrations, prepare_dataset
from lmpromp_ppl.data.registry import list_datasets, load_dataset
from lmpromp_ppl.data.synthetic import (
    count_collisions,
    four_clusters,
    latent_manifold,
    obstacle_reaching,
)
from lmpromp_ppl.data.ucr import load_gunpoint, load_ts, read_ts

__all__ = [
    "Demonstrations",
    "ModelData",
    "PhaseData",
    "SharedDesign",
    "shared_design",
    "DemoStatistics",
    "demo_statistics",
    "as_float64",
    "Scaling",
    "model_data",
    "standardise",
    "PreparedDataset",
    "prepare_dataset",
    "load_demonstrations",
    "load_dataset",
    "list_datasets",
    "load_npz",
    "save_npz",
    "load_csv",
    "save_csv",
    "load_lasa",
    "lasa_shapes",
    "load_gunpoint",
    "load_ts",
    "read_ts",
    "latent_manifold",
    "four_clusters",
    "obstacle_reaching",
    "count_collisions",
]

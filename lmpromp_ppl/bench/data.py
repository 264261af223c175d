"""The benchmark's demonstrations (synthetic latent-manifold data, thesis eq. 4.1) and their CAVI statistics.

:func:`shared_cavi_data` gives CAVI's statistics of rows whose demonstrations share one
time grid through the one data path (:func:`lmpromp_ppl.data.core.model_data`, compact
inputs), with the shared-design fast path required.
"""

from __future__ import annotations

import numpy as np

from lmpromp_ppl.basis import DEFAULT_WIDTH
from lmpromp_ppl.bench.config import RowSpec
from lmpromp_ppl.data.core import Demonstrations, model_data, standardise
from lmpromp_ppl.data.synthetic import latent_manifold
from lmpromp_ppl.errors import DataError
from lmpromp_ppl.inference import cavi

__all__ = ["row_demonstrations", "shared_cavi_data"]


def row_demonstrations(row: RowSpec) -> Demonstrations:
    """Standardised synthetic latent-manifold demonstrations for a row (thesis eq. 4.1).

    For K > 1 the demonstrations of K latent-manifold models (seeds
    ``seed, seed + 1, ...``, each with its own offset and projection) are
    concatenated, about L / K each, so that the mixture has K true types.
    """
    if row.K == 1:
        demos = latent_manifold(L=row.L, D=row.D, J=row.J, V=row.V, T=row.T, seed=row.seed)
    else:
        sizes = [row.L // row.K + (k < row.L % row.K) for k in range(row.K)]
        parts = [
            latent_manifold(L=n, D=row.D, J=row.J, V=row.V, T=row.T, seed=row.seed + k)
            for k, n in enumerate(sizes)
        ]
        demos = Demonstrations(
            times=tuple(t for p in parts for t in p.times),
            positions=tuple(y for p in parts for y in p.positions),
            name=f"synthetic:latent mixture of {row.K} (seeds {row.seed}..{row.seed + row.K - 1})",
        )
    return standardise(demos)[0]


def shared_cavi_data(demos: Demonstrations, num_basis: int, width: float = DEFAULT_WIDTH) -> cavi.CaviData:
    """CAVI statistics of demonstrations that share one time grid (the shared-design fast path).

    :func:`lmpromp_ppl.inference.cavi.sufficient_statistics` of the one data path's
    compact inputs (:func:`~lmpromp_ppl.data.core.model_data`), which never build the
    dense (L, S, d) design array (2.8 GB for L = 1000, S = 840, d = 420).

    Raises
    ------
    DataError
        when the demonstrations do not share one time grid
    """
    phases = demos.phases()
    first = phases[0]
    if any(p.shape != first.shape or not np.array_equal(p, first) for p in phases):
        raise DataError("shared_cavi_data needs demonstrations that share one time grid")
    return cavi.sufficient_statistics(model_data(demos, num_basis, width), shared_psi=True)

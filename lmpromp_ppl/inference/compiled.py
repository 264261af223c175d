"""The one ahead-of-time compile cache of the engines.

``jax.jit`` caches traces too, but a user waits for compilation, so the
engines compile explicitly (``lower(...).compile()``) to report compilation
time apart from fitting time.  :func:`compiled` keys an executable by the
function, the argument tree, the shapes and dtypes of its leaves and the static
arguments (the CAVI loop, its batched and split-and-merge variants);
:func:`lookup` and :func:`remember` hold the programs NUTS and SVI build per
configuration, in the same cache.

Every compiled program keeps its machine code in memory mappings of the
process (the CAVI loop about 800 of them), and Linux refuses a process more
than ``vm.max_map_count`` (65530 by default): past that, the next compilation
crashes the interpreter.  Before each compilation :func:`compiled` therefore
checks how many mappings the process holds and, above :data:`MAP_FRACTION` of
the limit, forgets every program (this cache and JAX's), which releases them.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["compiled", "compile_side_by_side", "compile_in_background", "lookup", "remember", "clear", "release_if_needed", "MAP_FRACTION"]

_CACHE: dict = {}
_BACKGROUND: ThreadPoolExecutor | None = None

#: Fraction of ``vm.max_map_count`` above which :func:`release_if_needed` forgets every compiled program.
MAP_FRACTION = 0.6


def _map_counts() -> tuple[int, int] | None:
    """(memory mappings of this process, the system's limit), or None where /proc does not tell."""
    try:
        with open("/proc/sys/vm/max_map_count") as f:
            limit = int(f.read())
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f), limit
    except (OSError, ValueError):
        return None


def release_if_needed() -> bool:
    """Forget every compiled program (this cache and JAX's) when the process nears its limit of memory mappings.

    Returns whether it did.  The programs are compiled again when next needed.
    """
    counts = _map_counts()
    if counts is None or counts[0] < MAP_FRACTION * counts[1]:
        return False
    clear()
    jax.clear_caches()
    return True


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
    release_if_needed()
    start = time.perf_counter()
    executable = function.lower(*args, **static).compile()
    seconds = time.perf_counter() - start
    _CACHE[key] = executable
    return executable, seconds


def compile_side_by_side(lowered: Sequence[Any], workers: int | None = None) -> list:
    """Compile lowered programs (``jax.stages.Lowered``) in threads, one per core; the executables in order.

    XLA releases Python's global lock while it compiles, so independent programs
    compile side by side (lowering, which traces Python and, for NumPyro models, a
    global handler stack, stays in the caller's thread).
    """
    lowered = list(lowered)
    if not lowered:
        return []
    release_if_needed()
    workers = min(len(lowered), workers or os.cpu_count() or 1)
    if workers == 1:
        return [program.compile() for program in lowered]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(lambda program: program.compile(), lowered))


def compile_in_background(lowered: Any) -> Future:
    """Start compiling a lowered program in a background thread; the ``Future`` of its executable.

    An engine lowers a program it will need after its run (the draws of a fit) and
    compiles it while the run goes on: XLA compiles without Python's global lock.
    One background thread, so programs queue rather than crowd the cores.
    """
    global _BACKGROUND
    if _BACKGROUND is None:
        _BACKGROUND = ThreadPoolExecutor(max_workers=1, thread_name_prefix="lmpromp-compile")
    release_if_needed()
    return _BACKGROUND.submit(lowered.compile)


def lookup(key: tuple):
    """A program an engine stored under ``key`` (None when absent): NUTS's sampler, SVI's chunk."""
    return _CACHE.get(("program", key))


def remember(key: tuple, program) -> None:
    """Store an engine's compiled program (with whatever it needs to run) under ``key``."""
    _CACHE[("program", key)] = program


def clear() -> None:
    """Forget every executable (benchmarks measure compilation from a cold cache)."""
    _CACHE.clear()

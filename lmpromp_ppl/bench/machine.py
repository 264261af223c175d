"""What the machine can do: the matrix-multiply rate (the roofline's peak) and a description."""

from __future__ import annotations

import math
import os
import platform
import time
from typing import Any

import jax
import jax.numpy as jnp

from lmpromp_ppl.results import package_version

__all__ = ["matmul_rate", "machine_info"]


def matmul_rate(n: int = 2000, repeats: int = 5) -> float:
    """Measured float64 rate (FLOP/s) of an n x n matrix product (2 n^3 operations), best of ``repeats``."""
    keys = jax.random.split(jax.random.key(0))
    a = jax.random.normal(keys[0], (n, n), jnp.float64)
    b = jax.random.normal(keys[1], (n, n), jnp.float64)
    product = jax.jit(jnp.matmul)
    jax.block_until_ready(product(a, b))
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(product(a, b))
        best = min(best, time.perf_counter() - start)
    return 2.0 * n**3 / best


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict[str, Any]:
    """CPU, cores, load, jax devices and package versions."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {
        "cpu": _cpu_model(),
        "cores": cores,
        "platform": platform.platform(),
        "load_average_at_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "jax_backend": jax.default_backend(),
        "jax_devices": [str(d) for d in jax.devices()],
        "xla_flags": os.environ.get("XLA_FLAGS"),
        "versions": {
            "python": platform.python_version(),
            **{name: package_version(name) for name in
               ("lmpromp-ppl", "jax", "jaxlib", "numpyro", "numpy", "scikit-learn", "movement_primitives")},
        },
    }

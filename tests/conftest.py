"""Shared test configuration: CPU, float64 (set by importing lmpromp_ppl), headless plots,
and one compilation cache for the whole test session.

Compilation dominates the suite's time, and many tests fit models of the same shapes
through fresh Python closures, which JAX's in-memory caches cannot share.  JAX's
persistent compilation cache, keyed by the compiled program itself, shares them
between tests, between the ``pytest-xdist`` workers and with the CLI and notebook
subprocesses (they inherit the environment); measured on 2 cores it shortens the
default suite by about 8 %.  The cache lives in a fresh temporary folder made by the
controlling process and removed when the session ends, so every session starts cold
and nothing outlives it.

The tests run tiny problems, so compiling costs them far more than running: XLA's CPU
backend compiles with LLVM's optimisation level 0 in the test session (appended to any
``XLA_FLAGS`` of the caller; inherited by the subprocesses).  HLO-level optimisation and
fusion are unchanged, and the programs compute the same operations; measured on 2 cores
the default suite took 609 s of pytest instead of 850-901 s, every test passing.
"""

import os
import shutil
import tempfile

os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("MPLBACKEND", "Agg")
_XLA_FLAGS = os.environ.get("XLA_FLAGS", "")
if "--xla_backend_optimization_level" not in _XLA_FLAGS:
    os.environ["XLA_FLAGS"] = (_XLA_FLAGS + " --xla_backend_optimization_level=0").strip()

_CACHE_ENV = "LMPROMP_TEST_COMPILATION_CACHE"
_owned_cache = None
if _CACHE_ENV not in os.environ:  # the controlling process (or a run without xdist) owns the cache
    _owned_cache = tempfile.mkdtemp(prefix="lmpromp-ppl-test-jax-cache-")
    os.environ[_CACHE_ENV] = _owned_cache
os.environ["JAX_COMPILATION_CACHE_DIR"] = os.environ[_CACHE_ENV]
# programs that compile in under half a second are cheaper to rebuild than to store
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")

import jax  # noqa: E402

jax.config.update("jax_compilation_cache_dir", os.environ[_CACHE_ENV])
jax.config.update("jax_persistent_cache_min_compile_time_secs",
                  float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))

import lmpromp_ppl  # noqa: E402,F401  (switches on float64)


def pytest_unconfigure(config):
    if _owned_cache is not None and not hasattr(config, "workerinput"):
        shutil.rmtree(_owned_cache, ignore_errors=True)

"""Shared test configuration: CPU, float64 (set by importing lmpromp_ppl), headless plots."""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("MPLBACKEND", "Agg")

import lmpromp_ppl  # noqa: E402,F401  (switches on float64)

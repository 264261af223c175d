"""Approximation-quality diagnostics against NUTS."""

"""Inference engines: CAVI (hand-derived, JAX), NUTS and SVI (NumPyro)."""

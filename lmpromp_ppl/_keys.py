"""Random keys derived from a fit's seed, for methods called without a key.

Every random choice of lmpromp-ppl follows from the ``seed`` given to
:func:`lmpromp_ppl.fit` (or ``--seed``).  Draws taken after the fit (from q,
replicated demonstrations, sampled trajectories) use an explicit key when one
is passed, and otherwise :func:`seed_key` of the fit's seed and a fixed
purpose tag, so that two seeds give different draws and one seed the same.
"""

from __future__ import annotations

__all__ = ["DRAWS", "POSTERIOR_PREDICTIVE", "PREDICTION", "seed_key", "raw_key", "typed_key"]

#: Purpose tags folded into the seed's key (distinct, so the streams are independent).
DRAWS = 1
POSTERIOR_PREDICTIVE = 2
PREDICTION = 3


def seed_key(seed: int | None, purpose: int):
    """``fold_in(key(seed), purpose)``; a result without a recorded seed uses seed 0."""
    import jax

    return jax.random.fold_in(jax.random.key(0 if seed is None else int(seed)), purpose)


def raw_key(key):
    """A raw uint32 key from either a typed (``jax.random.key``) or raw key (NumPyro's samplers take raw keys)."""
    import jax
    import jax.numpy as jnp

    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        return jax.random.key_data(key)
    return key


def typed_key(key):
    """A typed key (``jax.random.key``) from either kind; the same random stream as the raw key.

    A compiled function traced with one kind of key compiles again for the other, so the
    samplers shared by several callers (CAVI's draws from q) are called with typed keys.
    """
    import jax
    import jax.numpy as jnp

    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        return key
    return jax.random.wrap_key_data(key)

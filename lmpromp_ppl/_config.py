"""The one place where lmpromp-ppl configures JAX.

All inference in lmpromp-ppl runs in float64: closed-form ELBOs of models with
thousands of observations lose their monotonicity checks in float32. Importing
``lmpromp_ppl`` switches ``jax_enable_x64`` on before any array is created.
"""

import jax

jax.config.update("jax_enable_x64", True)

__all__: list[str] = []

"""Approximation-quality diagnostics against NUTS.

The identifiable quantities they compare (``gram_eig``, predictive moments,
sorted ``lam``, the active projector) are in :mod:`lmpromp_ppl.quantities`, a
layer below (results store them).

* :mod:`~lmpromp_ppl.diagnostics.alignment`: Procrustes alignment of ``M``
  and ``h`` and relabelling of mixture components;
* :mod:`~lmpromp_ppl.diagnostics.metrics`: marginal metrics (standardised
  mean difference, sd ratio, Wasserstein, coverage), joint distances, the
  Pareto k-hat and the reliability of the NUTS reference.
"""

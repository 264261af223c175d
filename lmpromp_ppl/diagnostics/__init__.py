"""Approximation-quality diagnostics against NUTS.

* :mod:`~lmpromp_ppl.diagnostics.quantities`: identifiable quantities
  (``gram_eig``, predictive moments, sorted ``lam``, the active projector);
* :mod:`~lmpromp_ppl.diagnostics.alignment`: Procrustes alignment of ``M``
  and ``h`` and relabelling of mixture components;
* :mod:`~lmpromp_ppl.diagnostics.metrics`: marginal metrics (standardised
  mean difference, sd ratio, Wasserstein, coverage), joint distances, the
  Pareto k-hat and the reliability of the NUTS reference.

Submodules are imported on use (``lmpromp_ppl.results`` imports
``quantities`` while the package initialises).
"""

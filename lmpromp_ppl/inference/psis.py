r"""Pareto-smoothed importance sampling of log importance ratios (arviz-stats), for every engine.

:func:`psis` is the one place where ratios :math:`\log p(\theta, y) - \log q(\theta)` of
independent draws from q are smoothed and their Pareto :math:`\hat k` is fitted
(Vehtari et al. 2024; Yao et al. 2018 for VI): the diagnostics report the k-hat
(:func:`lmpromp_ppl.diagnostics.metrics.pareto_khat`) and ``cavi_lr`` resamples its
draws by the smoothed weights when :math:`\hat k` < :data:`KHAT_RESAMPLE`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["psis", "KHAT_RESAMPLE"]

#: Below this k-hat the smoothed importance weights are reliable (Vehtari et al.'s threshold for S >= 2200).
KHAT_RESAMPLE = 0.7


def psis(log_ratio: np.ndarray) -> tuple[np.ndarray | None, float | None, str]:
    r"""Smoothed normalised log weights, the Pareto :math:`\hat k`, and a note, of S log importance ratios.

    ``arviz_stats``' ``psislw`` smooths the weights :math:`e^{-x}` (the LOO convention,
    where x is a log-likelihood), so the negated log ratio is passed.  Draws are
    independent, so ``r_eff = 1``.  When q equals p up to a constant every ratio is the
    same and no tail can be fitted: the weights are then uniform, ``khat`` is ``None``
    and the note says that the importance weights are constant (the ideal case).  A NaN
    or +inf ratio gives ``(None, None, note)``.
    """
    from arviz_stats.base import array_stats

    log_ratio = np.asarray(log_ratio, dtype=float).ravel()
    if log_ratio.size < 25:
        raise ValueError(f"need at least 25 draws for a Pareto k-hat, got {log_ratio.size}")
    finite = np.isfinite(log_ratio)
    if np.any(np.isnan(log_ratio)) or np.any(log_ratio == np.inf):
        return None, None, "some log importance ratios are NaN or +inf (q puts mass where p is undefined)"
    if not np.all(finite):  # -inf: p(theta, y) = 0 at a draw of q; weight 0
        log_ratio = np.where(finite, log_ratio, np.min(log_ratio[finite]) - 1e3)
    try:
        log_weights, khat = array_stats.psislw(-log_ratio, r_eff=1.0)
    except ValueError as exc:
        if "All tail values are the same" in str(exc):
            uniform = np.full(log_ratio.shape, -np.log(log_ratio.size))
            return uniform, None, "importance ratios are constant: q equals the posterior up to its normaliser"
        raise
    khat = float(khat)
    if not np.isfinite(khat):
        return None, None, "the generalized Pareto fit did not converge"
    log_weights = np.asarray(log_weights, dtype=float)
    log_weights = log_weights - np.logaddexp.reduce(log_weights)
    return log_weights, khat, ""

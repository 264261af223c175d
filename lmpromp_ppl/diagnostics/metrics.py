r"""Metrics of an approximation q against a reference (NUTS) posterior.

Every metric here compares *marginals*: both draw sets are flattened to
``(num_draws, num_elements)`` (sample dims first) and each element (a scalar
quantity such as ``b[3]`` or ``pred_mean[phase=10, dof=0]``) is compared on its
own.  The reference (NUTS) standard deviation is the unit:

* standardised mean difference :math:`(\bar\theta_q - \bar\theta_p) / s_p`;
* standard-deviation ratio :math:`s_q / s_p` (below 1: q under-disperses,
  the usual failure of mean-field VI);
* one-dimensional Wasserstein-1 distance :math:`W_1(q, p) / s_p`
  (:func:`wasserstein_marginals`: every marginal at once, equal to
  :func:`scipy.stats.wasserstein_distance` per marginal, which the tests check;
  ``arviz_stats`` only returns the sum over marginals);
* coverage: the fraction of reference draws inside q's central 90 %
  interval (0.9 when q and p agree; lower when q is too narrow or shifted).

:func:`joint_divergences` adds the joint Wasserstein distance and the
Kullback-Leibler estimate of ``arviz_stats`` on reference-standardised draws.

:func:`pareto_khat` is the PSIS diagnostic of Yao et al. (2018): the shape
:math:`\hat k` of a generalized Pareto distribution fitted to the upper tail
of the importance ratios :math:`r_s = p(\theta_s, y) / q(\theta_s)`,
:math:`\theta_s \sim q`.  :math:`\hat k < 0.5`: q is good; 0.5 to 0.7: usable;
above 0.7: importance sampling, and so the approximation, is unreliable.

:func:`reference_reliability` gives the reliability of the NUTS reference
itself: rank-normalised split R-hat, bulk and tail ESS (``arviz_stats``) and
the number of divergent transitions.

References
----------
Yao, Y., Vehtari, A., Simpson, D. and Gelman, A. (2018). Yes, but did it work?:
Evaluating variational inference. ICML.
Vehtari, A., Gelman, A., Simpson, D., Carpenter, B. and Bürkner, P.-C. (2021).
Rank-normalization, folding, and localization: an improved R-hat. Bayesian Analysis.
"""

from __future__ import annotations

import warnings
from typing import Mapping, NamedTuple

import numpy as np
import xarray as xr

__all__ = [
    "MarginalComparison",
    "KHAT_GOOD",
    "KHAT_USABLE",
    "flatten_draws",
    "compare_marginals",
    "ReferenceMarginals",
    "reference_marginals",
    "wasserstein_marginals",
    "summarise_comparison",
    "joint_divergences",
    "pareto_khat",
    "khat_verdict",
    "reference_reliability",
    "quantity_reliability",
    "RHAT_MAX",
    "ESS_MIN",
    "model_log_joint",
    "engine_khat",
]

#: k-hat below this: the approximation is good (Yao et al. 2018).
KHAT_GOOD = 0.5
#: k-hat below this (and above :data:`KHAT_GOOD`): usable; above: unreliable.
KHAT_USABLE = 0.7
#: The reference is reliable when every R-hat is at most this ...
RHAT_MAX = 1.01
#: ... and every bulk and tail ESS at least this (Vehtari et al. 2021).
ESS_MIN = 400


class MarginalComparison(NamedTuple):
    """Per-element comparison of q with the reference p; every field is (num_elements,).

    Attributes
    ----------
    smd : standardised mean difference, (mean_q - mean_p) / sd_p
    sd_ratio : sd_q / sd_p
    wasserstein : W_1(q, p) / sd_p
    coverage : fraction of p's draws inside q's central ``prob`` interval
    """

    smd: np.ndarray
    sd_ratio: np.ndarray
    wasserstein: np.ndarray
    coverage: np.ndarray


def flatten_draws(draws: np.ndarray, sample_ndim: int = 1) -> np.ndarray:
    """Reshape draws to ``(num_draws, num_elements)``, merging the ``sample_ndim`` leading dims."""
    draws = np.asarray(draws, dtype=float)
    if draws.ndim < sample_ndim:
        raise ValueError(f"draws of shape {draws.shape} have fewer than {sample_ndim} sample dims")
    num = int(np.prod(draws.shape[:sample_ndim]))
    return draws.reshape(num, -1)


def _check_pair(q: np.ndarray, p: np.ndarray) -> None:
    if q.ndim != 2 or p.ndim != 2 or q.shape[1] != p.shape[1]:
        raise ValueError(f"q {q.shape} and p {p.shape} must be (draws, elements) with the same elements")
    if q.shape[0] < 2 or p.shape[0] < 2:
        raise ValueError("need at least 2 draws from each distribution")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(p))):
        raise ValueError("draws contain NaN or inf")


class ReferenceMarginals(NamedTuple):
    """What :func:`compare_marginals` needs of the reference draws, computed once for every engine compared
    with them (:func:`reference_marginals`): each column sorted (E, n_p), the means and sds (E,)."""

    sorted: np.ndarray
    mean: np.ndarray
    sd: np.ndarray


def reference_marginals(p: np.ndarray) -> ReferenceMarginals:
    """:class:`ReferenceMarginals` of reference draws ``p`` (n_p, E)."""
    p = np.asarray(p, dtype=float)
    return ReferenceMarginals(np.sort(np.ascontiguousarray(p.T), axis=1), p.mean(axis=0), p.std(axis=0, ddof=1))


def _wasserstein_sorted(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """:func:`wasserstein_marginals` of column-sorted draws, (E, n_q) and (E, n_p)."""
    n, m = q.shape[1], p.shape[1]
    steps = np.union1d(np.arange(n + 1) / n, np.arange(m + 1) / m)
    middle = (steps[:-1] + steps[1:]) / 2.0
    i = np.minimum((middle * n).astype(int), n - 1)
    j = np.minimum((middle * m).astype(int), m - 1)
    return np.abs(q[:, i] - p[:, j]) @ np.diff(steps)


def wasserstein_marginals(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    r"""One-dimensional :math:`W_1` between the marginals of two draw sets, every column at once.

    :math:`W_1 = \int_0^1 |F_q^{-1}(u) - F_p^{-1}(u)|\,du`.  The empirical
    quantile functions are steps that change only at :math:`u = i/n_q` and
    :math:`u = j/n_p`, the same for every column; so each column needs only its
    two sorted draw sets, read at one pair of index arrays.  Equal to
    :func:`scipy.stats.wasserstein_distance` column by column (a test); the
    per-column loop took 15 s of a compare report with 8000 reference draws.

    q : (n_q, E), p : (n_p, E) -> (E,)
    """
    q = np.sort(np.ascontiguousarray(np.asarray(q, dtype=float).T), axis=1)
    p = np.sort(np.ascontiguousarray(np.asarray(p, dtype=float).T), axis=1)
    return _wasserstein_sorted(q, p)


def compare_marginals(q: np.ndarray, p: np.ndarray, prob: float = 0.9,
                      reference: ReferenceMarginals | None = None) -> MarginalComparison:
    """Compare every marginal of q with that of the reference p.

    Parameters
    ----------
    q : (num_q, E) draws from the approximation
    p : (num_p, E) draws from the reference (NUTS)
    prob : mass of q's central interval used for the coverage
    reference : :func:`reference_marginals` of ``p``, when several approximations are compared
        with the same reference (computed here when None)

    Returns
    -------
    MarginalComparison
        Elements whose reference sd is 0 get NaN in ``smd``, ``sd_ratio``
        and ``wasserstein`` (they carry no scale to compare in).
    """
    q = np.asarray(q, dtype=float)
    p = np.asarray(p, dtype=float)
    _check_pair(q, p)
    if not 0.0 < prob < 1.0:
        raise ValueError(f"prob must lie in (0, 1), got {prob}")
    ref = reference_marginals(p) if reference is None else reference
    if ref.sorted.shape != p.shape[::-1]:
        raise ValueError(f"the reference marginals {ref.sorted.shape} are not those of p {p.shape}")
    q_sorted = np.sort(np.ascontiguousarray(q.T), axis=1)
    sd_q = q.std(axis=0, ddof=1)
    scale = np.where(ref.sd > 0, ref.sd, np.nan)
    smd = (q.mean(axis=0) - ref.mean) / scale
    ratio = sd_q / scale
    w1 = _wasserstein_sorted(q_sorted, ref.sorted) / scale
    lower, upper = np.quantile(q_sorted, [(1.0 - prob) / 2.0, (1.0 + prob) / 2.0], axis=1)
    # p's draws inside [lower, upper], counted in its sorted columns
    inside = [np.searchsorted(col, hi, side="right") - np.searchsorted(col, lo, side="left")
              for col, lo, hi in zip(ref.sorted, lower, upper)]
    coverage = np.asarray(inside, dtype=float) / p.shape[0]
    return MarginalComparison(smd, ratio, w1, coverage)


def _finite_or_none(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def summarise_comparison(comparison: MarginalComparison) -> dict[str, float | None]:
    """The four numbers of ``metrics.json`` for one quantity (docs/cli.md).

    ``smd_max_abs`` (max over elements of abs(smd)), ``sd_ratio_median``,
    ``wasserstein_max`` and ``coverage90`` (mean over elements); elements
    without a reference scale are ignored, and a summary with no finite
    element is ``None``.
    """

    def reduce(fn, values):
        values = np.asarray(values, dtype=float)
        values = values[np.isfinite(values)]
        return _finite_or_none(fn(values)) if values.size else None

    return {
        "smd_max_abs": reduce(np.max, np.abs(comparison.smd)),
        "sd_ratio_median": reduce(np.median, comparison.sd_ratio),
        "wasserstein_max": reduce(np.max, comparison.wasserstein),
        "coverage90": reduce(np.mean, comparison.coverage),
    }


def joint_divergences(
    q: Mapping[str, np.ndarray],
    p: Mapping[str, np.ndarray],
    *,
    num_samples: int = 500,
    seed: int = 0,
) -> dict[str, float | None]:
    """Joint Wasserstein-1 distance and the KL(p || q) estimate of ``arviz_stats``.

    Both use the variables shared by ``q`` and ``p`` (each ``(num_draws,
    ...)``), standardised element-wise by the reference mean and sd so that
    the distances are in reference-sd units like the marginal metrics, and
    ``num_samples`` draws of each, chosen without replacement.

    Returns ``{"wasserstein_joint", "kl_p_q"}`` with p the reference (NUTS).
    ``wasserstein_joint`` is the optimal-transport distance between the two
    equal-size draw clouds (Euclidean ground cost).  For two uniform empirical
    measures of the same size the optimal plan is a permutation, so it is
    solved exactly as an assignment problem
    (:func:`scipy.optimize.linear_sum_assignment`); this equals
    ``arviz_stats.wasserstein(joint=True)`` (``scipy.stats.wasserstein_distance_nd``,
    a linear program) to rounding and is about 500 times faster at 400 draws.
    ``kl_p_q`` is ``arviz_stats.kl_divergence(p, q)``, the nearest-neighbour
    estimate of Pérez-Cruz (2008); it is large when q misses mass of p (q too narrow).
    """
    import arviz_stats
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial.distance import cdist

    names = [n for n in p if n in q]
    if not names:
        return {"wasserstein_joint": None, "kl_p_q": None}
    cols_q, cols_p = [], []
    for name in names:
        fq, fp = flatten_draws(q[name]), flatten_draws(p[name])
        sd = fp.std(axis=0, ddof=1)
        keep = sd > 0
        mean = fp.mean(axis=0)
        cols_q.append((fq[:, keep] - mean[keep]) / sd[keep])
        cols_p.append((fp[:, keep] - mean[keep]) / sd[keep])
    zq, zp = np.concatenate(cols_q, axis=1), np.concatenate(cols_p, axis=1)
    if zq.shape[1] == 0:
        return {"wasserstein_joint": None, "kl_p_q": None}
    num_samples = int(min(num_samples, zq.shape[0], zp.shape[0]))
    rng = np.random.default_rng(seed)
    zq = zq[rng.choice(zq.shape[0], num_samples, replace=False)]
    zp = zp[rng.choice(zp.shape[0], num_samples, replace=False)]
    cost = cdist(zq, zp)
    rows, cols = linear_sum_assignment(cost)
    w = cost[rows, cols].mean()

    def tree(z):
        da = xr.DataArray(z[None], dims=("chain", "draw", "element"))
        return xr.DataTree.from_dict({"posterior": xr.Dataset({"theta": da})})

    kl = arviz_stats.kl_divergence(tree(zp), tree(zq), num_samples=num_samples, random_seed=seed, round_to="none")
    return {"wasserstein_joint": _finite_or_none(float(w)), "kl_p_q": _finite_or_none(float(kl))}


def pareto_khat(log_ratio: np.ndarray) -> tuple[float | None, str]:
    r"""PSIS :math:`\hat k` of importance ratios given as :math:`\log p(\theta, y) - \log q(\theta)`.

    Parameters
    ----------
    log_ratio : (S,) log importance ratios of S independent draws from q

    Returns
    -------
    khat : the Pareto shape, or ``None`` when it cannot be estimated
    note : ``""``, or why ``khat`` is ``None``

    Notes
    -----
    The fit is :func:`lmpromp_ppl.inference.psis.psis` (arviz-stats' ``psislw`` of the
    negated ratios).  When q equals p up to a constant every ratio is the same and no
    tail can be fitted: ``khat`` is then ``None`` and the note says that the importance
    weights are constant (which is the ideal case, not a failure).
    """
    from lmpromp_ppl.inference.psis import psis

    _, khat, note = psis(log_ratio)
    return khat, note


def khat_verdict(khat: float | None) -> str:
    """Plain-words reading of a k-hat: good, usable, unreliable (Yao et al. 2018)."""
    if khat is None:
        return "not available"
    if khat < KHAT_GOOD:
        return "good"
    if khat < KHAT_USABLE:
        return "usable"
    return "unreliable"


def quantity_reliability(quantities: Mapping[str, np.ndarray]) -> dict[str, dict]:
    """Worst rank-normalised split R-hat and smallest bulk and tail ESS per quantity (arviz-stats).

    Parameters
    ----------
    quantities : name -> (chain, draw, ...) draws (e.g.
        :func:`lmpromp_ppl.quantities.invariant_quantities`)

    Returns
    -------
    name -> ``{"rhat_max", "ess_bulk_min", "ess_tail_min"}`` (Vehtari et al. 2021);
    elements constant across all draws are skipped, and a quantity with none left
    (or fewer than 4 draws per chain) gets ``None`` values.
    """
    from arviz_stats.base import array_stats

    per = {}
    for name, draws in quantities.items():
        draws = np.asarray(draws, dtype=float)
        if draws.ndim < 2:
            raise ValueError(f"{name}: need (chain, draw, ...) draws, got shape {draws.shape}")
        flat = draws.reshape(draws.shape[0], draws.shape[1], -1)
        flat = flat[:, :, np.ptp(flat.reshape(-1, flat.shape[2]), axis=0) > 0]
        if flat.shape[2] == 0 or flat.shape[1] < 4:
            per[name] = {"rhat_max": None, "ess_bulk_min": None, "ess_tail_min": None}
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            rhat = array_stats.rhat(flat, chain_axis=0, draw_axis=1)
            bulk = array_stats.ess(flat, chain_axis=0, draw_axis=1, method="bulk")
            tail = array_stats.ess(flat, chain_axis=0, draw_axis=1, method="tail", prob=(0.05, 0.95))
        per[name] = {
            "rhat_max": _finite_or_none(np.nanmax(rhat)) if np.any(np.isfinite(rhat)) else None,
            "ess_bulk_min": _finite_or_none(np.nanmin(bulk)) if np.any(np.isfinite(bulk)) else None,
            "ess_tail_min": _finite_or_none(np.nanmin(tail)) if np.any(np.isfinite(tail)) else None,
        }
    return per


def reference_reliability(
    quantities: Mapping[str, np.ndarray], divergences: int | None = None
) -> dict:
    """R-hat, bulk and tail ESS of the reference on each quantity, and a verdict.

    Parameters
    ----------
    quantities : name -> (chain, draw, ...) draws of identifiable quantities
        (mixture components already relabelled)
    divergences : number of divergent transitions (None if unknown)

    Returns
    -------
    dict with ``rhat_max``, ``ess_bulk_min``, ``ess_tail_min``,
    ``divergences``, ``per_quantity`` ({name: {rhat_max, ess_bulk_min,
    ess_tail_min}}) and ``problems`` (a list of plain-words sentences, empty
    when the reference meets R-hat <= 1.01, ESS >= 400 and no divergences).
    Elements that are constant across all draws are skipped.
    """
    per = quantity_reliability(quantities)

    def overall(key, fn):
        values = [v[key] for v in per.values() if v[key] is not None]
        return float(fn(values)) if values else None

    out = {
        "rhat_max": overall("rhat_max", max),
        "ess_bulk_min": overall("ess_bulk_min", min),
        "ess_tail_min": overall("ess_tail_min", min),
        "divergences": None if divergences is None else int(divergences),
        "per_quantity": per,
    }
    problems = []
    if out["rhat_max"] is None:
        problems.append("R-hat could not be computed (one chain, or too few draws)")
    elif out["rhat_max"] > RHAT_MAX:
        worst = max((v["rhat_max"] or 0.0, k) for k, v in per.items())[1]
        problems.append(f"R-hat reaches {out['rhat_max']:.3f} > {RHAT_MAX} (worst: {worst})")
    for key, label in (("ess_bulk_min", "bulk"), ("ess_tail_min", "tail")):
        if out[key] is not None and out[key] < ESS_MIN:
            worst = min((v[key] if v[key] is not None else np.inf, k) for k, v in per.items())[1]
            problems.append(f"{label} ESS falls to {out[key]:.0f} < {ESS_MIN} (worst: {worst})")
    if divergences:
        problems.append(f"{int(divergences)} divergent transitions")
    out["problems"] = problems
    return out


# --------------------------------------------------------------------------- importance ratios of fitted engines
def model_log_joint(model_fn, args: tuple, draws: Mapping[str, np.ndarray]) -> np.ndarray:
    """log p(theta, y) of a NumPyro model at each of n draws (``numpyro.infer.util.log_density``)."""
    import jax
    import jax.numpy as jnp
    from numpyro.infer.util import log_density

    params = {k: jnp.asarray(v) for k, v in draws.items()}

    def one(p):
        return log_density(model_fn, args, {}, p)[0]

    return np.asarray(jax.jit(jax.vmap(one))(params))


def numpyro_khat(log_ratio: np.ndarray) -> float | None:
    """numpyro's Pareto k-hat of log importance ratios (the fit inside ``numpyro.infer.psis_diagnostic``).

    A second, independent implementation of the generalized Pareto fit beside
    :func:`pareto_khat`'s (arviz-stats); ``None`` when this numpyro has no such
    function or the fit is not finite.
    """
    try:
        from numpyro.infer.importance import _psis_khat
    except ImportError:  # the fit is private to numpyro: absent, there is no cross-check
        return None
    log_ratio = np.asarray(log_ratio, dtype=float)
    if not np.all(np.isfinite(log_ratio)):
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return _finite_or_none(float(_psis_khat(log_ratio)))


def engine_khat(result, data, key, num_draws: int = 1000, program=None) -> dict:
    r"""Pareto :math:`\hat k` of a VI :class:`~lmpromp_ppl.results.FitResult` (Yao et al. 2018).

    Draws :math:`\theta_s \sim q` afresh and forms :math:`\log p(\theta_s, y) -
    \log q(\theta_s)` on the model q approximates:

    * ``cavi``: the full declared model (:func:`lmpromp_ppl.models.lmpromp.lmpromp_model`
      through ``numpyro.infer.util.log_density``) and the closed-form log density of
      the CAVI factors (the result's ``log_density``);
    * ``cavi_lr``: the linear-response Gaussian of the global quantities on the model with
      ``w`` and ``h`` integrated out (their exact conditionals cancel from the ratio;
      :mod:`lmpromp_ppl.inference.cavi.importance`);
    * ``svi_*``: the guide's own model (collapsed over ``w`` for the automatic
      guides, where ``w`` given theta is exact and cancels from the ratio),
      through numpyro's importance traces (compiled once, vmapped over the
      particles); numpyro's Pareto fit of the same ratios (:func:`numpyro_khat`)
      is reported alongside as a cross-check of the fit.  That the ratios equal
      those of numpyro's own ``psis_diagnostic`` for the same key is a test
      (``tests/test_svi.py``); the report does not recompute them, since
      ``psis_diagnostic`` evaluates the model op by op (19 s of a compare report).

    Parameters
    ----------
    result : a fitted VI result (its ``state`` holds the CAVI state or the SVI result)
    data : the :class:`~lmpromp_ppl.data.ModelData` the engine was fitted to
        (used for CAVI; SVI results carry theirs)
    key : jax PRNG key
    num_draws : draws from q (importance particles)
    program : for ``svi_*``, the compiled importance program and its context
        (:meth:`~lmpromp_ppl.inference.svi.SviResult.importance_log_ratios`); built when None

    Returns ``{"psis_khat", "psis_khat_numpyro", "note"}``; a k-hat that cannot be
    computed is ``None`` and the note says why.
    """
    out = {"psis_khat": None, "psis_khat_numpyro": None, "note": ""}
    engine = result.engine
    key_q = key
    if engine == "cavi":
        from lmpromp_ppl.models.lmpromp import lmpromp_model
        from lmpromp_ppl.models.mixture import mixture_model
        from lmpromp_ppl.models.registry import model_inputs

        if result.model == "mixture" and not bool(np.all(np.asarray(result.state.active))):
            out["note"] = "q has no factor for the removed mixture components, so log p - log q is not defined"
            return out
        draws = {k: np.asarray(v) for k, v in result.sampler(key_q, num_draws).items()}
        if result.model == "mixture":  # the explicit (z sampled) mixture, as q has a factor q(z)
            target = (mixture_model, (data, result.hyper, False))
        else:  # on the fastest equal form of the data (shared-design statistics where possible)
            target = (lmpromp_model, (model_inputs("lmpromp", "none", data), result.hyper))
        log_ratio = model_log_joint(*target, draws) - np.asarray(result.log_density(draws))
    elif engine == "cavi_lr":
        if not hasattr(result.state, "log_ratios"):
            out["note"] = "the cavi_lr result does not carry its linear response"
            return out
        log_ratio = result.state.log_ratios(key_q, num_draws)
    elif engine.startswith("svi_"):
        if not hasattr(result.state, "context"):
            out["note"] = "the SVI result does not carry its guide parameters"
            return out
        log_ratio, _ = result.state.importance_log_ratios(key_q, num_draws, program)
    else:
        out["note"] = f"no k-hat for engine {engine}"
        return out
    out["psis_khat"], out["note"] = pareto_khat(log_ratio)
    out["psis_khat_numpyro"] = numpyro_khat(log_ratio)
    return out

"""``lmpromp_ppl.fit``: one entry point for every model and engine.

The data are standardised per DoF (the scaling is stored with the result),
turned into :class:`~lmpromp_ppl.data.ModelData` with ``num_basis`` basis
functions per DoF, and handed to the engine.  Engines and models are named as
in docs/cli.md.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np

from lmpromp_ppl.basis import DEFAULT_NUM_BASIS, DEFAULT_WIDTH
from lmpromp_ppl.data.core import Demonstrations
from lmpromp_ppl.data.prepared import PreparedDataset, prepare_dataset
from lmpromp_ppl.diagnostics.degeneracy import result_warnings
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference.registry import ENGINE_OPTIONS, ENGINES, MIXTURE_OPTIONS, check_fit, run_engine
from lmpromp_ppl.models.hyper import Hyperparameters, preset
from lmpromp_ppl.models.registry import MODEL_NAMES as MODELS
from lmpromp_ppl.results import FitResult

__all__ = [
    "MODELS", "ENGINES", "ENGINE_OPTIONS", "MIXTURE_OPTIONS", "AUTO_NUM_BASIS",
    "fit", "select_num_basis", "resolve_num_basis", "observed_arrays", "adjusted_rand_index",
    "TIMING_FOLDS", "TIMING_SCORED", "TIMING_DRAWS", "TimingCalibration", "calibrate_timing",
]


#: Basis sizes J that ``num_basis="auto"`` compares by the bound (docs/defaults.md, *Choosing J by the bound*).
AUTO_NUM_BASIS = (6, 8, 10, 12, 15, 20, 25, 30, 40)


def adjusted_rand_index(labels, resp) -> float:
    """Adjusted Rand index of the MAP assignments :math:`\\arg\\max_k r_{ik}` against ``labels`` (scikit-learn)."""
    from sklearn.metrics import adjusted_rand_score

    return float(adjusted_rand_score(np.asarray(labels).astype(str), np.asarray(resp).argmax(axis=1)))


def observed_arrays(demos: Demonstrations) -> dict[str, np.ndarray]:
    """``t`` (L, T) and ``y`` (L, T, D) in data units, NaN-padded to the longest demonstration;
    ``aligned_phase`` (L, T) too when the demonstrations' phases were aligned (``demos.warp``)."""
    size = int(demos.lengths.max())

    def padded(arrays) -> np.ndarray:
        out = np.full((demos.num_demos, size) + arrays[0].shape[1:], np.nan)
        for i, a in enumerate(arrays):
            out[i, : a.shape[0]] = a
        return out

    out = {"t": padded(demos.times), "y": padded(demos.positions)}
    if demos.warp is not None:
        out["aligned_phase"] = padded(demos.warp)
    return out


def resolve_num_basis(num_basis: int | str | None, model: str) -> int | str:
    """``num_basis`` as given, or its default for ``model``: ``"auto"`` for the mixture,
    :data:`~lmpromp_ppl.basis.DEFAULT_NUM_BASIS` otherwise (docs/defaults.md, *Choosing J by the bound*)."""
    if num_basis is None:
        return "auto" if model == "mixture" else DEFAULT_NUM_BASIS
    if isinstance(num_basis, str) and num_basis != "auto":
        raise LmprompError(f"num_basis must be an integer >= 2 or 'auto', got {num_basis!r}")
    return num_basis


def fit(
    data: Demonstrations | str | PreparedDataset,
    model: str = "lmpromp",
    engine: str = "cavi",
    hyper: Hyperparameters | None = None,
    *,
    num_basis: int | str | None = None,
    width: float = DEFAULT_WIDTH,
    seed: int = 0,
    standardise: bool = True,
    align: str | None = None,
    progress: bool = False,
    **options,
) -> FitResult:
    """Fit ``model`` to demonstrations with ``engine``.

    Parameters
    ----------
    data : Demonstrations, a dataset string (``"lasa:GShape"``, ``"gunpoint"``, a file path), or a
        :class:`~lmpromp_ppl.data.PreparedDataset` (:func:`~lmpromp_ppl.data.prepare_dataset`) whose model inputs are used as
        they are (``num_basis``, ``width`` and ``standardise`` must then be left at their defaults)
    model : ``"promp"``, ``"lmpromp"`` or ``"mixture"``
    engine : ``"cavi"``, ``"cavi_lr"`` (CAVI with the joint local family and linear-response
        covariances, the single-type LMProMP), ``"nuts"``, ``"svi_meanfield"``, ``"svi_autonormal"``
        or ``"svi_lowrank"``
    hyper : hyperparameters; default: the ``default`` preset for CAVI (both engines), the
        ``proper`` preset for NUTS and SVI (near-improper Gamma priors cannot be
        sampled); both learn the noise precision beta (docs/defaults.md)
    num_basis : basis functions per DoF (J), or ``"auto"``: the J of
        :data:`AUTO_NUM_BASIS` with the highest evidence lower bound
        (:func:`select_num_basis`; the comparison is in ``summary["num_basis_selection"]``).
        Default: ``"auto"`` for the mixture, whose components each pay an Occam
        factor per weight, so that a basis finer than the data need would hide
        the movement types; :data:`~lmpromp_ppl.basis.DEFAULT_NUM_BASIS` otherwise
    width : basis width (:data:`lmpromp_ppl.basis.DEFAULT_WIDTH`)
    seed : seeds every random choice of the engine
    align : ``"dtw"``: align the demonstrations' phases before fitting
        (:func:`lmpromp_ppl.data.align.align_phases`; stored as ``observed_data.aligned_phase``);
        default: each demonstration's time mapped linearly to [0, 1]
    options : passed to the engine (e.g. ``tol``, ``max_iter``, ``num_restarts`` for
        CAVI, and for the mixture ``search`` (``"split_merge"``, the default, or ``"none"``)
        and ``max_moves``; ``num_chains``, ``num_warmup``, ``num_samples`` for NUTS; ``num_steps``,
        ``learning_rate`` for SVI)

    For the mixture with CAVI, ``summary["ari"]`` is the adjusted Rand index of the
    MAP responsibilities against the data's labels, when the demonstrations carry labels.
    """
    check_fit(model, engine, options)
    if hyper is None:
        hyper = preset("default" if engine in ("cavi", "cavi_lr") else "proper")
    if isinstance(data, PreparedDataset):
        if num_basis is not None or width != DEFAULT_WIDTH or not standardise or align is not None:
            raise LmprompError("a PreparedDataset fixes num_basis, width, the scaling and the phases; do not pass them")
        prepared = data
    else:
        num_basis = resolve_num_basis(num_basis, model)
        if num_basis == "auto":
            return _fit_auto_basis(data, model, engine, hyper, width=width, seed=seed, standardise=standardise,
                                   align=align, progress=progress, options=options)
        prepared = prepare_dataset(data, num_basis, standardise=standardise, width=width, align=align)
    return _fit_prepared(prepared, model, engine, hyper, seed=seed, progress=progress, options=options)


def _fit_prepared(prepared: PreparedDataset, model, engine, hyper, *, seed, progress, options) -> FitResult:
    """The engine's fit on prepared model inputs, as a :class:`FitResult` with its degeneracy warnings."""
    spec, raw, scaling, mdata = prepared.spec, prepared.raw, prepared.scaling, prepared.model_data
    hyper.validate_for(mdata.num_weights, mdata.num_demos)
    if model == "mixture" and mdata.num_demos < hyper.num_components:
        raise LmprompError(
            f"fewer demonstrations (L={mdata.num_demos}) than mixture components (K={hyper.num_components})"
        )
    common = dict(
        model=model,
        engine=engine,
        hyper=hyper,
        num_basis=prepared.num_basis,
        width=prepared.width,
        num_dofs=raw.num_dofs,
        scaling=scaling,
        dataset=spec,
        dof_names=raw.dof_names,
        observed=observed_arrays(raw),
        options=dict(options),
        seed=seed,
    )
    key = jax.random.key(seed)
    if engine == "cavi":
        result = _cavi_result(mdata, key, progress, common, options, raw.labels)
    elif engine == "cavi_lr":
        result = _cavi_lr_result(mdata, key, progress, common, options)
    elif engine == "nuts":
        result = _nuts_result(mdata, key, progress, common, options)
    else:
        result = _svi_result(mdata, key, progress, common, options)
    result.summary["warnings"] = result_warnings(result)
    return result


def select_num_basis(
    data: Demonstrations | str | PreparedDataset,
    *,
    grid=AUTO_NUM_BASIS,
    hyper: Hyperparameters | None = None,
    width: float = DEFAULT_WIDTH,
    seed: int = 0,
    standardise: bool = True,
) -> dict:
    r"""Choose the number of basis functions per DoF by the evidence lower bound.

    Fits the single-type LMProMP with CAVI for every J of ``grid`` no larger
    than the shortest demonstration's number of samples, on the same
    standardised data, and keeps the J whose bound on :math:`\log p(\mathbf y)`
    is highest: a larger basis pays an Occam factor for every extra weight of
    every demonstration and of the offset, so the bound trades smoothness
    against fit (docs/defaults.md, *Choosing J by the bound*).  ``hyper``
    (default: the ``default`` preset) is used with one component.

    Every J compiles the engine once, so the selection costs about as many
    compilations as fits (40 s for ``synthetic:clusters`` on two cores).

    The data are loaded and standardised once (a :class:`~lmpromp_ppl.data.PreparedDataset`
    keeps its own scaling and width); only the design matrices change with J.

    Returns ``{"num_basis": J, "grid": [...], "elbo": [...], "seconds": wall time,
    "result": FitResult at J, "prepared": PreparedDataset at J}``.
    """
    import time
    import warnings

    start = time.perf_counter()
    if isinstance(data, PreparedDataset):
        base_data = data
    else:  # built at the grid's first size, which the loop below then reuses
        first = min([int(J) for J in grid if int(J) >= 2], default=2)
        base_data = prepare_dataset(data, first, standardise=standardise, width=width)
    demos = base_data.scaled
    base = (preset("default") if hyper is None else hyper).replace(num_components=1)
    shortest = int(np.min(demos.lengths))
    sizes = sorted({int(J) for J in grid
                    if 2 <= int(J) <= shortest and demos.num_dofs * int(J) >= base.latent_dim})
    if not sizes:
        raise LmprompError(f"no basis size of {list(grid)} fits demonstrations of {shortest} samples")
    bounds, best = [], None
    for J in sizes:
        prepared = base_data if J == base_data.num_basis else base_data.with_basis(J)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = _fit_prepared(prepared, "lmpromp", "cavi", base, seed=seed, progress=False, options={})
        bounds.append(float(res.summary["elbo"]))
        if best is None or bounds[-1] > best[0].summary["elbo"]:
            best = (res, prepared)  # only the best fit is kept: memory of one fit whatever the grid
    return {"num_basis": best[0].num_basis, "grid": sizes, "elbo": bounds, "seconds": time.perf_counter() - start,
            "result": best[0], "prepared": best[1]}


def _fit_auto_basis(data, model, engine, hyper, *, width, seed, standardise, align, progress, options) -> FitResult:
    """``fit(..., num_basis="auto")``: :func:`select_num_basis`, then the requested fit at the chosen J."""
    prepared = prepare_dataset(data, min(AUTO_NUM_BASIS), standardise=standardise, width=width, align=align)
    if model == "mixture" and prepared.raw.num_demos < hyper.num_components:
        raise LmprompError(f"fewer demonstrations (L={prepared.raw.num_demos}) than mixture components "
                           f"(K={hyper.num_components})")
    choice = select_num_basis(prepared, grid=AUTO_NUM_BASIS, hyper=hyper, seed=seed)
    same = model == "lmpromp" and engine == "cavi" and not options and hyper.num_components == 1
    result = choice["result"] if same else _fit_prepared(choice["prepared"], model, engine, hyper, seed=seed,
                                                         progress=progress, options=options)
    result.summary["num_basis_selection"] = {key: choice[key] for key in ("num_basis", "grid", "elbo", "seconds")}
    return result


def _cavi_result(mdata, key, progress, common, options, labels=None) -> FitResult:
    from lmpromp_ppl.inference import cavi

    res = run_engine("cavi", common["model"], mdata, common["hyper"], key, progress=progress, **options)
    summary = {
        "elbo": float(res.elbo),
        "elbo_trace": np.asarray(res.elbo_trace).tolist(),
        "iterations": int(res.iterations),
        "converged": bool(res.converged),
        "seconds": float(res.seconds),
        "compile_seconds": float(res.compile_seconds),
        "active_latent_dims": cavi.active_latent_dims(res.state),
    }
    if common["model"] == "mixture":
        summary["active_components"] = cavi.active_components(res.state)
        if labels is not None:
            summary["ari"] = adjusted_rand_index(labels, cavi.responsibilities(res.state))
    state = res.state
    return FitResult(
        **common,
        sampler=lambda k, n: cavi.sample_q(k, state, n),
        log_density=lambda draws: cavi.log_q(state, draws),
        point={k: np.asarray(v) for k, v in cavi.point_estimate(state).items()},
        optimization={"elbo": np.asarray(res.elbo_trace)},
        summary=summary,
        state=state,
    )


def _cavi_lr_result(mdata, key, progress, common, options) -> FitResult:
    from lmpromp_ppl.inference import cavi

    res = run_engine("cavi_lr", common["model"], mdata, common["hyper"], key, progress=progress, **options)
    base = res.fit
    summary = {
        "elbo": float(base.elbo),
        "elbo_trace": np.asarray(base.elbo_trace).tolist(),
        "iterations": int(base.iterations),
        "converged": bool(base.converged),
        "seconds": float(base.seconds + res.lr_seconds),
        "compile_seconds": float(base.compile_seconds + res.lr_compile_seconds),
        "active_latent_dims": cavi.active_latent_dims(base.state),
        "linear_response": {"seconds": float(res.lr_seconds), "cg_residual": float(res.lr.residual),
                            "psis_khat": res.psis_khat, "psis_note": res.psis_note,
                            "importance_resampled": bool(res.resampled), "refresh_sweeps": int(res.refresh)},
    }
    point = {k: np.asarray(v) for k, v in cavi.point_estimate(base.state).items()}

    def sampler(key, num_draws):
        """The engine's draws; the refresh sweeps' time is added to the fit's (they are the engine's work)."""
        draws, seconds, compile_seconds = res.sample_timed(key, num_draws)
        info = summary["linear_response"]
        info["refresh_seconds"] = info.get("refresh_seconds", 0.0) + seconds
        info["refresh_compile_seconds"] = info.get("refresh_compile_seconds", 0.0) + compile_seconds
        summary["seconds"] += seconds
        summary["compile_seconds"] += compile_seconds
        return draws

    return FitResult(
        **common,
        sampler=sampler,
        log_density=res.log_density,
        point=point,
        optimization={"elbo": np.asarray(base.elbo_trace)},
        summary=summary,
        state=res,
    )


def _nuts_result(mdata, key, progress, common, options) -> FitResult:
    res = run_engine("nuts", common["model"], mdata, common["hyper"], key, progress=progress, **options)
    draws = {k: np.asarray(v) for k, v in res.samples.items()}
    point = {k: v.mean(axis=(0, 1)) for k, v in draws.items()}
    summary = {
        "seconds": float(res.seconds),
        "compile_seconds": float(res.compile_seconds),
        "divergences": int(np.sum(np.asarray(res.sample_stats["diverging"]))),
    }
    return FitResult(
        **common,
        draws=draws,
        point=point,
        sample_stats={k: np.asarray(v) for k, v in res.sample_stats.items()},
        summary=summary,
    )


def _svi_result(mdata, key, progress, common, options) -> FitResult:
    from lmpromp_ppl.inference.svi import DRAWS_AFTER_FIT

    fit_key, draw_key = jax.random.split(key)
    res = run_engine(common["engine"], common["model"], mdata, common["hyper"], fit_key, progress=progress, **options)
    loss = np.asarray(res.loss_trace)
    draws = {k: np.asarray(v) for k, v in res.sample(draw_key, DRAWS_AFTER_FIT).items()}
    summary = {
        "elbo": float(-np.mean(loss[-max(1, len(loss) // 20):])),
        "iterations": int(res.num_steps_run),
        "converged": bool(res.converged),
        "seconds": float(res.seconds),
        "compile_seconds": float(res.compile_seconds),
    }
    return FitResult(
        **common,
        draws={k: v[None] for k, v in draws.items()},
        point={k: v.mean(axis=0) for k, v in draws.items()},
        optimization={"loss": loss},
        summary=summary,
        state=res,
    )


#: Refits of :func:`calibrate_timing`: the training demonstrations are split into at most this many folds.
TIMING_FOLDS = 8
#: Held-out demonstrations whose durations :func:`calibrate_timing` scores, at most (evenly spread).
TIMING_SCORED = 24
#: Posterior draws per refit that average the timing's likelihood in :func:`calibrate_timing`.
TIMING_DRAWS = 50


_GOLDEN = (1.0 + 5.0**0.5) / 2.0


class TimingCalibration(NamedTuple):
    """The powers of the timing's likelihood weighed by cross-validation (:func:`calibrate_timing`)."""

    power: float  # the best-scoring power kappa in [0, 1]
    powers: np.ndarray  # (P,) the candidates (:data:`~lmpromp_ppl.predict.timing.TIMING_POWERS`)
    log_scores: np.ndarray  # (P,) summed log density of the held-out demonstrations' true log durations
    weights: np.ndarray  # (P,) pseudo-BMA weights of the candidates, proportional to exp(log_scores)
    num_scored: int  # held-out demonstrations longer than the observation (those that score)
    num_folds: int
    observed_time: float
    num_unconverged: int = 0  # refits that stopped at the engine's iteration limit

    @property
    def mean_power(self) -> float:
        """The weighted mean of the candidate powers (a summary of the average over them)."""
        return float(np.sum(self.powers * self.weights))


def calibrate_timing(result: FitResult, observed_time: float, *, folds: int = TIMING_FOLDS,
                     max_scored: int = TIMING_SCORED, max_draws: int = TIMING_DRAWS,
                     timing_points: int | str | None = "residual", max_start: float = 0.0,
                     progress=False) -> TimingCalibration:
    r"""The power :math:`\kappa` of the timing's likelihood under which the fit's duration
    posterior predicts the training demonstrations' own durations best.

    The model maps each demonstration's time linearly to phase, so a demonstration
    whose speed profile differs from the others is explained by a wrong duration
    with full confidence: on LASA the 90 % intervals cover the truth 0-57 % of the
    time, under NUTS as under CAVI (docs/derivation.md, *Calibrating the timing*).
    Tempering the likelihood, :math:`p_\kappa(T | \mathbf{o}) \propto p(T)\,
    p(\mathbf{o} | T)^\kappa`, is the generalised-Bayes repair for a misspecified
    likelihood (Grünwald and van Ommen 2017; Holmes and Walker 2017), and
    :math:`\kappa` is chosen as SafeBayes chooses its learning rate, by a log score
    on held-out data:

    1. the training demonstrations are split into ``min(L, folds)`` folds (every
       ``folds``-th demonstration); the model is refitted by CAVI without each fold,
       with the fit's hyperparameters, basis, scaling rule, options (when the fit is
       CAVI's) and aligned phases;
    2. each held-out demonstration longer than ``observed_time`` (at most ``max_scored``
       of them, evenly spread; folds without one are not refitted) is observed over its
       first ``observed_time`` (the situation of the prediction), and its duration's
       likelihood is evaluated on a grid, averaged over ``max_draws`` posterior draws
       of the refit (:func:`~lmpromp_ppl.predict.from_fit.timing_curve_of`);
       With ``max_start > 0`` (an observation that may have begun after the movement, as
       ``predict_from_fit(..., max_start=...)`` weighs it) the j-th scored demonstration is
       observed from phase :math:`u_j = ` ``max_start`` :math:`\cdot\{(j + 1/2)\varphi\}`
       (evenly spread, :math:`\varphi` the golden ratio) for ``observed_time`` seconds, and its
       likelihood runs over the duration and the start phase, the start integrated out;
    3. each candidate :math:`\kappa_k` of :data:`~lmpromp_ppl.predict.timing.TIMING_POWERS`
       (0, the prior alone, to 1, the model's posterior) scores the summed log density of the
       held-out true durations, :math:`S_k = \sum_i \log p_{\kappa_k}(\log T_i | \mathbf{o}_i)`;
       ``power`` maximises it, and ``weights`` :math:`\pi_k \propto \exp S_k` (pseudo-BMA:
       Yao, Vehtari, Simpson and Gelman 2018) average over the candidates instead of choosing one.
       With a handful of held-out demonstrations the scores differ by a few nats across the
       candidates, so the best one is a noisy choice; the average is what
       ``lmpromp predict --duration estimate`` uses (docs/derivation.md, *Calibrating the timing*).

    The refits use CAVI whatever the fit's engine: the over-confidence is the model's
    (the duration errors under NUTS and ``cavi_lr`` equal CAVI's), and a refit by NUTS
    would take minutes.  A fold whose refit the model does not allow (fewer demonstrations
    left than it needs, e.g. than latent dimensions) is skipped; fewer than two scoring
    demonstrations leave the power at 1.
    A refit's :class:`~lmpromp_ppl.errors.ConvergenceWarning` is counted in
    ``num_unconverged`` instead of being shown once per refit.
    Pass ``powers`` and ``weights`` to :func:`~lmpromp_ppl.predict.from_fit.predict_from_fit` as
    ``timing_power`` and ``timing_weights`` (or ``power`` alone as ``timing_power``).
    """
    import warnings

    from lmpromp_ppl._progress import reporter
    from lmpromp_ppl.errors import ConvergenceWarning
    from lmpromp_ppl.predict.from_fit import timing_curve_of
    from lmpromp_ppl.predict.timing import TIMING_POWERS, tempered_log_score

    if not (np.isfinite(observed_time) and observed_time > 0):
        raise LmprompError(f"the observed time must be positive and finite, got {observed_time!r}")
    if not 0.0 <= max_start < 1.0:
        raise LmprompError(f"max_start must lie in [0, 1), got {max_start!r}")
    for name, value, least in (("folds", folds, 2), ("max_scored", max_scored, 2), ("max_draws", max_draws, 1)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise LmprompError(f"{name} must be an integer of at least {least}, got {value!r}")
    demos = result.training_demonstrations()
    num_folds = min(demos.num_demos, int(folds))
    group = np.arange(demos.num_demos) % num_folds
    chosen = np.zeros(demos.num_demos, dtype=bool)
    chosen[np.unique(np.linspace(0, demos.num_demos - 1, min(demos.num_demos, int(max_scored))).round().astype(int))] = True
    scaling = result.scaling
    standardise = not (np.all(np.asarray(scaling.mean) == 0) and np.all(np.asarray(scaling.scale) == 1))
    options = dict(result.options) if result.engine == "cavi" else {}
    scores, scored, unconverged = np.zeros(TIMING_POWERS.size), 0, 0
    with reporter(progress, num_folds, "calibrating the timing", "log score") as report:
        for k in range(num_folds):
            if np.sum(group != k) >= 2 and np.any(chosen & (group == k)):
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always", ConvergenceWarning)
                    try:
                        refit = fit(demos.subset(group != k), result.model, "cavi", result.hyper,
                                    num_basis=result.num_basis, width=result.width,
                                    seed=0 if result.seed is None else result.seed, standardise=standardise, **options)
                    except LmprompError:  # too few demonstrations left for the model (e.g. fewer than V)
                        refit = None
                unconverged += any(issubclass(w.category, ConvergenceWarning) for w in caught)
                for w in caught:  # anything else is shown as it would be
                    if not issubclass(w.category, ConvergenceWarning):
                        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
                for i in np.flatnonzero(chosen & (group == k)) if refit is not None else ():
                    t = demos.times[i] - demos.times[i][0]
                    begin = max_start * ((scored + 0.5) * _GOLDEN % 1.0) * t[-1]  # 0 without max_start
                    seen = (t >= begin) & (t <= begin + observed_time)
                    if t[-1] <= begin + observed_time or np.sum(seen) < 2:
                        continue
                    curve = timing_curve_of(refit, t[seen] - begin, demos.positions[i][seen],
                                            timing_points=timing_points, max_draws=int(max_draws), max_start=max_start)
                    scores += tempered_log_score(curve, float(np.log(t[-1])))
                    scored += 1
            if report is not None:
                report(k + 1, float(np.max(scores)) if scored else float("nan"))
    if scored >= 2:
        power = float(TIMING_POWERS[int(np.argmax(scores))])
        weights = np.exp(scores - np.max(scores))
        weights = weights / weights.sum()
    else:  # nothing to score: the model's posterior
        power, weights = 1.0, (TIMING_POWERS == 1.0).astype(float)
    return TimingCalibration(power, TIMING_POWERS.copy(), scores, weights, scored, num_folds, float(observed_time),
                             unconverged)

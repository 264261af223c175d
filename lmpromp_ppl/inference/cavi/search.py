r"""Search over mixture configurations: restarts, merge and split moves (SMEM / VBMFA).

Plain CAVI for the mixture (:mod:`lmpromp_ppl.inference.cavi`) climbs to
the nearest local optimum of the bound; from a k-means start with more
components than movement types it typically keeps every component, each
covering part of a type.  This module searches between such optima, in the
manner of Ueda et al.'s split-and-merge EM (SMEM) and Ghahramani & Beal's
variational Bayesian mixtures of factor analysers (VBMFA):

* **merge** components k and l: the responsibilities of l are added to k, l is
  removed (``active`` False), and k's factors are re-initialised by a weighted
  PCA of the weight means under the merged responsibilities.  Candidates are
  ranked by the correlation of the two columns of responsibilities (SMEM's
  criterion), ties (one-hot responsibilities) by the distance of the offsets
  :math:`\mu_{b_k}` in trajectory space (:func:`merge_candidates`);
* **split** component k into k and a removed slot j: k's demonstrations are
  divided by 2-means in trajectory space and both parts re-initialised by PCA.
  Candidates are the components with the largest expected negative
  log-likelihood per demonstration, :math:`-\frac1{N_k}\sum_i r_{ik}E\log\mathcal N(w_i\mid b_k + M_kh_{ik}, \alpha_k^{-1}I)`
  (:func:`split_candidates`); splits need a removed slot, so K is an upper bound.

A round runs every candidate state, together with the unchanged state, for a
few *partial* sweeps (every factor but q(z) and q(pi), so the re-initialised
components adapt to their responsibilities) and then full sweeps (at most
``move_iter``), all in one compiled, vectorised loop (:func:`run_candidates`).
The best move is accepted only if its bound exceeds that of the unchanged state
after the same sweeps (:func:`accept`); otherwise the search stops.  The best
bound kept is therefore non-decreasing over the search, and the full sweeps
themselves are the plain CAVI sweeps of :func:`lmpromp_ppl.inference.cavi.step`.

Removed components contribute nothing to the bound (the module docstring of
:mod:`~lmpromp_ppl.inference.cavi.state`), so bounds with different numbers of
active components are bounds of the same declared K-component model and can be
compared.
"""

from __future__ import annotations

import math
import time
from functools import partial
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from sklearn.cluster import KMeans

from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference.cavi.data import CaviData
from lmpromp_ppl.inference.cavi.init import function_space
from lmpromp_ppl.inference.cavi.loop import fresh, iterate, run
from lmpromp_ppl.inference.cavi.posterior import responsibilities
from lmpromp_ppl.inference.cavi.restarts import CaviFit, best_fit, check_restart_bound
from lmpromp_ppl.inference.cavi.state import CaviHyper, CaviState, expected_stats
from lmpromp_ppl.inference.cavi.updates import updates_for
from lmpromp_ppl.inference.compiled import compiled

__all__ = [
    "SEARCHES",
    "Move",
    "SearchResult",
    "accept",
    "merge_candidates",
    "split_candidates",
    "merge_state",
    "state_from_labels",
    "split_state",
    "run_candidates",
    "search",
    "fit_with_search",
]

#: Values of ``search``: plain CAVI from each start, or with split and merge moves.
SEARCHES = ("none", "split_merge")


class Move(NamedTuple):
    """A proposed move: ``kind`` ``"merge"`` (components (k, l), l removed) or ``"split"`` ((k, j), j revived)."""

    kind: str
    components: tuple[int, int]


class SearchResult(NamedTuple):
    """Output of :func:`search`.

    Attributes
    ----------
    state : the best state found (before the final full run of :func:`fit_with_search`)
    elbo : its bound
    trace : ELBO after each full sweep along the accepted path
    moves : the accepted moves, in order
    best_elbos : the best bound after the initial run and after every round (non-decreasing)
    compile_seconds : ahead-of-time compilation of :func:`run_candidates` (0 when already compiled)
    """

    state: CaviState
    elbo: float
    trace: np.ndarray
    moves: list[Move]
    best_elbos: list[float]
    compile_seconds: float


def accept(candidate_elbo: float, reference_elbo: float, rel_tol: float = 1e-9) -> bool:
    """The acceptance rule: a move is kept only if its bound is higher than the reference's.

    ``reference_elbo`` is the bound of the unchanged state after the same number of
    sweeps; the candidate must beat it by more than ``rel_tol`` relative (so that
    round-off never accepts a move).  NaN is never accepted.
    """
    if not (math.isfinite(candidate_elbo) and math.isfinite(reference_elbo)):
        return False
    return candidate_elbo > reference_elbo + rel_tol * max(abs(reference_elbo), 1.0)


# --------------------------------------------------------------------------- candidates
def merge_candidates(state: CaviState, data: CaviData) -> list[tuple[int, int]]:
    """Pairs (k, l) of active components, most promising merge first.

    Ranked by the correlation of the columns k and l of the responsibilities
    (Ueda et al.'s merge criterion), then, among equal correlations (e.g. hard
    assignments), by the distance of the offsets in trajectory space.  In each
    pair k has the larger expected count (it absorbs l).
    """
    active = np.flatnonzero(np.asarray(state.active))
    resp = np.asarray(responsibilities(state))
    counts = resp.sum(axis=0)
    centres = function_space(data, np.asarray(state.b_mean))
    rows = []
    for a_i, a in enumerate(active):
        for b in active[a_i + 1:]:
            ra, rb = resp[:, a], resp[:, b]
            sa, sb = ra.std(), rb.std()
            corr = float(np.mean((ra - ra.mean()) * (rb - rb.mean())) / (sa * sb)) if sa > 0 and sb > 0 else -1.0
            dist = float(np.linalg.norm(centres[a] - centres[b]))
            k, l = (int(a), int(b)) if counts[a] >= counts[b] else (int(b), int(a))
            rows.append((-round(corr, 3), dist, k, l))
    rows.sort()
    return [(k, l) for _, _, k, l in rows]


def split_candidates(state: CaviState, hyper: CaviHyper, min_count: float = 2.0) -> list[int]:
    """Active components with at least ``min_count`` expected demonstrations, worst fit first.

    The fit of component k is its expected negative log-likelihood per
    demonstration, :math:`-\\frac1{N_k}\\sum_ir_{ik}\\big(\\frac d2(E\\log\\alpha_k - \\log 2\\pi)
    - \\frac{\\bar\\alpha_k}2E\\|w_i - b_k - M_kh_{ik}\\|^2\\big)`.
    """
    st = expected_stats(state, hyper, logs=True)
    d = state.w_mean.shape[1]
    resp = np.asarray(st.resp)
    counts = resp.sum(axis=0)
    nll = -(
        0.5 * d * (np.asarray(st.log_alpha_mean)[None] - math.log(2 * math.pi))
        - 0.5 * np.asarray(st.alpha_mean)[None] * np.asarray(st.residual_sq)
    )
    per_demo = np.sum(resp * nll, axis=0) / np.maximum(counts, 1e-300)
    active = np.asarray(state.active)
    ks = [k for k in range(resp.shape[1]) if active[k] and counts[k] >= min_count]
    return sorted(ks, key=lambda k: -per_demo[k])


# --------------------------------------------------------------------------- moves
def _fresh_component(
    state: CaviState, hyper: CaviHyper, k: int, weights: np.ndarray, fallback_M: np.ndarray
) -> dict[str, np.ndarray]:
    """Factors of component k re-initialised from a weighted PCA of the weight means (as :mod:`.init`).

    ``weights`` (L,) are the responsibilities the component takes; with fewer than
    V + 1 expected demonstrations the projection ``fallback_M`` is kept and the
    scores are its least-squares coordinates.
    """
    W = np.asarray(state.w_mean)
    L, d = W.shape
    V = state.M_mean.shape[2]
    N = float(weights.sum())
    b = weights @ W / max(N, 1e-300)
    centred = W - b
    if N > V + 0.5:
        cov = (centred * weights[:, None]).T @ centred / N
        eigvals, vectors = np.linalg.eigh(cov)
        variance = eigvals[::-1][:V]
        components = vectors[:, ::-1][:, :V]
        variance = np.maximum(variance, 1e-10 * max(variance.max(), 1e-300))
        scale = np.sqrt(variance)
        M = components * scale
        h = centred @ components / scale
    else:
        M = fallback_M
        h = np.linalg.lstsq(M, centred.T, rcond=None)[0].T
    residual = centred - h @ M.T
    spread = float(np.sum(weights[:, None] * centred**2) / max(N * d, 1e-300))
    floor = 1e-3 * spread + 1e-12
    alpha = 1.0 / max(float(np.sum(weights[:, None] * residual**2) / max(N * d, 1e-300)), floor)
    col_sq = np.sum(M**2, axis=0)
    lam = d / np.maximum(col_sq, 1e-8 * col_sq.max() + 1e-300)
    gamma = float(hyper.gamma)
    MtM = M.T @ M
    h_cov = np.linalg.inv((weights * alpha)[:, None, None] * MtM + gamma * np.eye(V))
    S = np.einsum("i,iuv->uv", weights, h_cov + np.einsum("iu,iv->iuv", h, h))
    A = alpha * S + np.diag(lam)
    if state.M_var.ndim == 3:
        M_var = np.linalg.inv(A)
        M_var = 0.5 * (M_var + M_var.T)
    else:
        M_var = 1.0 / np.diag(A)
    alpha_shape = float(hyper.a0) + 0.5 * d * N
    lam_shape = np.full(V, float(hyper.c0) + 0.5 * d)
    return dict(
        b_mean=b, b_var=1.0 / (N * alpha + float(hyper.lambda0)), M_mean=M, M_var=M_var,
        alpha_shape=alpha_shape, alpha_rate=alpha_shape / alpha, lam_shape=lam_shape, lam_rate=lam_shape / lam,
        h_mean=h, h_cov=h_cov,
    )


def _with_components(
    state: CaviState, hyper: CaviHyper, resp: np.ndarray, active: np.ndarray,
    fresh: dict[int, dict[str, np.ndarray]],
) -> CaviState:
    """``state`` with new responsibilities, active mask, q(pi) and the factors of the components in ``fresh``."""
    fields = {name: np.array(getattr(state, name)) for name in (
        "b_mean", "b_var", "M_mean", "M_var", "alpha_shape", "alpha_rate", "lam_shape", "lam_rate")}
    h_mean, h_cov = np.array(state.h_mean), np.array(state.h_cov)
    for k, values in fresh.items():
        for name in fields:
            fields[name][k] = values[name]
        h_mean[:, k] = values["h_mean"]
        h_cov[:, k] = values["h_cov"]
    f64 = lambda x: jnp.asarray(x, jnp.float64)  # noqa: E731
    return state._replace(
        **{name: f64(value) for name, value in fields.items()},
        h_mean=f64(h_mean), h_cov=f64(h_cov), resp=f64(resp), active=jnp.asarray(active, jnp.bool_),
        pi_conc=f64(float(hyper.kappa0) + resp.sum(axis=0)),
    )


def state_from_labels(state: CaviState, hyper: CaviHyper, labels: np.ndarray) -> CaviState:
    """``state`` with one active component per label (codes 0..n-1 < K), each re-initialised by PCA.

    Starts CAVI at a known partition (e.g. the data's movement types), to compare the
    bound the search finds with the bound at the labels.
    """
    codes = np.asarray(labels, dtype=int)
    K = state.M_mean.shape[0]
    if codes.min() < 0 or codes.max() >= K:
        raise LmprompError(f"label codes must lie in 0..{K - 1}, got {codes.min()}..{codes.max()}")
    resp = np.eye(K)[codes]
    active = np.zeros(K, bool)
    active[np.unique(codes)] = True
    fresh = {int(k): _fresh_component(state, hyper, int(k), resp[:, k], np.asarray(state.M_mean[k]))
             for k in np.unique(codes)}
    return _with_components(state, hyper, resp, active, fresh)


def merge_state(state: CaviState, hyper: CaviHyper, k: int, l: int) -> CaviState:
    """Merge component l into k: :math:`r_{ik} \\leftarrow r_{ik} + r_{il}`, l removed, k re-initialised."""
    resp = np.array(responsibilities(state))
    active = np.array(state.active)
    if not (active[k] and active[l]) or k == l:
        raise LmprompError(f"cannot merge components {k} and {l}: both must be distinct and active")
    resp[:, k] += resp[:, l]
    resp[:, l] = 0.0
    active[l] = False
    fresh = {k: _fresh_component(state, hyper, k, resp[:, k], np.asarray(state.M_mean[k]))}
    return _with_components(state, hyper, resp, active, fresh)


def split_state(
    state: CaviState, data: CaviData, hyper: CaviHyper, k: int, j: int, seed: int
) -> CaviState | None:
    """Split component k into k and the removed slot j by 2-means (seeded) of k's demonstrations.

    A demonstration belongs to k when :math:`r_{ik} \\ge 1/2`; returns None when
    fewer than two do or 2-means finds a single group.
    """
    resp = np.array(responsibilities(state))
    active = np.array(state.active)
    if not active[k] or active[j]:
        raise LmprompError(f"cannot split component {k} into {j}: {k} must be active and {j} removed")
    members = np.flatnonzero(resp[:, k] >= 0.5)
    if members.size < 2:
        return None
    coords = function_space(data, np.asarray(state.w_mean))[members]
    groups = KMeans(n_clusters=2, n_init=5, random_state=seed).fit_predict(coords)
    if np.unique(groups).size < 2:
        return None
    moved = members[groups == 1]
    resp[moved, j] = resp[moved, k]
    resp[moved, k] = 0.0
    active[j] = True
    parent = np.asarray(state.M_mean[k])
    fresh = {c: _fresh_component(state, hyper, c, resp[:, c], parent) for c in (k, j)}
    return _with_components(state, hyper, resp, active, fresh)


# --------------------------------------------------------------------------- compiled runs
@jax.jit
def _fixed_z_step(state: CaviState, data: CaviData, hyper: CaviHyper) -> CaviState:
    """A partial sweep: every update of :func:`~.updates.updates_for` except q(z) and q(pi); no pruning."""
    for name, update in updates_for(state).items():
        if name not in ("z", "pi"):
            state = update(state, data, hyper)
    return state


@partial(jax.jit, static_argnames=("buffer", "partial_sweeps"))
def run_candidates(
    states: CaviState, data: CaviData, hyper: CaviHyper, tol: Array, limit: Array,
    buffer: int, partial_sweeps: int,
):
    """Run a batch of states (leading axis) for ``partial_sweeps`` partial then at most ``limit`` full sweeps.

    Returns (states, traces (B, buffer), iterations (B,), converged (B,)); the full
    sweeps stop per state as in :func:`~.loop.run`.
    """

    def one(state):
        state = jax.lax.fori_loop(0, partial_sweeps, lambda _, s: _fixed_z_step(s, data, hyper), state)
        result = iterate(state, data, hyper, tol, limit, fresh(), buffer)
        return result.state, result.elbo_trace, result.iterations, result.converged

    return jax.vmap(one)(states)


def _stack(states: list[CaviState]) -> CaviState:
    return jax.tree.map(lambda *xs: jnp.stack(xs), *states)


def _index(states: CaviState, b: int) -> CaviState:
    return jax.tree.map(lambda x: x[b], states)


# --------------------------------------------------------------------------- search
def search(
    state: CaviState,
    data: CaviData,
    hyper: CaviHyper,
    *,
    tol: float = 1e-8,
    move_iter: int = 300,
    partial_sweeps: int = 10,
    max_moves: int | None = None,
    max_merges: int = 6,
    max_splits: int = 3,
    seed: int = 0,
) -> SearchResult:
    """Greedy split-and-merge search from ``state`` (module docstring).

    Each round proposes the top ``max_merges`` merges and ``max_splits`` splits, runs
    them and the unchanged state together (:func:`run_candidates`; the batch always
    has 1 + ``max_merges`` + ``max_splits`` slots, so it compiles once per data shape)
    and moves to the best candidate when :func:`accept` holds; it stops after a round
    without an accepted move or after ``max_moves`` moves (default 2K).
    """
    K = state.M_mean.shape[0]
    max_moves = 2 * K if max_moves is None else max_moves
    slots = 1 + max_merges + max_splits
    tol_arr = jnp.asarray(tol, jnp.float64)
    limit = jnp.asarray(move_iter, jnp.int32)
    rng = np.random.default_rng(seed)
    compile_seconds = [0.0]

    def run_batch(states):
        while len(states) < slots:
            states.append(states[0])
        args = (_stack(states), data, hyper, tol_arr, limit)
        executable, seconds = compiled(run_candidates, args, buffer=move_iter, partial_sweeps=partial_sweeps)
        compile_seconds[0] += seconds
        out_states, traces, iterations, _ = executable(*args)
        traces, iterations = np.asarray(traces), np.asarray(iterations)
        finals = np.array([traces[b, n - 1] if n > 0 else -np.inf for b, n in enumerate(iterations)])
        return out_states, traces, iterations, finals

    # the start: full sweeps only (partial_sweeps of the batch are harmless for a converged start)
    out, traces, iterations, finals = run_batch([state])
    state, best = _index(out, 0), float(finals[0])
    trace = [traces[0, : iterations[0]]]
    moves: list[Move] = []
    best_elbos = [best]
    while len(moves) < max_moves:
        proposals: list[tuple[Move, CaviState]] = []
        for k, l in merge_candidates(state, data)[:max_merges]:
            proposals.append((Move("merge", (k, l)), merge_state(state, hyper, k, l)))
        free = [j for j in range(K) if not bool(state.active[j])]
        if free:
            for k in split_candidates(state, hyper)[:max_splits]:
                moved = split_state(state, data, hyper, k, free[0], int(rng.integers(2**31 - 1)))
                if moved is not None:
                    proposals.append((Move("split", (k, free[0])), moved))
        if not proposals:
            break
        out, traces, iterations, finals = run_batch([state] + [s for _, s in proposals])
        reference = float(finals[0])
        candidates = finals[1 : 1 + len(proposals)]
        b = int(np.argmax(np.where(np.isfinite(candidates), candidates, -np.inf)))
        if accept(float(candidates[b]), reference) and accept(float(candidates[b]), best):
            moves.append(proposals[b][0])
            state, best = _index(out, 1 + b), float(candidates[b])
            trace.append(traces[1 + b, : iterations[1 + b]])
            best_elbos.append(best)
            continue
        if reference > best:  # keep the further sweeps of the unchanged state
            state, best = _index(out, 0), reference
            trace.append(traces[0, : iterations[0]])
        best_elbos.append(best)
        break
    return SearchResult(state, best, np.concatenate(trace), moves, best_elbos, compile_seconds[0])


def fit_with_search(
    starts,
    data: CaviData,
    hyper: CaviHyper,
    *,
    tol: float,
    max_iter: int,
    max_moves: int | None,
    seed: int,
    callback: Callable[[int, float], None] | None = None,
) -> CaviFit:
    """:func:`search` from every start, then full CAVI to ``tol`` / ``max_iter``; the best final bound wins.

    ``callback(sweeps, ELBO)`` reports the final runs' sweeps (of all starts together).
    """
    best, restart_elbos, seconds, compile_seconds, offset = None, [], 0.0, 0.0, 0
    for r, start in enumerate(starts):
        begin = time.perf_counter()
        found = search(start, data, hyper, tol=tol, max_moves=max_moves, seed=seed + r)
        searched = time.perf_counter() - begin - found.compile_seconds
        compile_seconds += found.compile_seconds
        report = None if callback is None else (lambda done, value, o=offset: callback(o + done, value))
        result = run(found.state, data, hyper, float(tol), int(max_iter), callback=report)
        offset += result.iterations
        seconds += searched + result.seconds
        compile_seconds += result.compile_seconds
        trace = result.elbo_trace
        final = check_restart_bound(float(trace[-1]) if trace.size else found.elbo, r)
        restart_elbos.append(final)
        full_trace = np.concatenate([found.trace, trace])
        if best is None or final > best[0]:
            best = (final, result, full_trace)
    final, result, trace = best
    return best_fit(result, final, trace, seconds, compile_seconds, restart_elbos, tol=tol, max_iter=max_iter)

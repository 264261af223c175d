r"""Plain-word warnings about a fit that is degenerate, whatever the engine.

A fit can optimise or sample the declared model correctly and still describe
the demonstrations badly.  :func:`degeneracy_warnings` checks the symptoms seen
on real recordings (docs/defaults.md):

* **not converged**: the optimiser stopped at its iteration limit, or NUTS
  reported divergent transitions;
* **mean carried by M h**: the demonstrations' control variables share a
  common offset, :math:`\lVert \frac1L\sum_i E[h_i] \rVert` above
  :data:`H_MEAN_LIMIT` prior standard deviations :math:`\gamma^{-1/2}`.  The
  prior puts ``h`` at 0, so the mean movement belongs in ``b``; when it is
  carried by a column of ``M``, that column's ARD precision, the movement
  distribution and conditioning through ``h`` are all distorted.  The norm is
  taken per draw (it is invariant to rotations of the latent space) and
  averaged.  When ``M`` and the basis are known the warning also needs the
  movement that offset carries, :math:`\Psi M \bar h` (RMS over phase and DoF,
  standardised units, per draw and averaged), above :data:`MOVEMENT_LIMIT`:
  under NUTS a latent dimension the data do not need has a small column of
  ``M`` and ``h`` drawn from the prior, whose mean over L demonstrations is
  :math:`\sqrt{V/L}` prior s.d. from 0 by chance (0.65 for V = 3, L = 7) and
  carries no movement;
* **weights far beyond the data's scale**: :math:`\max_i \lVert E[w_i]
  \rVert_\infty` above :data:`WEIGHT_LIMIT` in standardised units (data of
  unit spread are fitted by weights of order one with a well-conditioned
  basis);
* **every latent dimension switched off**: ARD removed all columns of ``M``
  (``active_latent_dims`` empty), so the model is a ProMP with an isotropic
  weight covariance;
* **a mixture component that copies another**: two active components whose
  mean movements differ by less than :data:`COPY_DISTANCE` (RMS over the
  phase, standardised units) and whose spreads differ by less than 10 %.

Each warning is one sentence a person can read; ``fit``, ``compare`` and
``summary.json`` (key ``warnings``) show them.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from lmpromp_ppl.basis import DEFAULT_WIDTH, rbf_basis

__all__ = ["H_MEAN_LIMIT", "MOVEMENT_LIMIT", "WEIGHT_LIMIT", "COPY_DISTANCE", "degeneracy_warnings", "result_warnings"]

#: Largest mean of E[h_i] (in prior standard deviations) before "mean carried by M h".
H_MEAN_LIMIT = 0.5
#: Largest RMS movement (standardised units) that M times the mean of E[h_i] may carry.
MOVEMENT_LIMIT = 0.1
#: Largest |E[w]| (standardised units) before "weights far beyond the data's scale".
WEIGHT_LIMIT = 10.0
#: Largest RMS distance of two components' mean movements (standardised units) for a copy.
COPY_DISTANCE = 0.05


def _h_mean(h: np.ndarray, resp: np.ndarray | None) -> np.ndarray:
    """Mean of h over demonstrations, per sample and component: ``h`` (S, L, K, V) -> (S, K, V).

    ``resp`` (L, K) weights the demonstrations per component.
    """
    if resp is None:
        weights = np.full(h.shape[1:3], 1.0 / h.shape[1])
    else:
        weights = np.asarray(resp, dtype=float) / np.maximum(np.sum(resp, axis=0, keepdims=True), 1e-12)
    return np.einsum("lk,slkv->skv", weights, h)


def _h_offset(h: np.ndarray, gamma: float, resp: np.ndarray | None) -> np.ndarray:
    """Norm of the mean of h over demonstrations, per sample and component, in prior s.d.: (S, K)."""
    return np.linalg.norm(_h_mean(h, resp), axis=-1) * np.sqrt(gamma)


def _carried_movement(h, M, resp, num_dofs: int, num_basis: int, width: float) -> np.ndarray:
    r"""RMS over phase and DoF of :math:`\Psi M \bar h` per sample and component (standardised units): (S, K).

    ``h`` (S, L, K, V) and ``M`` (S, K, d, V) from the same draws (or the posterior mean, S = 1).
    """
    movement = _movements(np.einsum("skdv,skv->skd", M, _h_mean(h, resp)), num_dofs, num_basis, width)
    return np.sqrt(np.mean(movement**2, axis=(-2, -1)))


def _movements(weights: np.ndarray, num_dofs: int, num_basis: int, width: float) -> np.ndarray:
    r"""Movements :math:`\Psi v` of weight vectors on 50 phases: ``weights`` (..., d) -> (..., 50, D)."""
    phi = np.asarray(rbf_basis(np.linspace(0, 1, 50), num_basis, width))
    return np.einsum("pj,...cj->...pc", phi, weights.reshape(weights.shape[:-1] + (num_dofs, num_basis)))


def degeneracy_warnings(
    model: str,
    *,
    point: Mapping[str, np.ndarray],
    summary: Mapping | None = None,
    draws: Mapping[str, np.ndarray] | None = None,
    gamma: float = 1.0,
    num_dofs: int | None = None,
    num_basis: int | None = None,
    width: float = DEFAULT_WIDTH,
    resp: np.ndarray | None = None,
    active: list[int] | None = None,
) -> list[str]:
    """Warnings (module docstring) for one fit; empty when none applies.

    Parameters
    ----------
    model : ``"lmpromp"``, ``"mixture"`` or ``"promp"``
    point : posterior means (``h``, ``w``, ``b``, ``alpha``, ``M``; standardised units)
    summary : the fit summary (``converged``, ``iterations``, ``divergences``,
        ``active_latent_dims``)
    draws : draws with leading (chain, draw) dims, used for the rotation-invariant
        ``h`` offset when present (NUTS, SVI); otherwise ``point["h"]``
    gamma : prior precision of ``h``
    num_dofs, num_basis, width : the basis, for the movement carried by M h and the mixture's copy check
    resp : (L, K) responsibilities of the mixture's demonstrations
    active : indices of the mixture's active components (default: all)
    """
    summary = summary or {}
    out: list[str] = []
    if summary.get("converged") is False:
        its = summary.get("iterations")
        out.append(f"not converged: the optimiser stopped after {its} iterations before meeting its tolerance")
    divergences = summary.get("divergences")
    if divergences:
        out.append(f"not converged: NUTS reported {int(divergences)} divergent transitions")
    if model == "promp":
        return out
    mixture = model == "mixture"
    h = M = None
    if draws is not None and "h" in draws:
        h = np.asarray(draws["h"], dtype=float)
        h = h.reshape((-1,) + h.shape[2:])  # (S, L, [K,] V)
        if "M" in draws:
            M = np.asarray(draws["M"], dtype=float)
            M = M.reshape((-1,) + M.shape[2:])  # (S, [K,] d, V)
    elif "h" in point:
        h = np.asarray(point["h"], dtype=float)[None]
        if "M" in point:
            M = np.asarray(point["M"], dtype=float)[None]
    if h is not None:
        if h.ndim == 3:
            h = h[:, :, None, :]
        if M is not None and M.ndim == 3:
            M = M[:, None]
        if mixture and resp is None and h.shape[2] > 1:
            h = None  # without responsibilities the per-component mean is undefined
    if h is not None:
        which = resp if mixture else None
        offset = _h_offset(h, gamma, which).mean(axis=0)  # (K,)
        movement = None
        if M is not None and num_dofs and num_basis and M.shape[-2] == num_dofs * num_basis:
            movement = _carried_movement(h, M, which, num_dofs, num_basis, width).mean(axis=0)
        components = range(offset.shape[0]) if active is None or not mixture else active
        for k in components:
            if offset[k] > H_MEAN_LIMIT and (movement is None or movement[k] > MOVEMENT_LIMIT):
                where = f" of component {k}" if mixture else ""
                carried = "" if movement is None else \
                    f" and M E[h] moves the mean movement by {movement[k]:.2g} data s.d. (limit {MOVEMENT_LIMIT})"
                out.append(
                    f"mean movement carried by M h{where}: the demonstrations' E[h] average "
                    f"{offset[k]:.2g} prior s.d. from 0 (limit {H_MEAN_LIMIT}){carried}; the offset b should "
                    f"carry it (a weaker prior on b, smaller lambda0, helps)"
                )
    if "w" in point:
        wmax = float(np.max(np.abs(np.asarray(point["w"]))))
        if wmax > WEIGHT_LIMIT:
            out.append(
                f"weights far beyond the data's scale: max |E[w]| = {wmax:.3g} on standardised data "
                f"(limit {WEIGHT_LIMIT:g}); the basis is probably too wide or too fine for the data"
            )
    dims = summary.get("active_latent_dims")
    if dims is not None:
        lists = dims if dims and isinstance(dims[0], list) else [dims]
        if mixture and active is not None:
            lists = [lists[k] for k in active if k < len(lists)]
        if lists and all(len(x) == 0 for x in lists):
            out.append("every latent dimension is switched off (ARD): the fit is a ProMP with an isotropic weight covariance")
    if mixture and num_dofs and num_basis and "b" in point and "alpha" in point:
        out.extend(_copies(point, active, num_dofs, num_basis, width, gamma))
    return out


def _copies(point, active, num_dofs, num_basis, width, gamma) -> list[str]:
    b = np.asarray(point["b"], dtype=float)
    if b.ndim != 2:
        return []
    K = b.shape[0]
    active = list(range(K)) if active is None else list(active)
    means = _movements(b, num_dofs, num_basis, width)
    alpha = np.asarray(point["alpha"], dtype=float).reshape(K)
    spread = 1.0 / alpha
    if "M" in point:
        M = np.asarray(point["M"], dtype=float)
        spread = spread + np.einsum("kdv,kdv->k", M, M) / (gamma * M.shape[1])
    out = []
    for i, k in enumerate(active):
        for l in active[i + 1:]:
            dist = float(np.sqrt(np.mean((means[k] - means[l]) ** 2)))
            ratio = spread[k] / spread[l]
            if dist < COPY_DISTANCE and 0.9 < ratio < 1.0 / 0.9:
                out.append(
                    f"mixture components {k} and {l} are copies: their mean movements differ by {dist:.2g} "
                    f"(RMS, standardised units) and their spreads by {abs(1 - ratio):.0%}"
                )
    return out


def result_warnings(result) -> list[str]:
    """:func:`degeneracy_warnings` of a :class:`~lmpromp_ppl.results.FitResult` (fresh or loaded)."""
    state = getattr(result, "state", None)
    resp = getattr(state, "resp", None)
    active = result.summary.get("active_components")
    return degeneracy_warnings(
        result.model,
        point=result.point,
        summary=result.summary,
        draws=result.draws,
        gamma=result.hyper.gamma,
        num_dofs=result.num_dofs,
        num_basis=result.num_basis,
        width=result.width,
        resp=None if resp is None else np.asarray(resp),
        active=active,
    )

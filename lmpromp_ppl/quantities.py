r"""Identifiable quantities computed from posterior draws (stored by results, compared by diagnostics).

M and h are identifiable only up to a rotation (and sign) of the latent space,
and mixture components only up to a relabelling, so engines are compared on
quantities that do not depend on either:

* ``gram_eig``: the eigenvalues of :math:`M M^T`, descending (its nonzero
  eigenvalues are those of the V x V matrix :math:`M^T M`);
* ``pred_mean``, ``pred_sd``: the mean and standard deviation of the
  movement distribution :math:`p(\tau)` of a new demonstration at each phase,
  with the weight prior integrated out — for the LMProMP
  :math:`w \sim N(b, \alpha^{-1} I + \gamma^{-1} M M^T)`; for the mixture the
  moment-matched mixture of its components; for the ProMP
  :math:`N(\mu_w, \Sigma_w)`.  Observation noise :math:`\beta^{-1}` is not
  included (it is the movement, not the measurement).  Units are those of
  the data (the fit's per-DoF scaling is undone).
"""

from __future__ import annotations

import numpy as np

from lmpromp_ppl.basis import DEFAULT_WIDTH, rbf_basis
from lmpromp_ppl.data.core import Scaling

__all__ = [
    "gram_eigenvalues",
    "trajectory_moments",
    "derived_quantities",
    "sorted_lam",
    "active_rank",
    "active_projector",
    "identifiable_quantities",
    "invariant_quantities",
]


def gram_eigenvalues(M: np.ndarray) -> np.ndarray:
    """Eigenvalues of :math:`M M^T`, descending: ``M`` (..., d, V) -> (..., V)."""
    M = np.asarray(M)
    gram = np.einsum("...dv,...du->...vu", M, M)
    eig = np.linalg.eigvalsh(gram)
    return np.clip(eig[..., ::-1], 0.0, None)


def _block(x: np.ndarray, num_dofs: int, num_basis: int) -> np.ndarray:
    """Split the weight axis (axis -2 or -1) into (dof, basis)."""
    return x.reshape(x.shape[:-1] + (num_dofs, num_basis))


def trajectory_moments(
    model: str,
    draws: dict,
    *,
    num_dofs: int,
    num_basis: int,
    gamma: float,
    phase: np.ndarray,
    width: float = DEFAULT_WIDTH,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-draw mean and s.d. of the movement distribution, (..., phase, dof).

    ``draws`` holds arrays with arbitrary leading sample dims and the site
    names of docs/cli.md.  Results are in standardised units.
    """
    phi = np.asarray(rbf_basis(phase, num_basis, width))  # (P, J)
    if model == "promp":
        mu = _block(np.asarray(draws["mu_w"]), num_dofs, num_basis)  # (..., D, J)
        mean = np.einsum("pj,...kj->...pk", phi, mu)
        cov = np.asarray(draws["Sigma_w"])
        cov = cov.reshape(cov.shape[:-2] + (num_dofs, num_basis, num_dofs, num_basis))
        cov_kk = np.einsum("...kjkl->...kjl", cov)  # diagonal DoF blocks
        var = np.einsum("pj,...kjl,pl->...pk", phi, cov_kk, phi)
        return mean, np.sqrt(np.clip(var, 0.0, None))

    b = np.asarray(draws["b"])
    M = np.asarray(draws["M"])
    alpha = np.asarray(draws["alpha"])
    b_blk = _block(b, num_dofs, num_basis)  # (..., [K,] D, J)
    M_blk = M.reshape(M.shape[:-2] + (num_dofs, num_basis, M.shape[-1]))  # (..., [K,] D, J, V)
    mean = np.einsum("pj,...kj->...pk", phi, b_blk)
    proj = np.einsum("pj,...kjv->...pkv", phi, M_blk)
    var = (np.sum(phi**2, axis=1)[:, None] / alpha[..., None, None]) + np.sum(proj**2, axis=-1) / gamma
    if model == "lmpromp":
        return mean, np.sqrt(var)
    if model == "mixture":
        pi = np.asarray(draws["pi"])[..., :, None, None]  # (..., K, 1, 1)
        mix_mean = np.sum(pi * mean, axis=-3)
        second = np.sum(pi * (var + mean**2), axis=-3)
        return mix_mean, np.sqrt(np.clip(second - mix_mean**2, 0.0, None))
    raise ValueError(f"unknown model {model!r}")


def derived_quantities(
    model: str,
    draws: dict,
    *,
    num_dofs: int,
    num_basis: int,
    gamma: float,
    scaling: Scaling | None = None,
    num_phases: int = 50,
    width: float = DEFAULT_WIDTH,
) -> dict[str, np.ndarray]:
    """``gram_eig``, ``pred_mean``, ``pred_sd`` and ``phase`` for the ``derived`` group."""
    phase = np.linspace(0.0, 1.0, num_phases)
    mean, sd = trajectory_moments(
        model, draws, num_dofs=num_dofs, num_basis=num_basis, gamma=gamma, phase=phase, width=width
    )
    if scaling is not None:
        mean = scaling.invert(mean)
        sd = scaling.invert_sd(sd)
    out = {"pred_mean": mean, "pred_sd": sd, "phase": phase}
    if model != "promp":
        out["gram_eig"] = gram_eigenvalues(draws["M"])
    return out


def sorted_lam(lam: np.ndarray) -> np.ndarray:
    """Column precisions sorted ascending along the last axis (most active column first).

    Sorting removes the arbitrary order of the latent columns, which a
    rotation of the latent space permutes (:mod:`lmpromp_ppl.diagnostics.alignment`).
    """
    return np.sort(np.asarray(lam), axis=-1)


def active_rank(gram_eig: np.ndarray, threshold: float = 1e-3) -> int:
    """Number of active latent dims: mean eigenvalues of M M^T above ``threshold`` times the largest.

    ``gram_eig`` is (..., V) with any leading dims (draws, components); the
    eigenvalues are averaged over all but the last axis.  Mirrors the ARD rule
    of docs/cli.md (``active_latent_dims``).
    """
    mean = np.asarray(gram_eig, dtype=float).reshape(-1, np.shape(gram_eig)[-1]).mean(axis=0)
    if not np.any(mean > 0):
        return 0
    return int(np.sum(mean > threshold * mean.max()))


def active_projector(M: np.ndarray, rank: int) -> np.ndarray:
    r"""Orthogonal projector onto the span of the ``rank`` leading eigenvectors of :math:`M M^T`.

    ``M`` (..., d, V) -> (..., d, d).  Invariant to :math:`M \to M R` for any
    orthogonal R, so comparable across engines without alignment; with
    ``rank`` = V it is the projector onto M's column space.
    """
    M = np.asarray(M, dtype=float)
    if not 0 <= rank <= M.shape[-1]:
        raise ValueError(f"rank must lie in [0, {M.shape[-1]}], got {rank}")
    u, _, _ = np.linalg.svd(M, full_matrices=False)  # singular values descending
    u = u[..., :rank]
    return np.einsum("...iv,...jv->...ij", u, u)


def identifiable_quantities(model: str, draws: dict, derived: dict, *, rank: int | None = None) -> dict[str, np.ndarray]:
    """The quantities engines are compared on, from aligned draws and their derived group.

    Parameters
    ----------
    model : ``"lmpromp"``, ``"mixture"`` or ``"promp"``
    draws : site draws with leading sample dims, mixture components already
        relabelled and ``M`` Procrustes-aligned (:func:`lmpromp_ppl.diagnostics.alignment.align_draws`)
    derived : output of :func:`derived_quantities` for the same draws
    rank : active latent dims for ``projector`` (default: :func:`active_rank` of these draws)

    Returns
    -------
    ``b``, ``alpha``, ``lam`` (sorted), ``gram_eig`` (recomputed from the
    relabelled ``M``), ``projector``, ``M_aligned``, ``pred_mean``, ``pred_sd``,
    ``w`` for the LMProMP models; ``mu_w``, ``pred_mean``, ``pred_sd``, ``w``
    for the ProMP.  Sites missing from ``draws`` are left out.
    """
    out: dict[str, np.ndarray] = {}
    for name in ("b", "alpha", "mu_w"):
        if name in draws:
            out[name] = np.asarray(draws[name])
    if "lam" in draws:
        out["lam"] = sorted_lam(draws["lam"])
    if model != "promp" and "M" in draws:
        out["gram_eig"] = gram_eigenvalues(draws["M"])
        r = active_rank(out["gram_eig"]) if rank is None else rank
        out["projector"] = active_projector(draws["M"], r)
        out["M_aligned"] = np.asarray(draws["M"])
    for name in ("pred_mean", "pred_sd"):
        if name in derived:
            out[name] = np.asarray(derived[name])
    if "w" in draws:
        out["w"] = np.asarray(draws["w"])
    return out


def invariant_quantities(samples) -> dict[str, np.ndarray]:
    r"""Quantities of single-type LMProMP draws that do not depend on the latent rotation or column order.

    Straight from the sites, without alignment: the quantities the benchmarks
    judge a NUTS run's R-hat and ESS on.

    Parameters
    ----------
    samples : site name -> (..., site shape) draws of a single-type LMProMP

    Returns
    -------
    dict with ``b`` (..., d), ``alpha`` (...), ``lam_sorted`` (..., V),
    ascending, and ``gram_eig`` (..., V), the eigenvalues of
    :math:`\mathbf M \mathbf M^T`, descending.
    """
    M = np.asarray(samples["M"])
    gram = np.einsum("...dv,...du->...vu", M, M)
    return {
        "b": np.asarray(samples["b"]),
        "alpha": np.asarray(samples["alpha"]),
        "lam_sorted": np.sort(np.asarray(samples["lam"]), axis=-1),
        "gram_eig": np.clip(np.linalg.eigvalsh(gram)[..., ::-1], 0.0, None),
    }

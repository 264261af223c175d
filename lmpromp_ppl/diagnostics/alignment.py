r"""Removing the non-identifiabilities of the LMProMP before comparing draws.

Two symmetries leave the likelihood unchanged (thesis Sec. 4.1, 4.2):

* **Rotation and sign of the latent space.**  For any orthogonal
  :math:`R` (:math:`R R^T = I`), :math:`\mathbf M \mathbf h_i =
  (\mathbf M R)(R^T \mathbf h_i)` and :math:`R^T \mathbf h_i` has the same
  :math:`\mathcal N(0, \gamma^{-1} I)` prior, so :math:`(\mathbf M, \mathbf h)`
  and :math:`(\mathbf M R, \mathbf h R)` (rows of ``h``) explain the data
  equally well.  With ARD the column precisions :math:`\lambda_v` pin the
  columns down only up to a permutation and a sign each; columns with equal
  scale can still rotate into each other.  Column-wise comparisons of ``M``
  (or ``h``) therefore come after an orthogonal Procrustes alignment of each
  draw to a common reference (:func:`procrustes_rotations`, which uses
  the solution of :func:`scipy.linalg.orthogonal_procrustes` in one batched SVD).
* **Label switching.**  The mixture's likelihood is invariant to permuting
  the components, so every component-indexed site (``b``, ``M``, ``alpha``,
  ``lam``, ``pi``, ``h``, ``gram_eig``; the values of ``z``) is relabelled
  draw by draw to match a reference (:func:`component_permutations`: the
  assignment of :func:`scipy.optimize.linear_sum_assignment` on the squared
  distances between the component offsets :math:`\mathbf b_k`) before any
  metric or R-hat.

The references are built from the NUTS draws themselves by iterating
"align every draw to the reference, replace the reference by the mean of the
aligned draws" (generalized Procrustes / a Stephens-type relabelling), and
then shared by every engine so that all are compared in one frame.
"""

from __future__ import annotations

from typing import Mapping, NamedTuple

import numpy as np
from scipy.optimize import linear_sum_assignment

__all__ = [
    "COMPONENT_AXIS",
    "Reference",
    "procrustes_rotations",
    "procrustes_reference",
    "component_permutations",
    "relabel_reference",
    "relabel_components",
    "build_reference",
    "align_draws",
]

#: Position of the ``component`` dim among the non-sample dims of each
#: component-indexed site (docs/cli.md); ``z`` holds component labels as values.
COMPONENT_AXIS: dict[str, int] = {"b": 0, "M": 0, "alpha": 0, "lam": 0, "pi": 0, "gram_eig": 0, "h": 1}


def procrustes_rotations(M: np.ndarray, reference: np.ndarray) -> np.ndarray:
    r"""Orthogonal :math:`R = \arg\min_{R^T R = I} \|\mathbf M R - \mathbf M_{ref}\|_F` per draw.

    Parameters
    ----------
    M : (..., d, V) draws
    reference : (d, V)

    Returns
    -------
    R : (..., V, V); ``M @ R`` is aligned and ``h @ R`` the matching control variables
    """
    M = np.asarray(M, dtype=float)
    reference = np.asarray(reference, dtype=float)
    if M.ndim < 2 or M.shape[-2:] != reference.shape:
        raise ValueError(f"M {M.shape} must end in the reference's shape {reference.shape}")
    # R = U V^T from the SVD U S V^T of M^T M_ref (as scipy.linalg.orthogonal_procrustes; a test),
    # every draw in one batched SVD
    u, _, vt = np.linalg.svd(np.swapaxes(M, -1, -2) @ reference)
    return u @ vt


def procrustes_reference(M: np.ndarray, num_iter: int = 20, tol: float = 1e-10) -> np.ndarray:
    """Generalized Procrustes mean of draws ``M`` (n, d, V): the reference frame of the latent space.

    Starts from the first draw and alternates aligning every draw to the
    reference with replacing the reference by the mean of the aligned draws.
    """
    M = np.asarray(M, dtype=float)
    if M.ndim != 3:
        raise ValueError(f"M must be (draws, d, V), got {M.shape}")
    reference = M[0]
    for _ in range(num_iter):
        aligned = M @ procrustes_rotations(M, reference)
        new = aligned.mean(axis=0)
        change = np.linalg.norm(new - reference) / max(np.linalg.norm(new), 1e-300)
        reference = new
        if change < tol:
            break
    return reference


def component_permutations(b: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Per draw, the permutation that best matches components to the reference.

    Parameters
    ----------
    b : (n, K, d) component offsets of n draws
    reference : (K, d) reference offsets

    Returns
    -------
    perm : (n, K) ints; relabelled component ``k`` of draw ``s`` is old component
        ``perm[s, k]`` (minimises the summed squared distance to the reference)
    """
    b = np.asarray(b, dtype=float)
    reference = np.asarray(reference, dtype=float)
    if b.ndim != 3 or b.shape[1:] != reference.shape:
        raise ValueError(f"b {b.shape} must be (draws,) + the reference's shape {reference.shape}")
    cost = np.sum((reference[None, :, None, :] - b[:, None, :, :]) ** 2, axis=-1)  # (n, K_ref, K)
    perm = np.empty(b.shape[:2], dtype=int)
    for s in range(b.shape[0]):
        rows, cols = linear_sum_assignment(cost[s])
        perm[s, rows] = cols
    return perm


def relabel_reference(b: np.ndarray, num_iter: int = 20) -> np.ndarray:
    """Reference component offsets (K, d) from draws ``b`` (n, K, d), iterating relabel-then-average."""
    b = np.asarray(b, dtype=float)
    reference = b[0]
    for _ in range(num_iter):
        perm = component_permutations(b, reference)
        new = np.take_along_axis(b, perm[:, :, None], axis=1).mean(axis=0)
        if np.allclose(new, reference, rtol=0.0, atol=1e-12):
            break
        reference = new
    return reference


def relabel_components(draws: Mapping[str, np.ndarray], perm: np.ndarray, sample_ndim: int = 1) -> dict:
    """Apply per-draw component permutations to every component-indexed site.

    Parameters
    ----------
    draws : site name -> array with ``sample_ndim`` leading sample dims
    perm : sample shape + (K,) permutations from :func:`component_permutations`
    sample_ndim : number of leading sample dims (2 for (chain, draw))

    Returns
    -------
    dict with the same keys; sites without a component dim are unchanged,
    ``z`` values are mapped to the new labels.
    """
    perm = np.asarray(perm)
    sample_shape = perm.shape[:-1]
    if len(sample_shape) != sample_ndim:
        raise ValueError(f"perm {perm.shape} must have {sample_ndim} sample dims and one component dim")
    num_components = perm.shape[-1]
    out = {}
    for name, value in draws.items():
        value = np.asarray(value)
        axis = COMPONENT_AXIS.get(name)
        if name == "z":
            inverse = np.argsort(perm, axis=-1)  # old label -> new label
            out[name] = np.take_along_axis(inverse, value.astype(int), axis=-1)
            continue
        if axis is None or value.ndim <= sample_ndim + axis or value.shape[sample_ndim + axis] != num_components:
            out[name] = value
            continue
        index = perm.reshape(sample_shape + (1,) * axis + (num_components,) + (1,) * (value.ndim - sample_ndim - axis - 1))
        out[name] = np.take_along_axis(value, index, axis=sample_ndim + axis)
    return out


class Reference(NamedTuple):
    """A common frame for comparing engines.

    Attributes
    ----------
    b : (K, d) component offsets used for relabelling, or None (single-type model)
    M : ([K,] d, V) Procrustes reference of ``M``, or None (ProMP baseline)
    """

    b: np.ndarray | None
    M: np.ndarray | None


def _merge_samples(x: np.ndarray, sample_ndim: int) -> np.ndarray:
    return x.reshape((-1,) + x.shape[sample_ndim:])


def build_reference(model: str, draws: Mapping[str, np.ndarray], sample_ndim: int = 2) -> Reference:
    """Reference frame from (NUTS) draws: relabelling offsets, then Procrustes means of ``M``."""
    b_ref = None
    if model == "mixture":
        b_ref = relabel_reference(_merge_samples(np.asarray(draws["b"]), sample_ndim))
        draws = align_draws(model, draws, Reference(b_ref, None), sample_ndim)
    if "M" not in draws:
        return Reference(b_ref, None)
    M = _merge_samples(np.asarray(draws["M"], dtype=float), sample_ndim)
    if model == "mixture":
        M_ref = np.stack([procrustes_reference(M[:, k]) for k in range(M.shape[1])])
    else:
        M_ref = procrustes_reference(M)
    return Reference(b_ref, M_ref)


def align_draws(model: str, draws: Mapping[str, np.ndarray], reference: Reference, sample_ndim: int = 2) -> dict:
    """Relabel components (mixture) and rotate ``M`` and ``h`` into the reference frame.

    Returns a new dict; ``M`` becomes ``M R`` and ``h`` becomes ``h R`` per draw
    (and per component), which leaves ``M h`` and every identifiable quantity
    unchanged.
    """
    out = {k: np.asarray(v) for k, v in draws.items()}
    sample_shape = next(iter(out.values())).shape[:sample_ndim] if out else ()
    if model == "mixture" and reference.b is not None:
        b = _merge_samples(out["b"], sample_ndim)
        perm = component_permutations(b, reference.b).reshape(sample_shape + (reference.b.shape[0],))
        out = relabel_components(out, perm, sample_ndim)
    if reference.M is None or "M" not in out:
        return out
    M = out["M"].astype(float)
    if model == "mixture":
        rot = np.stack([procrustes_rotations(M[..., k, :, :], reference.M[k]) for k in range(M.shape[sample_ndim])],
                       axis=sample_ndim)  # sample + (K, V, V)
        out["M"] = M @ rot
        if "h" in out:  # (sample, L, K, V) @ (sample, 1, K, V, V)
            h = out["h"].astype(float)
            out["h"] = np.einsum("...lkv,...kvu->...lku", h, rot)
    else:
        rot = procrustes_rotations(M, reference.M)  # sample + (V, V)
        out["M"] = M @ rot
        if "h" in out:
            out["h"] = out["h"].astype(float) @ rot
    return out

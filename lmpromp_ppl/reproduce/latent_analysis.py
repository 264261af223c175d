r"""``latent-analysis``: GunPoint in the latent control space, the analogue of the golf study (thesis Sec. 5.3, Fig. 5.8).

An LMProMP (V = 10) is fitted to all of GunPoint (train and test splits
together, classes Gun-Draw and Point, as the golf study pools novices and
experts).  The latent coordinates :math:`E[\mathbf h_i]` of the two leading
dimensions (by column norm of M) are drawn coloured by class and by split, with
the column scales :math:`1/E[\lambda_v]` (ARD).  Numbers: active dimensions,
the share of :math:`\|M\|_F^2` in the first two columns, and the
leave-one-out accuracy of a nearest-class-mean rule on the two latent
coordinates (against the first two principal components of the ridge weights).
"""

from __future__ import annotations

import numpy as np

from lmpromp_ppl.data import load_dataset
from lmpromp_ppl.data.core import Demonstrations
from lmpromp_ppl.inference.classical import classical_promp
from lmpromp_ppl.reproduce._common import (
    Claim,
    Context,
    ExperimentOutput,
    fit_lmpromp,
    matplotlib_figure,
    save_figure,
    standardised_model_data,
)

__all__ = ["nearest_mean_accuracy", "run"]


def nearest_mean_accuracy(x: np.ndarray, labels: np.ndarray) -> float:
    """Leave-one-out accuracy of assigning each point to the class with the nearest mean (of the others)."""
    correct = 0
    classes = sorted(set(labels))
    for i in range(len(x)):
        keep = np.arange(len(x)) != i
        means = [x[keep & (labels == c)].mean(axis=0) for c in classes]
        guess = classes[int(np.argmin([np.linalg.norm(x[i] - m) for m in means]))]
        correct += guess == labels[i]
    return correct / len(x)


def _pooled(quick: bool) -> tuple[Demonstrations, np.ndarray]:
    train, test = load_dataset("gunpoint:train"), load_dataset("gunpoint:test")
    if quick:
        train, test = train.subset(np.arange(4)), test.subset(np.arange(4))
    demos = Demonstrations(train.times + test.times, train.positions + test.positions,
                           np.concatenate([train.labels, test.labels]), train.dof_names, "gunpoint:train+test")
    split = np.array(["train"] * train.num_demos + ["test"] * test.num_demos)
    return demos, split


def run(context: Context) -> ExperimentOutput:
    """Fit GunPoint, draw Fig. 5.8 as ``latent-analysis.png``."""
    demos, split = _pooled(context.quick)
    J, V = (8, 3) if context.quick else (10, 10)
    J = context.settings.num_basis(J)
    data, _, _ = standardised_model_data(demos, J, width=context.settings.width)
    fit = fit_lmpromp(data, context.settings.hyper.replace(latent_dim=V), context.seed)
    M, h = np.asarray(fit.params["M"]), np.asarray(fit.params["h"])
    norms = np.linalg.norm(M, axis=0)
    order = np.argsort(-norms)
    coords = h[:, order[:2]] * norms[order[:2]]
    inverse = 1.0 / np.asarray(fit.params["lam"])
    active = int(np.sum(inverse > 1e-3 * inverse.max()))
    share = float(np.sum(norms[order[:2]] ** 2) / np.sum(norms**2))
    labels = np.asarray(demos.labels)
    accuracy = nearest_mean_accuracy(coords, labels)
    _, _, w_hat = classical_promp(data)
    centred = w_hat - w_hat.mean(axis=0)
    pcs = centred @ np.linalg.svd(centred, full_matrices=False)[2][:2].T
    pca_accuracy = nearest_mean_accuracy(pcs, labels)
    n = len(labels)
    accuracy_se = float(np.sqrt(accuracy * (1 - accuracy) / n))
    split_gap = float(np.linalg.norm(coords[split == "train"].mean(0) - coords[split == "test"].mean(0))
                      / np.sqrt(np.mean(np.var(coords, axis=0))))
    fig, axes = matplotlib_figure(1, 3, (13, 4))
    for name, color in zip(sorted(set(labels)), ("tab:blue", "tab:red")):
        axes[0, 0].scatter(*coords[labels == name].T, s=12, color=color, label=name, alpha=0.7)
    for name, marker in (("train", "o"), ("test", "x")):
        axes[0, 1].scatter(*coords[split == name].T, s=14, marker=marker, label=name, alpha=0.7)
    for ax, title in zip(axes[0, :2], ("(A) by class", "(B) by split")):
        ax.set_xlabel("latent dim 1 (scaled by |m_1|)")
        ax.set_ylabel("latent dim 2 (scaled by |m_2|)")
        ax.set_title(title)
        ax.legend(fontsize=8)
    axes[0, 2].bar(np.arange(V), np.sort(inverse)[::-1])
    axes[0, 2].set_yscale("log")
    axes[0, 2].set_title("(C) column scales 1/E[lambda_v]")
    save_figure(fig, context.out / "latent-analysis.png")
    numbers = {
        "active_dims": active,
        "latent_dim": V,
        "first_two_share": share,
        "column_scales": np.sort(inverse)[::-1].tolist(),
        "class_accuracy_latent": accuracy,
        "class_accuracy_latent_se": accuracy_se,
        "class_accuracy_pca": pca_accuracy,
        "split_mean_gap_sd": split_gap,
        "converged": fit.converged,
    }
    claims = [
        Claim(
            claim="The model keeps only the latent dimensions the data need: the others shrink to zero",
            thesis="Sec. 5.3, Fig. 5.8C (golf)",
            measured=f"{active} of {V} latent dimensions active (1/E[lam] > 1e-3 max); first two carry {100 * share:.0f} % of |M|_F^2",
            verdict="holds" if active < V and share > 0.5 else ("holds partly" if active < V or share > 0.5 else "does not hold"),
        ),
        Claim(
            claim="Groups of movements (novices vs experts in golf; here Gun-Draw vs Point) are distinguishable in the first two latent dimensions",
            thesis="Sec. 5.3, Fig. 5.8A-B",
            measured=(f"LOO nearest-class-mean accuracy on the two latent coordinates {accuracy:.3f} ± {accuracy_se:.3f} "
                      f"(chance 0.5; first two PCs of the ridge weights: {pca_accuracy:.3f})"),
            verdict="holds" if accuracy - 2 * accuracy_se > 0.5 else ("holds partly" if accuracy > 0.5 else "does not hold"),
        ),
    ]
    section = (
        f"GunPoint train + test pooled ({n} movements), J = {J}, V = {V}. Active dimensions: {active}; the first two "
        f"carry {100 * share:.0f} % of |M|_F^2. Class accuracy (LOO nearest class mean) on the two latent coordinates: "
        f"{accuracy:.3f} ± {accuracy_se:.3f}; on the first two PCs of the ridge weights: {pca_accuracy:.3f}. "
        f"Distance between the train and test means in latent space: {split_gap:.2f} pooled s.d."
    )
    return ExperimentOutput(numbers=numbers, section=section, claims=claims,
                            sizes={"gunpoint": {"demonstrations": n, "num_basis": J, "latent_dim": V}},
                            figures=["latent-analysis.png"])

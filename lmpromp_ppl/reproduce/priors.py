r"""``priors``: ProMP, LMProMP and mixture priors on four clusters of weights (thesis Sec. 5.1, Fig. 5.3).

Synthetic data (:func:`lmpromp_ppl.data.four_clusters`): weight vectors on four
clusters arranged on a circle in a 2-D plane U of the weight space.  The first
half of the demonstrations trains the ProMP, the LMProMP (V = 2) and the
mixture (K = 2, V = 2, as in the thesis); the second half is held out.  The
priors are drawn projected onto U (Fig. 5.3); the numbers are the held-out
prior predictive log density of whole test trajectories (per row, mean ±
standard error over test demonstrations) and the distance of each prior mean
(or component mean) from the nearest cluster centre, measured as the RMS
distance between their trajectories in units of the circle's radius (the
weights themselves are poorly identified by least squares with overlapping
basis functions, so the ProMP's weight mean is noisy even where its
trajectory is not).
"""

from __future__ import annotations

import numpy as np

from lmpromp_ppl.basis import rbf_basis
from lmpromp_ppl.data.synthetic import GENERATOR_WIDTH, four_clusters
from lmpromp_ppl.predict import observe, prior, score_heldout
from lmpromp_ppl.reproduce._common import (
    Claim,
    Context,
    ExperimentOutput,
    fit_lmpromp,
    fit_mixture,
    fit_promp,
    matplotlib_figure,
    mean_se,
    save_figure,
    standardised_model_data,
)

__all__ = ["run"]


def _ellipse(ax, mean2: np.ndarray, cov2: np.ndarray, color: str, label: str | None = None) -> None:
    values, vectors = np.linalg.eigh(cov2)
    angle = np.linspace(0, 2 * np.pi, 100)
    circle = np.stack([np.cos(angle), np.sin(angle)])
    points = mean2[:, None] + 2 * vectors @ (np.sqrt(np.maximum(values, 0))[:, None] * circle)
    ax.plot(points[0], points[1], color=color, lw=2, label=label)


def run(context: Context) -> ExperimentOutput:
    """Fit the three priors, score held-out trajectories, draw Fig. 5.3 as ``priors.png``."""
    num = 16 if context.quick else 80
    T = 20 if context.quick else 50
    # the fits use the generator's basis whatever the settings: the clusters' plane U
    # and centres live in its weight space (only the hyperparameters follow the settings)
    J, width = 8, GENERATOR_WIDTH
    demos = four_clusters(L=num, D=1, J=J, T=T, seed=context.seed)
    meta = demos.metadata
    train, test = np.arange(num // 2), np.arange(num // 2, num)
    data, scaling, _ = standardised_model_data(demos.subset(train), J, width=width)
    hyper = context.settings.hyper.replace(latent_dim=2)
    fits = {
        "promp": fit_promp(data),
        "lmpromp": fit_lmpromp(data, hyper, context.seed),
        "mixture": fit_mixture(data, hyper.replace(num_components=2), context.seed, restarts=3),
    }
    gamma = hyper.gamma
    # standardisation of one DoF with a normalised basis maps weights affinely: w_s = (w - m) / s
    shift, scale = float(scaling.mean[0]), float(scaling.scale[0])
    U = np.asarray(meta["subspace"])
    centres = (np.asarray(meta["centres"]) - shift) / scale
    # distances are measured between mean trajectories (weights are poorly identified by least squares)
    grid = np.linspace(0.0, 1.0, 200)
    phi = np.asarray(rbf_basis(grid, J, width))
    centre_paths = centres @ phi.T
    radius = float(np.sqrt(np.mean((centre_paths[0] - phi @ ((np.asarray(meta["b"]) - shift) / scale)) ** 2)))
    noise_sd = 1.0 / np.sqrt(float(meta["beta"])) / scale
    sites = {"promp": ("mu_w", "Sigma_w"), "lmpromp": ("b", "M", "alpha"), "mixture": ("pi", "b", "M", "alpha")}
    numbers, densities = {}, {}
    for name, fit in fits.items():
        params = {k: fit.params[k] for k in sites[name]}
        predictive = prior(name, params, gamma).weights
        per_demo = []
        for i in test:
            y = scaling.apply(demos.positions[i])
            target = observe(demos.phases()[i], y, noise_sd=noise_sd, num_dofs=1, num_basis=J, width=width)
            per_demo.append(float(score_heldout(predictive, target).log_density_per_row))
        densities[name] = per_demo
        means = np.asarray(predictive.means)
        weights = np.asarray(predictive.weights)
        distance = [float(np.min(np.sqrt(np.mean((centre_paths - phi @ m) ** 2, axis=1))) / radius) for m in means]
        lpd, lpd_se = mean_se(per_demo)
        numbers[name] = {
            "heldout_lpd_mean": lpd,
            "heldout_lpd_se": lpd_se,
            "mean_to_nearest_centre": distance,
            "component_weights": weights.tolist(),
            "plane_variance": [float(np.trace(U.T @ c @ U)) for c in np.asarray(predictive.covs)],
            "converged": fit.converged,
        }
    for name in ("lmpromp", "mixture"):
        diff = [a - b for a, b in zip(densities[name], densities["promp"])]
        numbers[name]["lpd_gain_over_promp_mean"], numbers[name]["lpd_gain_over_promp_se"] = mean_se(diff)
    diff = [a - b for a, b in zip(densities["mixture"], densities["lmpromp"])]
    numbers["mixture"]["lpd_gain_over_lmpromp_mean"], numbers["mixture"]["lpd_gain_over_lmpromp_se"] = mean_se(diff)
    within = np.asarray(meta["coords"])
    cluster = np.asarray(meta["cluster"])
    numbers["cluster_plane_variance"] = float(np.mean([np.trace(np.cov(within[cluster == k].T)) for k in range(4)])) / scale**2
    numbers["lmpromp"]["conditional_plane_variance"] = 2.0 / float(fits["lmpromp"].params["alpha"])
    _figure(demos, train, fits, U, shift, scale, centres, context.out / "priors.png")
    promp_distance = numbers["promp"]["mean_to_nearest_centre"][0]
    mix = numbers["mixture"]
    claims = [
        Claim(
            claim="The ProMP prior averages over all movement types: its mean lies away from every demonstrated cluster",
            thesis="Sec. 5.1, Fig. 5.3A",
            measured=f"distance of the ProMP mean from the nearest cluster centre: {promp_distance:.2f} radii",
            verdict="holds" if promp_distance > 0.5 else "does not hold",
        ),
        Claim(
            claim="The mixture prior models the four movement types more accurately than the ProMP and single-type priors",
            thesis="Sec. 5.1, Fig. 5.3C",
            measured=(f"held-out prior predictive log density per row: ProMP {numbers['promp']['heldout_lpd_mean']:.3f} ± "
                      f"{numbers['promp']['heldout_lpd_se']:.3f}, LMProMP {numbers['lmpromp']['heldout_lpd_mean']:.3f} ± "
                      f"{numbers['lmpromp']['heldout_lpd_se']:.3f}, mixture {mix['heldout_lpd_mean']:.3f} ± {mix['heldout_lpd_se']:.3f}; "
                      f"mixture - ProMP {mix['lpd_gain_over_promp_mean']:.3f} ± {mix['lpd_gain_over_promp_se']:.3f}, "
                      f"mixture - LMProMP {mix['lpd_gain_over_lmpromp_mean']:.3f} ± {mix['lpd_gain_over_lmpromp_se']:.3f} (paired over test demos)"),
            verdict=_verdict(mix),
        ),
        Claim(
            claim="Given h, the single-type LMProMP prior is tight, about the spread of one cluster",
            thesis="Sec. 5.1, Fig. 5.3B",
            measured=(f"in-plane variance of alpha^-1 I: {numbers['lmpromp']['conditional_plane_variance']:.3g}; mean in-plane "
                      f"variance of a cluster: {numbers['cluster_plane_variance']:.3g}; ProMP prior in-plane variance: "
                      f"{numbers['promp']['plane_variance'][0]:.3g} (std. units)"),
            verdict="holds" if numbers["lmpromp"]["conditional_plane_variance"] < 2 * numbers["cluster_plane_variance"] else "does not hold",
        ),
    ]
    table = ["| model | held-out log dens. / row | mean trajectory to nearest centre (radii) | component weights |", "|---|---|---|---|"]
    for name in sites:
        n = numbers[name]
        table.append(f"| {name} | {n['heldout_lpd_mean']:.3f} ± {n['heldout_lpd_se']:.3f} | "
                     f"{', '.join(f'{d:.2f}' for d in n['mean_to_nearest_centre'])} | "
                     f"{', '.join(f'{w:.2f}' for w in n['component_weights'])} |")
    section = "\n\n".join([
        f"four_clusters with L = {num} (first {num // 2} train, rest held out), D = 1, J = {J}, T = {T}. "
        "Panels: ProMP (A), LMProMP with its 2 latent directions (B, red, +-2 s.d. of h), mixture K = 2 (C); "
        "ellipses are 2 s.d. of each prior projected onto the cluster plane; points are the demonstrations' "
        "true weights (standardised).",
        "\n".join(table),
    ])
    return ExperimentOutput(numbers=numbers, section=section, claims=claims,
                            sizes={"four_clusters": {"L": num, "train": num // 2, "T": T, "J": J}},
                            figures=["priors.png"])


def _verdict(mix: dict) -> str:
    over_promp = mix["lpd_gain_over_promp_mean"] > 2 * mix["lpd_gain_over_promp_se"]
    over_single = mix["lpd_gain_over_lmpromp_mean"] > 2 * mix["lpd_gain_over_lmpromp_se"]
    if over_promp and over_single:
        return "holds"
    return "holds partly" if over_promp or over_single else "does not hold"


def _figure(demos, train, fits, U, shift, scale, centres, path) -> None:
    meta = demos.metadata
    w = (np.asarray(meta["w"])[train] - shift) / scale
    cluster = np.asarray(meta["cluster"])[train]
    fig, axes = matplotlib_figure(1, 3, (13, 4.2))
    colors = ["tab:blue", "tab:orange", "tab:green", "tab:purple"]
    titles = ("(A) ProMP", "(B) LMProMP, single type", "(C) mixture of LMProMPs")
    for ax, title in zip(axes[0], titles):
        for k in range(4):
            xy = w[cluster == k] @ U
            ax.scatter(xy[:, 0], xy[:, 1], s=14, color=colors[k], alpha=0.7)
        ax.scatter(*(centres @ U).T, marker="x", color="k")
        ax.set_title(title)
        ax.set_aspect("equal", adjustable="datalim")
    p = fits["promp"].params
    _ellipse(axes[0, 0], p["mu_w"] @ U, U.T @ p["Sigma_w"] @ U, "k")
    q = fits["lmpromp"].params
    b, M, alpha = np.asarray(q["b"]), np.asarray(q["M"]), float(q["alpha"])
    _ellipse(axes[0, 1], b @ U, U.T @ (np.eye(b.size) / alpha + M @ M.T) @ U, "k")
    _ellipse(axes[0, 1], b @ U, U.T @ (np.eye(b.size) / alpha) @ U, "gray")
    for v in range(M.shape[1]):
        ends = np.stack([b - 2 * M[:, v], b + 2 * M[:, v]]) @ U
        axes[0, 1].plot(ends[:, 0], ends[:, 1], color="red", lw=2)
    r = fits["mixture"].params
    for k in range(np.asarray(r["pi"]).size):
        if float(r["pi"][k]) <= 0:
            continue
        bk, Mk, ak = np.asarray(r["b"][k]), np.asarray(r["M"][k]), float(r["alpha"][k])
        _ellipse(axes[0, 2], bk @ U, U.T @ (np.eye(bk.size) / ak + Mk @ Mk.T) @ U, "k")
        for v in range(Mk.shape[1]):
            ends = np.stack([bk - 2 * Mk[:, v], bk + 2 * Mk[:, v]]) @ U
            axes[0, 2].plot(ends[:, 0], ends[:, 1], color="red", lw=1.5)
    save_figure(fig, path)

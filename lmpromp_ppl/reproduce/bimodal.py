r"""``bimodal``: ProMP vs mixture of LMProMPs on bimodal movements (thesis Sec. 5.4, Figs. 5.9, 5.10).

Two parts.

* The 7-D obstacle-reaching data (:func:`lmpromp_ppl.data.obstacle_reaching`,
  half the demonstrations pass the obstacle on the left, half on the right):
  ProMP, LMProMP and mixture (K = 2) are conditioned on new goal positions
  (via-points at phase 1, drawn uniformly inside the box of the demonstrated
  goals), 100 trajectories are sampled from each conditioned distribution,
  and the fraction entering the obstacle is counted
  (:func:`lmpromp_ppl.data.count_collisions`); also for the conditioned mean
  trajectories (for the mixture: the mean of its most responsible component
  and the mixture's overall mean).
* LASA ``Multi_Models_*`` shapes: leave-one-out, conditioning on the held-out
  movement's start point (every LASA movement ends at the origin, so the end
  carries no information) and scoring the rest of it, as in the noise experiment.
"""

from __future__ import annotations

import jax
import numpy as np

from lmpromp_ppl.data import count_collisions, load_dataset, obstacle_reaching
from lmpromp_ppl.predict import condition, sample_trajectories, trajectory_distribution, via_point
from lmpromp_ppl.reproduce._common import (
    Claim,
    Context,
    ExperimentOutput,
    matplotlib_figure,
    mean_se,
    progress_bar,
    save_figure,
    standardised_model_data,
)
from lmpromp_ppl.reproduce.prediction import (
    MODEL_NAMES,
    Setting,
    Task,
    fit_models,
    gain_counts,
    loo_sweep,
    sweep_table,
    verdict_from_counts,
)

__all__ = ["run"]

_SITES = {"promp": ("mu_w", "Sigma_w"), "lmpromp": ("b", "M", "alpha"), "mixture": ("pi", "b", "M", "alpha")}


def _reaching(context: Context, bar) -> tuple[dict, object]:
    L, T, goals, draws = (8, 30, 2, 20) if context.quick else (20, 100, 10, 100)
    settings = context.settings
    J, V, width = settings.num_basis(8), 3, settings.width
    hyper = settings.hyper.replace(latent_dim=V, num_components=2)
    demos = obstacle_reaching(L=L, T=T, seed=context.seed)
    meta = demos.metadata
    data, scaling, _ = standardised_model_data(demos, J, width=width)
    fits = fit_models(data, hyper, MODEL_NAMES, context.seed)
    ends = np.stack([p[-1, :3] for p in demos.positions])
    rng = np.random.default_rng([context.seed, 5])
    targets = rng.uniform(ends.min(axis=0), ends.max(axis=0), size=(goals, 3))
    phase = np.linspace(0.0, 1.0, 100)
    key = jax.random.key(context.seed)
    samples = {m: [] for m in fits}
    means = {m: [] for m in fits}
    component_means = []
    examples = {}
    for g, target in enumerate(targets):
        obs = via_point(1.0, target, dofs=[0, 1, 2], position_sd=0.005, num_dofs=7, num_basis=J, width=width,
                        scaling=scaling)
        for name, fit in fits.items():
            conditioned = condition(name, {k: fit.params[k] for k in _SITES[name]}, obs, hyper.gamma, exact=True)
            key, sub = jax.random.split(key)
            paths = scaling.invert(np.asarray(sample_trajectories(sub, conditioned.weights, phase, draws, num_dofs=7,
                                                                  num_basis=J, width=width)))
            samples[name].append(count_collisions(paths, meta) / draws)
            moments = trajectory_distribution(conditioned.weights, phase, num_dofs=7, num_basis=J, width=width)
            mean_path = scaling.invert(np.asarray(moments.mean))
            means[name].append(float(count_collisions(mean_path, meta)))
            if name == "mixture":
                best = int(np.argmax(np.asarray(moments.component_weights)))
                component_means.append(float(count_collisions(scaling.invert(np.asarray(moments.component_means[best])), meta)))
            if g == 0:
                examples[name] = paths[:20]
        bar.update()
    numbers = {"goals": goals, "samples_per_goal": draws, "demonstrations": L,
               "demo_collisions": count_collisions(demos.positions, meta)}
    for name in fits:
        numbers[name] = {}
        numbers[name]["sample_collision_mean"], numbers[name]["sample_collision_se"] = mean_se(samples[name])
        numbers[name]["mean_path_collision_mean"], numbers[name]["mean_path_collision_se"] = mean_se(means[name])
    numbers["mixture"]["top_component_mean_collision_mean"], numbers["mixture"]["top_component_mean_collision_se"] = \
        mean_se(component_means)
    numbers["mixture"]["active_components"] = int(np.sum(np.asarray(fits["mixture"].params["pi"]) > 0))
    diff = [a - b for a, b in zip(samples["promp"], samples["mixture"])]
    numbers["promp_minus_mixture_mean"], numbers["promp_minus_mixture_se"] = mean_se(diff)
    return numbers, (demos, examples, targets)


def run(context: Context) -> ExperimentOutput:
    """Run both parts; figure ``bimodal.png``."""
    if context.quick:
        shapes = [("Multi_Models_1", "lasa:Multi_Models_1?every=50", 8, (0, 1, 2))]
    else:
        shapes = [(f"Multi_Models_{k}", f"lasa:Multi_Models_{k}?every=20", 10, None) for k in range(1, 5)]
    goals = 2 if context.quick else 10
    total = goals + sum(3 if f else 7 for *_, f in shapes)
    with progress_bar(total, "bimodal", context.progress) as bar:
        reaching, (demos, examples, targets) = _reaching(context, bar)
        lasa = {}
        for label, spec, J, folds in shapes:
            d = load_dataset(spec)
            task = Task(f"LASA {label}", d, context.settings.num_basis(J), 3, folds or tuple(range(d.num_demos)),
                        context.settings.width)
            lasa[task.label] = loo_sweep(task, [Setting(observed_fraction=0.0)], context.settings.hyper, MODEL_NAMES,
                                         context.seed, bar)
    _figure(demos, examples, targets, context.out / "bimodal.png")
    p, m = reaching["promp"], reaching["mixture"]
    wins, losses, n = gain_counts(lasa, "mixture", "lpd")
    rwins, rlosses, _ = gain_counts(lasa, "mixture", "rmse")
    claims = [
        Claim(
            claim="Conditioned on new targets, ProMP trajectories pass through the obstacle while the mixture's avoid it",
            thesis="Sec. 5.4, Figs. 5.9, 5.10",
            measured=(f"fraction of sampled trajectories entering the obstacle: ProMP {p['sample_collision_mean']:.3f} ± "
                      f"{p['sample_collision_se']:.3f}, LMProMP {reaching['lmpromp']['sample_collision_mean']:.3f} ± "
                      f"{reaching['lmpromp']['sample_collision_se']:.3f}, mixture {m['sample_collision_mean']:.3f} ± "
                      f"{m['sample_collision_se']:.3f} (s.e. over {reaching['goals']} goals); mean trajectories colliding: "
                      f"ProMP {p['mean_path_collision_mean']:.2f}, mixture's top component {m['top_component_mean_collision_mean']:.2f}"),
            verdict=_collision_verdict(reaching),
        ),
        Claim(
            claim="The mixture represents multi-modal movements better than the ProMP (LASA Multi_Models, prediction from the start point)",
            thesis="Sec. 5.4",
            measured=(f"held-out log density: mixture better than ProMP beyond 2 s.e. in {wins}/{n} shapes, worse in {losses}; "
                      f"RMSE: better in {rwins}/{n}, worse in {rlosses}"),
            verdict=verdict_from_counts(wins, losses, n),
        ),
    ]
    table = ["| model | sampled trajectories in obstacle | conditioned mean in obstacle |", "|---|---|---|"]
    for name in MODEL_NAMES:
        r = reaching[name]
        table.append(f"| {name} | {r['sample_collision_mean']:.3f} ± {r['sample_collision_se']:.3f} | "
                     f"{r['mean_path_collision_mean']:.2f} ± {r['mean_path_collision_se']:.2f} |")
    table.append(f"| mixture, most responsible component | | {m['top_component_mean_collision_mean']:.2f} ± "
                 f"{m['top_component_mean_collision_se']:.2f} |")
    section = "\n\n".join([
        f"Obstacle reaching: {reaching['demonstrations']} demonstrations ({reaching['demo_collisions']} collide), "
        f"{reaching['goals']} new goals, {reaching['samples_per_goal']} samples per goal and model; the mixture "
        f"kept {m['active_components']} components. Figure: x-y paths (top view) of 20 samples for the first goal.",
        "\n".join(table),
        "LASA Multi_Models, leave-one-out, conditioned on the start point, scored on the rest:",
        sweep_table(lasa, "observed_fraction", MODEL_NAMES),
    ])
    sizes = {"reaching": {"L": reaching["demonstrations"], "goals": reaching["goals"], "samples": reaching["samples_per_goal"]},
             **{k: {"folds": v[0]["models"]["promp"]["folds"]} for k, v in lasa.items()}}
    return ExperimentOutput(numbers={"reaching": reaching, "lasa": lasa}, section=section, claims=claims, sizes=sizes,
                            figures=["bimodal.png"])


def _collision_verdict(reaching: dict) -> str:
    p, m = reaching["promp"], reaching["mixture"]
    better = reaching["promp_minus_mixture_mean"] > 2 * reaching["promp_minus_mixture_se"]
    if better and m["sample_collision_mean"] < 0.05:
        return "holds"
    return "holds partly" if better or m["sample_collision_mean"] < p["sample_collision_mean"] else "does not hold"


def _figure(demos, examples, targets, path) -> None:
    meta = demos.metadata
    fig, axes = matplotlib_figure(1, 3, (13, 4))
    angle = np.linspace(0, 2 * np.pi, 100)
    centre, radius = np.asarray(meta["obstacle_centre"]), float(meta["obstacle_radius"])
    for ax, name in zip(axes[0], MODEL_NAMES):
        for p in demos.positions:
            ax.plot(p[:, 0], p[:, 1], color="0.75", lw=0.8)
        for p in examples[name]:
            ax.plot(p[:, 0], p[:, 1], color="tab:blue", lw=0.8, alpha=0.7)
        ax.plot(centre[0] + radius * np.cos(angle), centre[1] + radius * np.sin(angle), color="red")
        ax.scatter(targets[0, 0], targets[0, 1], marker="*", color="k", s=80, zorder=5)
        ax.set_title(f"{name}: conditioned samples (grey: demonstrations)")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_aspect("equal", adjustable="datalim")
    save_figure(fig, path)

"""Writing ``report.md``, ``report.html`` and the PNG figures of ``lmpromp compare``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lmpromp_ppl.diagnostics.metrics import ESS_MIN, KHAT_GOOD, KHAT_USABLE, RHAT_MAX, khat_verdict
from lmpromp_ppl.reports import figures
from lmpromp_ppl.reports.render import (
    Alert, Figure, Heading, Paragraph, Table, format_ess, format_number, format_rhat, to_html, to_markdown,
)

__all__ = ["write_report", "IDENTIFIABILITY_TEXT", "METRICS_TEXT"]

IDENTIFIABILITY_TEXT = (
    "The projection `M` and the control variables `h` are not identifiable on their own. "
    "A demonstration's weights depend on them only through the product `M h`, and for any rotation "
    "or reflection `R` of the latent space (an orthogonal matrix, including flipping the sign of a "
    "latent axis or swapping two axes) `M h = (M R)(R^T h)`, with `R^T h` just as likely under the "
    "prior. So two engines can find the same posterior in different orientations, and two NUTS "
    "chains can too. In the same way the mixture's components can be numbered in any order "
    "(label switching). This report therefore compares quantities that do not depend on either "
    "choice: the offset `b`, the weight precision `alpha`, the column precisions `lam` sorted, "
    "the eigenvalues `gram_eig` of `M M^T`, the projector onto the active column space of `M`, "
    "the predictive mean and standard deviation of a new demonstration at each phase, and each "
    "demonstration's weights `w`. Where `M` or `h` are compared or plotted column by column, each "
    "draw is first rotated onto a common reference by orthogonal Procrustes alignment "
    "(the reference is the Procrustes mean of the NUTS draws). For the mixture, each draw's "
    "components are first renumbered to match the NUTS reference (an optimal assignment on the "
    "distances between component offsets `b_k`), and only then are metrics and R-hat computed."
)

METRICS_TEXT = (
    "All metrics compare one scalar at a time (each element of a quantity) and use the NUTS "
    "standard deviation as the unit. **smd** is the standardised mean difference "
    "(VI mean minus NUTS mean, in NUTS sd); the table shows its largest absolute value. "
    "**sd ratio** is VI sd divided by NUTS sd: 1 means the same spread, below 1 means the "
    "approximation is too confident (mean-field VI typically under-disperses), above 1 too "
    "uncertain; the table shows the median over elements. **wasserstein** is the 1-D "
    "Wasserstein (earth mover's) distance between the two marginals, in NUTS sd (largest over "
    "elements). **coverage90** is the fraction of NUTS draws inside the VI central 90 % interval, "
    "averaged over elements: 0.90 when the marginals agree, lower when VI is too narrow or shifted. "
    f"The **Pareto k-hat** (Yao et al. 2018) fits a generalized Pareto tail to the importance "
    f"ratios p(theta, y) / q(theta) of draws from the approximation: below {KHAT_GOOD} the "
    f"approximation is good, {KHAT_GOOD} to {KHAT_USABLE} usable, above {KHAT_USABLE} unreliable "
    "(importance sampling could not even correct it). It judges the whole joint approximation, "
    "including every demonstration's `w` and `h`, so it is often high in many dimensions even when "
    "the identifiable marginals agree well. The joint Wasserstein distance and the KL(NUTS || VI) "
    "nearest-neighbour estimate (arviz-stats) use the standardised global quantities "
    "(b, alpha, lam, gram_eig) jointly."
)


def _fmt(x, digits: int = 3) -> str:
    return format_number(x, digits)


def _predictive_band(q: dict) -> tuple[np.ndarray, np.ndarray]:
    """Mean and sd of a new demonstration's position, mixing over posterior draws."""
    mean, sd = q["pred_mean"], q["pred_sd"]
    return mean.mean(axis=0), np.sqrt((sd**2).mean(axis=0) + mean.var(axis=0))


def _latent_coords(model: str, details: dict) -> tuple[dict, str, tuple[str, str]]:
    """Two coordinates per demonstration for the latent figure, its title and its axis labels."""
    aligned = details["aligned"]
    if model == "lmpromp" and all("h" in a and a["h"].shape[-1] >= 1 for a in aligned.values()):
        coords = {}
        for name, a in aligned.items():
            h = a["h"].mean(axis=0)
            coords[name] = h[:, :2] if h.shape[1] >= 2 else np.c_[np.arange(h.shape[0]), h[:, 0]]
        one = any(a["h"].shape[-1] < 2 for a in aligned.values())
        labels = ("demonstration", "h, latent dim 1") if one else ("h, latent dim 1", "h, latent dim 2")
        return coords, "posterior mean of h, Procrustes-aligned to the NUTS reference (latent dims 1 and 2)", labels
    w_ref = aligned["nuts"]["w"].mean(axis=0)
    centre = w_ref.mean(axis=0)
    _, _, vt = np.linalg.svd(w_ref - centre, full_matrices=False)
    basis = vt[:2].T
    coords = {name: (a["w"].mean(axis=0) - centre) @ basis for name, a in aligned.items()}
    return (coords, "posterior mean of w projected on the first two principal axes of the NUTS posterior mean",
            ("w, principal axis 1", "w, principal axis 2"))


def write_report(out: Path, metrics: dict, results: dict, details: dict, demos) -> list[Path]:
    """Write the figures, ``report.md`` and ``report.html`` into ``out``; return the figure paths."""
    out = Path(out)
    model = metrics["model"]
    engines = metrics["engines"]
    vi = [e for e in engines if e != "nuts"]
    paths = []

    traces = figures.plot_traces({e: results[e].optimization for e in vi}, out / "traces.png")
    marg = figures.plot_marginals(details["quantities"], out / "marginals.png",
                                  names=("alpha", "lam", "gram_eig", "b", "mu_w"))
    forest = figures.plot_sd_ratios(
        {e: {q: c.sd_ratio for q, c in details["comparisons"][e].items() if q != "M_aligned"} for e in vi},
        out / "sd_ratios.png")
    bands = {e: _predictive_band(details["quantities"][e]) for e in engines}
    pred = figures.plot_predictive(bands, details["phase"], demos, out / "predictive.png")
    coords, coord_title, coord_labels = _latent_coords(model, details)
    latent = figures.plot_latent(coords, demos.labels, out / "latent.png", coord_title, coord_labels)
    paths = [p for p in (traces, marg, forest, pred, latent) if p is not None]

    hyper = metrics["hyperparameters"]
    blocks = [
        Heading(f"lmpromp compare: {model} on {metrics['dataset']}", 1),
        Paragraph(
            f"Engines: {', '.join(engines)}. NUTS is the reference. All engines share one set of "
            f"hyperparameters, the `{metrics['preset']}` preset with V = {hyper['latent_dim']}"
            + (f", K = {hyper['num_components']}" if model == "mixture" else "")
            + f" and J = {metrics['num_basis']} basis functions per DoF, so they approximate the same "
            f"posterior. Seed {metrics['seed']}."
        ),
        Paragraph(
            "Files: `metrics.json` (the numbers below), `report.md` and the self-contained `report.html`, "
            "the PNG figures, and for each engine `<engine>/posterior.nc` (ArviZ DataTree, netCDF) with "
            "`<engine>/summary.json`; load one with `lmpromp_ppl.load(DIR/<engine>)`. VI engines store "
            "draws from q as one chain. To keep the report small the files hold an evenly thinned subset "
            "of the draws (the metrics use them all); CAVI's file also holds the variational parameters, "
            "so `result.sampler(key, n)` re-samples q."
        ),
    ]
    nuts = engines["nuts"]
    problems = nuts.get("reliability_problems") or []
    blocks.append(Heading("Is the reference reliable?"))
    if problems:
        blocks.append(Alert(
            "THE NUTS REFERENCE IS UNRELIABLE: " + "; ".join(problems) + f". (Targets: R-hat <= {RHAT_MAX}, "
            f"bulk and tail ESS >= {ESS_MIN}, no divergences.) Differences between VI and NUTS below may "
            "come from NUTS itself; run more chains and draws (--chains, --warmup, --samples) before "
            "trusting them."))
    else:
        blocks.append(Paragraph(
            f"Yes: on the identifiable quantities R-hat <= {RHAT_MAX}, bulk and tail ESS >= {ESS_MIN}, "
            "and there were no divergent transitions."))
    per = details["reliability"]["per_quantity"]
    blocks.append(Table(
        ["quantity", "max R-hat", "min bulk ESS", "min tail ESS"],
        [[q, format_rhat(v["rhat_max"]), format_ess(v["ess_bulk_min"]), format_ess(v["ess_tail_min"])]
         for q, v in per.items()]
        + [["**all**", format_rhat(nuts["rhat_max"]), format_ess(nuts["ess_bulk_min"]),
            format_ess(nuts["ess_tail_min"])]],
        caption=f"NUTS: {_fmt(nuts['divergences'])} divergent transitions.",
    ))

    blocks.append(Heading("Engines"))
    rows = []
    for e, m in engines.items():
        k = m.get("psis_khat")
        rows.append([e, _fmt(m.get("seconds")), _fmt(m.get("compile_seconds")), _fmt(m.get("elbo"), 6),
                     _fmt(k) + ("" if e == "nuts" else f" ({khat_verdict(k)})"), _fmt(m.get("psis_khat_numpyro")),
                     _fmt((m.get("joint") or {}).get("wasserstein_joint")), _fmt((m.get("joint") or {}).get("kl_p_q"))])
    blocks.append(Table(["engine", "seconds", "compile s", "ELBO", "Pareto k-hat", "k-hat (numpyro)",
                         "joint W1", "KL(NUTS||VI)"], rows,
                        caption="Seconds exclude compilation. k-hat (numpyro): numpyro's generalized Pareto fit "
                                "of the same importance ratios, a cross-check of the arviz-stats fit."
                                + (" cavi_lr: seconds include the exact-conditional Gibbs sweeps of its draws; its "
                                   "k-hat is that of the linear-response Gaussian on the model with w and h "
                                   "integrated out, the draws before the sweeps (which have no closed-form density)."
                                   if "cavi_lr" in engines else "")))
    warned = [f"{e}: {w}" for e, m in engines.items() for w in m.get("warnings", [])]
    if warned:
        blocks.append(Alert("engine warnings (their results may not have converged): " + "; ".join(warned) + "."))
    degenerate = [f"{e}: {w}" for e, m in engines.items() for w in m.get("degeneracy", [])]
    if degenerate:
        blocks.append(Alert("degenerate fits (the model describes the demonstrations badly, whatever the engine): "
                            + "; ".join(degenerate) + "."))
    notes = [f"{e}: {m['psis_khat_note']}" for e, m in engines.items() if m.get("psis_khat_note")]
    if notes:
        blocks.append(Paragraph("k-hat notes: " + "; ".join(notes) + "."))

    blocks.append(Heading("How far is each approximation from NUTS?"))
    for quantities, title in ((("b", "alpha", "lam", "gram_eig", "pred_mean", "w"), "vs_nuts"),
                              (("pred_sd", "projector", "M_aligned", "mu_w"), "vs_nuts_extra")):
        rows = []
        for q in quantities:
            for e in vi:
                s = engines[e].get(title, {}).get(q)
                if s is not None:
                    rows.append([q, e, _fmt(s["smd_max_abs"]), _fmt(s["sd_ratio_median"]),
                                 _fmt(s["wasserstein_max"]), _fmt(s["coverage90"])])
        if rows:
            blocks.append(Table(["quantity", "engine", "max |smd|", "median sd ratio", "max W1", "coverage90"],
                                rows, caption=("Contract quantities (metrics.json `vs_nuts`)." if title == "vs_nuts"
                                               else "Further quantities (metrics.json `vs_nuts_extra`).")))
    blocks.append(Paragraph(METRICS_TEXT))
    blocks.append(Heading("Why M and h are not compared directly"))
    blocks.append(Paragraph(IDENTIFIABILITY_TEXT))

    blocks.append(Heading("Figures"))
    captions = {
        "traces.png": "Optimisation traces: the CAVI ELBO per sweep and the SVI loss (negative ELBO estimate) per step.",
        "marginals.png": "Marginal posterior densities of every engine overlaid (arviz-plots); at most 4 elements per quantity.",
        "sd_ratios.png": "Standard-deviation ratios VI / NUTS per quantity: dot = median over elements, line = range.",
        "predictive.png": "Predictive mean +- 2 sd of a new demonstration per engine (observation noise excluded), over the demonstrations.",
        "latent.png": f"Latent coordinates: {coord_title}" + (", coloured by label." if demos.labels is not None else "."),
    }
    blocks += [Figure(p, captions[p.name]) for p in paths]

    (out / "report.md").write_text(to_markdown(blocks))
    (out / "report.html").write_text(to_html(blocks, f"lmpromp compare: {model} on {metrics['dataset']}"))
    return paths

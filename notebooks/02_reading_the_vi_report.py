# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3 (ipykernel)
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 02 · Reading the VI report
#
# `lmpromp compare` (Python: `lmpromp_ppl.reports.compare`) fits one model
# with several engines under **one** set of hyperparameters and measures how
# far each variational approximation is from NUTS.  This notebook runs it on a
# small synthetic problem and reads the report:
#
# 1. is the NUTS reference itself reliable?
# 2. why $M$ (and $h$) are never compared directly;
# 3. what the standard-deviation ratio says (mean-field VI is over-confident);
# 4. what Pareto $\hat k$ says;
# 5. when to trust mean-field VI.
#
# Size knob: `LMPROMP_NOTEBOOK_SIZE=small` (tests) compares CAVI with NUTS
# run for 2 chains of 100 draws; `full` (default) adds every SVI guide and
# uses 2 x 1000 NUTS draws.  Small runs are for checking the code path, not for conclusions: the
# report will itself say that the reference is too short.

# %%
import os

SIZE = os.environ.get("LMPROMP_NOTEBOOK_SIZE", "full")
assert SIZE in ("small", "full"), f"LMPROMP_NOTEBOOK_SIZE must be small or full, got {SIZE!r}"
if SIZE == "small":
    DATASET = "synthetic:latent?L=6&D=2&J=4&V=2&seed=0"
    SETTINGS = dict(engines="cavi,nuts", num_basis=4, num_chains=2, num_warmup=100,
                    num_samples=100, num_draws=100)
else:
    DATASET = "synthetic:latent?L=12&D=2&J=5&V=2&seed=0"
    SETTINGS = dict(engines="cavi,svi,nuts", num_basis=5, num_chains=2, num_warmup=1000,
                    num_samples=1000, svi_steps=5000, num_draws=1000)
print(SIZE, DATASET, SETTINGS)

# %%
import tempfile
import warnings
from pathlib import Path

warnings.filterwarnings("ignore", message="IProgress not found")  # tqdm without ipywidgets

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from IPython.display import Image, Markdown, display

import lmpromp_ppl as lp
from lmpromp_ppl.reports import compare

plt.rcParams.update({"figure.dpi": 90, "axes.grid": True, "grid.alpha": 0.3})

# %% [markdown]
# ## Running the comparison
#
# The data come from the LMProMP's own generative model (eq. 4.1) with
# $V = 2$ true latent dimensions, so every engine fits a correctly specified
# model.  All engines share the `proper` preset: the thesis's near-improper
# Gamma(1e-5, 1e-5) priors cannot be sampled by NUTS.  The command line
# equivalent is
# `lmpromp compare DATASET --model lmpromp --engines cavi,svi,nuts --out DIR`.

# %%
out = Path(tempfile.mkdtemp()) / "report"
metrics = compare(DATASET, "lmpromp", out_dir=out, latent_dim=2, seed=0, progress=False, **SETTINGS)
engines = metrics["engines"]
print(sorted(p.name for p in out.iterdir()))

# %% [markdown]
# ## 1. Is the reference reliable?
#
# Every VI metric is measured against NUTS, so first check NUTS: split
# $\hat R \le 1.01$, bulk and tail effective sample sizes $\ge 400$ and no
# divergent transitions, on identifiable quantities.  When these fail the
# report opens with a warning, and differences between VI and NUTS may be
# NUTS's own error.

# %%
nuts = engines["nuts"]
print({k: nuts[k] for k in ("rhat_max", "ess_bulk_min", "ess_tail_min", "divergences")})
for problem in nuts["reliability_problems"] or ["none: the reference passes every check"]:
    print("-", problem)

# %% [markdown]
# ## 2. Why $M$ is not identifiable
#
# A demonstration's weights depend on $M$ and $h_i$ only through the product
# $M h_i$, and the prior of $h_i$, $\mathcal N(0, \gamma^{-1} I)$, is
# rotation invariant.  For any orthogonal $R$ (a rotation, a sign flip of a
# latent axis, a swap of two axes) $(MR, R^T h)$ explains the data exactly as
# well as $(M, h)$.  The columns of $M$ can also trade scale with $h$ in the
# posterior.  So two engines, or two NUTS chains, can report different $M$ for
# the same posterior.  Quantities that do not change under $R$ are
# comparable: the eigenvalues of $M M^T$ (`gram_eig`), the predictive mean
# and standard deviation of the trajectory, the weights $w$, $b$, $\alpha$,
# $\lambda$.  We check the invariance numerically with the CAVI fit.

# %%
cavi_fit = lp.load(out / "cavi")
M, h = np.asarray(cavi_fit.point["M"]), np.asarray(cavi_fit.point["h"])
theta = 0.7
R = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
print("max |M h - (M R)(R^T h)|      =", np.abs(h @ M.T - (h @ R) @ (M @ R).T).max())
print("max |M - M R|                 =", np.abs(M - M @ R).max())
print("eigenvalues of M M^T          =", np.round(np.linalg.eigvalsh(M @ M.T)[::-1][:2], 4))
print("eigenvalues of (MR)(MR)^T     =", np.round(np.linalg.eigvalsh(M @ R @ (M @ R).T)[::-1][:2], 4))

# %% [markdown]
# Before comparing, the report therefore Procrustes-aligns every engine's $M$
# to the NUTS reference and compares only identifiable quantities.  The
# NUTS draws of one raw entry of $M$ against the invariant `gram_eig` show the
# difference: per chain the raw entry may sit at either sign (or any
# rotation) while the eigenvalue distribution agrees across chains.

# %%
nuts_fit = lp.load(out / "nuts")
tree = nuts_fit.to_datatree()
M_draws = tree["posterior"]["M"].values  # (chain, draw, weight, latent)
gram = tree["derived"]["gram_eig"].values  # (chain, draw, latent)
fig, axes = plt.subplots(1, 2, figsize=(10, 3.2))
for c in range(M_draws.shape[0]):
    axes[0].hist(M_draws[c, :, 0, 0], bins=30, alpha=0.5, label=f"chain {c}")
    axes[1].hist(gram[c, :, 0], bins=30, alpha=0.5, label=f"chain {c}")
axes[0].set(title="raw M[0, 0] (not identifiable)", xlabel="value")
axes[1].set(title="largest eigenvalue of M M^T (identifiable)", xlabel="value")
axes[0].legend()
plt.tight_layout()

# %% [markdown]
# ## 3. The standard-deviation ratio
#
# For every element of every identifiable quantity the report divides the VI
# marginal standard deviation by the NUTS one and shows the median.  1 means
# the same spread; below 1 the approximation is **over-confident**.
# Mean-field families break the posterior correlations (between $w_i$ and
# $h_i$, between $M$ and $h$, between $\alpha$ and everything), and the
# reverse KL divergence that VI minimises prefers to under-cover: a factorised
# $q$ fitted to a correlated posterior has the conditional, not the marginal,
# variances.  `coverage90` tells the same story as a probability: the fraction
# of NUTS draws inside VI's central 90 % interval (0.9 when they agree).

# %%
rows = []
for name, e in engines.items():
    for q, m in (e.get("vs_nuts") or {}).items():
        rows.append({"engine": name, "quantity": q, "sd_ratio_median": m["sd_ratio_median"],
                     "coverage90": m["coverage90"], "smd_max_abs": m["smd_max_abs"]})
table = pd.DataFrame(rows)
display(table.pivot(index="quantity", columns="engine", values="sd_ratio_median").round(2))

# %%
pivot = table.pivot(index="quantity", columns="engine", values="sd_ratio_median")
ax = pivot.plot.bar(figsize=(8, 3.5), rot=0)
ax.axhline(1.0, color="k", lw=1)
ax.set(ylabel="median sd ratio VI / NUTS", title="below 1: VI is over-confident")
plt.tight_layout()

# %% [markdown]
# ## 4. Pareto $\hat k$
#
# $\hat k$ (Yao et al. 2018) fits a generalised Pareto tail to the importance
# ratios $p(\theta, y)/q(\theta)$ of draws from $q$.  Below 0.5 the
# approximation is good, 0.5-0.7 usable after importance reweighting, above
# 0.7 unreliable.  Unlike the marginal metrics it judges the *whole joint*
# $q$, including every $w_i$ and $h_i$: with dozens of dimensions and
# correlations that a mean-field $q$ cannot represent, $\hat k$ is usually far
# above 0.7 even when the identifiable marginals agree reasonably.  It answers
# "can I use $q$ as a proposal for exact inference?", not "is the predictive
# good enough?".

# %%
summary = pd.DataFrame({
    name: {"ELBO": e.get("elbo"), "Pareto k-hat": e.get("psis_khat"), "seconds": e.get("seconds"),
           "compile s": e.get("compile_seconds")}
    for name, e in engines.items()
}).T
display(summary.round(3))

# %% [markdown]
# ## 5. The report's own figures
#
# `report.md` and the self-contained `report.html` hold the tables above with
# explanations and these figures: the median sd ratios and the marginals of
# the identifiable quantities per engine.

# %%
for name in ("sd_ratios.png", "marginals.png"):
    if (out / name).exists():
        display(Image(filename=str(out / name), width=800))

# %%
report = (out / "report.md").read_text()
display(Markdown(report.split("## Engines")[0]))

# %% [markdown]
# ## When to trust mean-field VI
#
# * **Trust the reference first**: no VI verdict from a NUTS run that fails
#   its $\hat R$ / ESS / divergence checks (run more chains and draws).
# * **Predictive means** (`pred_mean`) and the offset $b$ are usually close
#   (small `smd`): mean-field VI is fine for "where does the movement go".
# * **Uncertainties** are too small (sd ratio < 1, `coverage90` < 0.9), worst
#   for $\alpha$ and the weights: do not use mean-field variances as
#   calibrated error bars; use NUTS when uncertainty matters (e.g. deciding
#   whether a via-point is reachable).  A richer guide is not automatically
#   better: read its sd ratios too (`svi_lowrank` above is far from 1 in both
#   directions, from near 0 for $\alpha$ to above 1 for the weights).
# * **$\hat k > 0.7$** means $q$ cannot be repaired by importance sampling; it
#   does not by itself make the predictive mean wrong.
# * **Compare only identifiable quantities**: $M$ and $h$ differ by rotations
#   between runs; look at `gram_eig`, the predictive, $w$.
#
# CAVI and the `svi_meanfield` guide optimise the same family, so their
# numbers should be close once both converge; a gap means one has not
# converged (the report lists engine warnings).

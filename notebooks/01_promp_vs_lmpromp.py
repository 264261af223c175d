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
# # 01 · ProMP versus LMProMP on LASA handwriting
#
# A **probabilistic movement primitive** (ProMP, thesis Sec. 3.1) writes a
# demonstrated trajectory as a weighted sum of basis functions,
# $y_k(z) = \psi(z)^T w_k + \epsilon$, and puts a Gaussian on the weights,
# $w \sim \mathcal N(\mu_w, \Sigma_w)$.  The **latent-manifold ProMP**
# (LMProMP, Sec. 4.1) replaces the free covariance by a low-dimensional
# explanation of the variation between demonstrations:
#
# $$ w_i = b + M h_i + \epsilon_i, \qquad h_i \sim \mathcal N(0, \gamma^{-1} I_V),
#    \qquad \epsilon_i \sim \mathcal N(0, \alpha^{-1} I_d). $$
#
# $b$ is the mean movement, the columns of $M$ are the directions in which
# demonstrations differ, and the **control variables** $h_i$ say how far each
# demonstration moves along them.  This notebook shows
#
# 1. the basis functions and how a trajectory becomes a weight vector;
# 2. a ProMP and an LMProMP fitted to the seven `GShape` demonstrations of LASA;
# 3. what the control variables do: vary $h$ and watch the trajectory;
# 4. conditioning both models on a via-point.
#
# The size knob `LMPROMP_NOTEBOOK_SIZE` (`small` in the tests, `full` by
# default) only changes how many trajectories are sampled for the figures:
# everything here runs in seconds.

# %%
import os

SIZE = os.environ.get("LMPROMP_NOTEBOOK_SIZE", "full")
assert SIZE in ("small", "full"), f"LMPROMP_NOTEBOOK_SIZE must be small or full, got {SIZE!r}"
EVERY = 50  # keep every 50th of LASA's 1000 samples: 21 per demonstration
NUM_BASIS = 8  # J, basis functions per DoF (few, so that the ProMP's d x d covariance stays small)
NUM_PATHS = 8 if SIZE == "small" else 20  # sampled trajectories per figure
print(f"size={SIZE}: every={EVERY}, J={NUM_BASIS}, {NUM_PATHS} sampled paths per figure")

# %%
import warnings

warnings.filterwarnings("ignore", message="IProgress not found")  # tqdm without ipywidgets

import jax
import matplotlib.pyplot as plt
import numpy as np

import lmpromp_ppl as lp
from lmpromp_ppl.data import prepare_dataset
from lmpromp_ppl.basis import design_matrix, rbf_basis
from lmpromp_ppl.inference.cavi import sufficient_statistics, ridge_weights
from lmpromp_ppl.predict import (
    condition,
    prior,
    sample_trajectories,
    trajectory_distribution,
    unstandardise,
    unstandardise_samples,
    via_point,
)

plt.rcParams.update({"figure.dpi": 90, "axes.grid": True, "grid.alpha": 0.3})
SPEC = f"lasa:GShape?every={EVERY}"

# %% [markdown]
# ## 1. Basis functions
#
# `rbf_basis` gives $J$ normalised Gaussian bumps $\psi_j(z)$ over the phase
# $z \in [0, 1]$; each row sums to one.  For $D$ degrees of freedom the design
# matrix $\Psi$ is block diagonal: weight $j$ of DoF $k$ is entry $kJ + j$ of
# $w$, and row $tD + k$ of $\Psi$ is DoF $k$ at time $t$
# (`lmpromp_ppl.basis`).

# %%
phase = np.linspace(0.0, 1.0, 200)
phi = np.asarray(rbf_basis(phase, NUM_BASIS))
fig, axes = plt.subplots(1, 2, figsize=(10, 3))
axes[0].plot(phase, phi)
axes[0].set(title=f"{NUM_BASIS} normalised basis functions", xlabel="phase z", ylabel=r"$\psi_j(z)$")
axes[1].imshow(np.asarray(design_matrix(np.linspace(0, 1, 8), 2, NUM_BASIS)), cmap="Greys", aspect="auto")
axes[1].set(title=r"$\Psi$ for 8 phases, D = 2", xlabel="weight index k J + j", ylabel="row t D + k")
plt.tight_layout()

# %% [markdown]
# ## 2. Data and per-demonstration weights
#
# `prepare` loads the data set, maps each demonstration's time to a phase in
# $[0, 1]$, standardises every DoF and builds the design matrices; `lp.fit`
# does the same internally, so everything below lives in the same standardised
# weight space.  Ridge regression of each demonstration on $\Psi$ gives its
# weight vector $w_i$; $\Psi w_i$ reproduces the demonstration.

# %%
prepared = prepare_dataset(SPEC, NUM_BASIS)  # loaded, standardised and turned into model inputs once
spec, raw, scaled, scaling, mdata = prepared.spec, prepared.raw, prepared.scaled, prepared.scaling, prepared.model_data
D, J = raw.num_dofs, NUM_BASIS
W = ridge_weights(sufficient_statistics(mdata))  # (L, D*J), standardised space
L, d = W.shape
print(raw, f"-> L={L} demonstrations, d={d} weights")


def trajectory(w, z=phase):
    """Positions (T, D) in data units of weight vector(s) w (..., D*J)."""
    w = np.asarray(w).reshape(np.shape(w)[:-1] + (D, J))
    y = np.einsum("tj,...kj->...tk", np.asarray(rbf_basis(z, J)), w)
    return y * scaling.scale + scaling.mean


fig, ax = plt.subplots(figsize=(5, 4))
for i, y in enumerate(raw.positions):
    ax.plot(y[:, 0], y[:, 1], "o", ms=2, color=f"C{i}")
    ax.plot(*trajectory(W[i]).T, "-", color=f"C{i}", lw=1)
ax.set(title="GShape: samples (dots) and basis fits (lines)", xlabel="x [mm]", ylabel="y [mm]")
ax.set_aspect("equal")

# %% [markdown]
# ## 3. The ProMP: one Gaussian over the weights
#
# The classical ProMP estimates $\mu_w$ and $\Sigma_w$ as the mean and
# covariance of the weight vectors.  With $L = 7$ demonstrations and
# $d = DJ$ weights the sample covariance has rank at most $L - 1$: it must be
# regularised, and most of its $d(d+1)/2$ entries are guessed from very little
# data.  (The Bayesian ProMP `lp.fit(..., model="promp", engine="nuts")` puts
# an LKJ prior on the correlation instead; here we keep the textbook estimate.)

# %%
mu_w = W.mean(axis=0)
Sigma_w = np.cov(W, rowvar=False) + 1e-4 * np.eye(d)
promp = {"mu_w": mu_w, "Sigma_w": Sigma_w}
print("rank of the sample covariance:", np.linalg.matrix_rank(np.cov(W, rowvar=False)), "of", d)


def plot_distribution(ax, weights, color, label, key=0, n=NUM_PATHS):
    """Mean path and sampled paths (data units) of a weight distribution."""
    paths = unstandardise_samples(
        sample_trajectories(jax.random.key(key), weights, phase, n, num_dofs=D, num_basis=J), scaling
    )
    for p in np.asarray(paths):
        ax.plot(p[:, 0], p[:, 1], color=color, lw=0.6, alpha=0.4)
    mean = unstandardise(trajectory_distribution(weights, phase, num_dofs=D, num_basis=J), scaling).mean
    ax.plot(*np.asarray(mean).T, color=color, lw=2.5, label=label)


# %% [markdown]
# ## 4. The LMProMP: an offset, a few directions, and control variables
#
# `lp.fit` with the hand-derived CAVI engine (Sec. 4.1.1) fits the
# mean-field posterior.  We allow $V = 3$ latent dimensions; the
# automatic-relevance prior on the columns of $M$ (precisions $\lambda_v$)
# switches off the ones the data do not need.
#
# We use the library's default settings (`lp.preset("default")`, see
# `docs/defaults.md`): the thesis's priors, but with the observation noise
# $\beta$ learned from the data instead of fixed at 100.  `fit` warns in plain
# words when a fit is degenerate (for example when a column of $M$ carries
# the mean movement instead of $b$); the fit's `summary["warnings"]` lists
# them, and we print it below.  (Try `NUM_BASIS = 6`: six basis functions are
# too coarse for the G, its weights exceed 10 standard deviations, and `fit`
# warns that the mean movement is carried by $M h$.)

# %%
HYPER = lp.preset("default", latent_dim=3)
with warnings.catch_warnings(record=True) as caught:  # show the message, not where it was raised
    warnings.simplefilter("always")
    fit = lp.fit(SPEC, model="lmpromp", engine="cavi", hyper=HYPER, num_basis=NUM_BASIS, tol=1e-6)
for w in caught:
    print(f"{w.category.__name__}: {w.message}")
point = fit.point
active = fit.summary["active_latent_dims"]
print(f"CAVI: {fit.summary['iterations']} sweeps, converged: {fit.summary['converged']}, ELBO {fit.summary['elbo']:.1f}")
print("column scales 1/E[lambda_v]:", np.round(1.0 / point["lam"], 4), "-> active dims", active)
print("residual weight s.d. alpha^-1/2:", float(point["alpha"]) ** -0.5)
print("degeneracy warnings:", fit.summary["warnings"] or "none")

# %%
fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharex=True, sharey=True)
for ax in axes:
    for y in raw.positions:
        ax.plot(y[:, 0], y[:, 1], "k.", ms=1.5)
    ax.set_aspect("equal")
plot_distribution(axes[0], prior("promp", promp).weights, "C0", "ProMP mean")
plot_distribution(axes[1], prior("lmpromp", point, fit.hyper.gamma).weights, "C3", "LMProMP mean")
axes[0].set(title="ProMP prior: samples", xlabel="x [mm]", ylabel="y [mm]")
axes[1].set(title="LMProMP prior: samples", xlabel="x [mm]")
for ax in axes:
    ax.legend(loc="lower right")
plt.tight_layout()

# %% [markdown]
# Both priors produce G-shaped samples.  The ProMP's come from a covariance
# with $d(d+1)/2$ free numbers; the LMProMP's from $b$, the active columns of
# $M$ and one residual precision $\alpha$.  The LMProMP's samples are more
# ragged: its isotropic residual $\alpha^{-1} I$ perturbs every weight
# independently, which is not a smooth deformation of the G.  What the
# demonstrations share is in the active column of $M$, next.
#
# ## 5. What the control variables do
#
# Fix every $h$-coordinate at 0 except one, sweep it over
# $[-2, 2]$ prior standard deviations and draw $\Psi(b + Mh)$.  An active
# direction bends the whole G coherently; a switched-off direction (its
# column of $M$ is shrunk to nearly zero) does nothing.

# %%
b, M = np.asarray(point["b"]), np.asarray(point["M"])
V = M.shape[1]
sweep = np.linspace(-2.0, 2.0, 5) / np.sqrt(fit.hyper.gamma)
fig, axes = plt.subplots(1, V, figsize=(4 * V, 4), sharex=True, sharey=True)
for v, ax in enumerate(axes):
    for s, c in zip(sweep, plt.cm.coolwarm(np.linspace(0, 1, len(sweep)))):
        h = np.zeros(V)
        h[v] = s
        ax.plot(*trajectory(b + M @ h).T, color=c, label=f"h_{v + 1} = {s:+.1f}")
    ax.set_title(f"vary h_{v + 1} ({'active' if v in active else 'switched off'})")
    ax.set_aspect("equal")
axes[0].legend(fontsize=7)
plt.tight_layout()

# %% [markdown]
# The posterior means of the control variables place each demonstration
# along the active directions: $h_i$ is a compact code of "how this
# demonstration differs from the average".  (Seven demonstrations are few: the
# bound may switch every column off, because the mean-field family shrinks $M$
# where the data determine it weakly; `docs/defaults.md` measures this against
# NUTS.  Then the largest column is shown, and `fit.summary["warnings"]` says so.)

# %%
h_mean = np.asarray(point["h"])
first = active[0] if active else int(np.argmax(1.0 / np.asarray(point["lam"])))
print("shown: h_%d (%s)" % (first + 1, "active" if active else "largest column; every column is switched off"))
fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
axes[0].bar(np.arange(L), h_mean[:, first], color=[f"C{i}" for i in range(L)])
axes[0].set(title=f"E[h_{first + 1}] per demonstration", xlabel="demonstration")
for i, y in enumerate(raw.positions):
    axes[1].plot(y[:, 0], y[:, 1], color=f"C{i}", lw=1)
axes[1].set(title="demonstrations (same colours)", xlabel="x [mm]", ylabel="y [mm]")
axes[1].set_aspect("equal")
plt.tight_layout()

# %% [markdown]
# ## 6. Conditioning on a via-point
#
# Asking the movement to pass through a point at a given phase is Gaussian
# conditioning of the weight distribution (ProMP: eqs. 3.2, 3.3; LMProMP:
# eqs. 4.4-4.7 with $\gamma^{-1}$ for the prior covariance of $h$, erratum 3
# of `docs/derivation.md`).  `via_point` builds the observation in data units.
# We take a target that lies off the mean: demonstration 0's position at phase
# 0.5, pushed 3 mm outwards.

# %%
z_via = 0.5
target = trajectory(W[0], np.array([z_via]))[0] + np.array([3.0, 0.0])
obs = via_point(z_via, target, position_sd=0.3, num_dofs=D, num_basis=J, scaling=scaling)
post_promp = condition("promp", promp, obs)
post_lm = condition("lmpromp", point, obs, fit.hyper.gamma)  # eqs. 4.4-4.7
post_exact = condition("lmpromp", point, obs, fit.hyper.gamma, exact=True)  # exact p(w | o)
posts = {"ProMP": post_promp, "LMProMP (eqs. 4.6, 4.7)": post_lm, "LMProMP (exact)": post_exact}

fig, axes = plt.subplots(1, 3, figsize=(14, 4), sharex=True, sharey=True)
for ax, (name, post), color in zip(axes, posts.items(), ("C0", "C3", "C2")):
    for y in raw.positions:
        ax.plot(y[:, 0], y[:, 1], "k.", ms=1.5)
    plot_distribution(ax, post.weights, color, f"{name} | via-point", key=1)
    ax.plot(*target, "k*", ms=14, label="via-point")
    ax.set_title(name)
    ax.set_aspect("equal")
    ax.legend(loc="lower right", fontsize=8)
plt.tight_layout()

# %%
print("E[h | via-point] (LMProMP):", np.round(np.asarray(post_lm.latent.means[0]), 2))
print("target:", np.round(target, 2))
for name, post in posts.items():
    m = unstandardise(trajectory_distribution(post.weights, np.array([z_via]), num_dofs=D, num_basis=J), scaling)
    miss = float(np.linalg.norm(np.asarray(m.mean[0]) - target))
    print(f"{name:>24}: mean at phase {z_via} = {np.round(np.asarray(m.mean[0]), 2)}, {miss:.2f} mm from the target")

# %% [markdown]
# The ProMP and the exact LMProMP conditional pass through the via-point (the
# printout gives each mean's distance from it).  Eqs. 4.6 and 4.7 of the thesis
# need not, by design: they condition only the control variables,
# $p(h \mid o)$, and then draw a *new* execution $w = b + M h + \epsilon$ with
# its own residual $\epsilon$.  Their mean can only move along the active
# columns of $M$ (here one direction in weight space), so it reaches the
# via-point only as far as that direction allows, and the rest of the movement
# stays a G of the kind demonstrated.  Here that one direction happens to reach
# the target, so the two LMProMP conditionals agree; in general they do not
# (`docs/derivation.md` shows that eqs. 4.6-4.7 are not $p(w \mid o)$).
# `exact=True` also conditions the residual and bends the path through the
# point.  The ProMP's
# adjustment is whatever its regularised covariance, estimated from seven
# samples, happens to correlate with the via-point.
#
# **Takeaways.** A ProMP needs the full weight covariance; an LMProMP
# explains the variation between demonstrations with a few directions and
# learns how many it needs (ARD).  Its control variables are a handle on the
# movement, and conditioning acts through them.

r"""Exact-conditional (Gibbs) refresh of posterior draws of the single-type LMProMP.

Every conditional of the LMProMP (eq. 4.1) given the others is a closed-form Gaussian or
Gamma, so a blocked Gibbs sweep over them is a Markov kernel :math:`K` that leaves the
posterior :math:`p(\theta, \mathbf w, \mathbf h \mid \mathbf y)` invariant.  Applied to the
draws of an approximation :math:`q`, it can only bring them closer: by the data-processing
inequality, :math:`\mathrm{KL}(qK \,\|\, p) = \mathrm{KL}(qK \,\|\, pK) \le \mathrm{KL}(q \,\|\, p)`
(Salimans, Kingma and Welling 2015, "Markov chain Monte Carlo and variational inference:
bridging the gap"; the same argument as any MCMC chain started from a variational fit).
:func:`refresh` runs ``sweeps`` sweeps from each draw, independently and in parallel (one
``vmap`` over the draws): the draws stay independent, so no chain needs to mix, only to
move each draw from where :math:`q` put it towards where the posterior puts it.

One sweep, in the order that integrates out what the next block depends on most
(docs/derivation.md, *Refreshing the draws by exact conditionals*):

1. :math:`\mathbf b \mid \mathbf M, \alpha, \beta, \mathbf y` with ``w`` and ``h``
   integrated out (:func:`~lmpromp_ppl.models.conditionals.offset_marginal`), then
   :math:`\mathbf w_i \mid \mathbf b, \mathbf M, \alpha, \beta, \mathbf y_i` (prior
   :math:`\mathcal N(\mathbf b, \alpha^{-1}\mathbf I + \gamma^{-1}\mathbf M\mathbf M^T)`) and
   :math:`\mathbf h_i \mid \mathbf w_i, \mathbf b, \mathbf M, \alpha`: together one exact draw
   of the block :math:`(\mathbf b, \mathbf w, \mathbf h)`;
2. :math:`\mathbf M \mid \mathbf w, \mathbf h, \mathbf b, \alpha, \boldsymbol\lambda`: its rows
   :math:`\mathbf m_{j\cdot} \sim \mathcal N(\mathbf P^{-1}\alpha\sum_i\mathbf h_i(w_{ij} - b_j), \mathbf P^{-1})`,
   :math:`\mathbf P = \mathrm{diag}(\boldsymbol\lambda) + \alpha\sum_i\mathbf h_i\mathbf h_i^T`;
3. :math:`\lambda_v \mid \mathbf M \sim \Gamma(c_0 + d/2,\ d_0 + \|\mathbf m_v\|^2/2)`;
4. :math:`\alpha \mid \mathbf w, \mathbf h, \mathbf b, \mathbf M \sim \Gamma(a_0 + Ld/2,\ b_0 + \sum_i\|\mathbf w_i - \mathbf b - \mathbf M\mathbf h_i\|^2/2)`;
5. when learned, :math:`\beta \mid \mathbf w, \mathbf y \sim \Gamma(\beta_{a0} + N/2,\ \beta_{b0} + \sum_i\|\mathbf y_i - \Psi_i\mathbf w_i\|^2/2)`,
   :math:`N` the observed entries, from the statistics
   :math:`\|\mathbf y_i - \Psi_i\mathbf w_i\|^2 = \mathbf y_i^T\mathbf y_i - 2\mathbf w_i^T\Psi_i^T\mathbf y_i + \mathbf w_i^T\Psi_i^T\Psi_i\mathbf w_i`.

When every demonstration has the same design (:class:`~lmpromp_ppl.data.core.SharedDesign`), the
sweeps run in the eigenbasis of :math:`\Psi^T\Psi`, where every covariance of block 1 is a
diagonal plus rank V (:func:`rotated_conditionals`): O(d V^2 + L d V) per sweep and draw, with no
d x d factorisation; the draws are rotated in before the first sweep and out after the last.

Every conditional is checked against the NumPyro declaration in ``tests/test_refresh.py``
(the log joint minus the conditional's log density is constant in the block), and the
kernel's invariance by a Geweke-style test (sweeps started at the true parameters of
simulated datasets leave them distributed as the prior).
"""

from __future__ import annotations

import time
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.scipy.linalg import solve_triangular

from lmpromp_ppl.data.core import ModelData, PhaseData, SharedDesign, shared_design
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference.compiled import compiled
from lmpromp_ppl.models.conditionals import data_statistics, gaussian_conditional, offset_marginal, woodbury_precision
from lmpromp_ppl.models.hyper import Hyperparameters

__all__ = ["refresh", "sweep", "conditional_b", "conditional_locals", "conditional_M", "conditional_lam",
           "conditional_alpha", "conditional_beta", "rotated_conditionals", "RotatedConditionals", "GLOBAL_SITES", "REFRESH_SWEEPS", "check_refresh"]

#: Sweeps of the refresh that ``cavi_lr`` applies to its draws by default.
REFRESH_SWEEPS = 60

#: The sites a refreshed draw carries besides the locals ``w`` and ``h``.
GLOBAL_SITES = ("b", "M", "alpha", "lam", "beta")


def _gaussian_draw(key: Array, mean: Array, chol: Array) -> Array:
    """A draw from N(mean, (chol chol^T)^-1), batched over leading dimensions."""
    eps = jax.random.normal(key, mean.shape + (1,), dtype=mean.dtype)
    return mean + solve_triangular(jnp.swapaxes(chol, -1, -2), eps, lower=False)[..., 0]


def _gamma_draw(key: Array, shape, rate) -> Array:
    """A draw from Gamma(shape, rate) (rate parametrisation), batched."""
    return jax.random.gamma(key, shape, jnp.shape(rate)) / rate


def conditional_b(stats, M: Array, alpha: Array, beta: Array, hyper: Hyperparameters) -> tuple[Array, Array]:
    r"""Mean and precision Cholesky factor of :math:`p(\mathbf b \mid \mathbf M, \alpha, \beta, \mathbf y)`, w and h integrated out."""
    _, mean, chol = offset_marginal(stats, M, alpha, beta, hyper.lambda0, hyper.gamma)
    return mean, chol


def conditional_locals(stats, b: Array, M: Array, alpha: Array, beta: Array, hyper: Hyperparameters):
    r"""Moments of :math:`p(\mathbf w_i \mid \mathbf b, \mathbf M, \alpha, \beta, \mathbf y_i)` (h integrated out).

    Returns the mean (L, d) and the precision Cholesky factor (L, d, d); the conditional of
    ``h`` given ``w`` is :func:`_conditional_h`.
    """
    gram, cross, sq, count = stats
    prior = woodbury_precision(alpha, M, hyper.gamma)
    mean, chol, _ = gaussian_conditional(gram, cross, sq, count, beta, jnp.broadcast_to(b, cross.shape), prior)
    return mean, chol


def _conditional_h(w: Array, b: Array, M: Array, alpha: Array, gamma: float) -> tuple[Array, Array]:
    r"""Mean (L, V) and precision Cholesky factor (V, V) of :math:`p(\mathbf h_i \mid \mathbf w_i, \mathbf b, \mathbf M, \alpha)`."""
    precision = gamma * jnp.eye(M.shape[1]) + alpha * M.T @ M
    chol = jnp.linalg.cholesky(precision)
    rhs = alpha * (w - b) @ M  # (L, V)
    mean = jax.scipy.linalg.cho_solve((chol, True), rhs.T).T
    return mean, chol


def conditional_M(w: Array, h: Array, b: Array, alpha: Array, lam: Array) -> tuple[Array, Array]:
    r"""Row means (d, V) and the shared precision Cholesky factor (V, V) of :math:`p(\mathbf M \mid \mathbf w, \mathbf h, \mathbf b, \alpha, \boldsymbol\lambda)`."""
    precision = jnp.diag(lam) + alpha * h.T @ h
    chol = jnp.linalg.cholesky(precision)
    rhs = alpha * (w - b).T @ h  # (d, V)
    mean = jax.scipy.linalg.cho_solve((chol, True), rhs.T).T
    return mean, chol


def conditional_lam(M: Array, hyper: Hyperparameters) -> tuple[Array, Array]:
    r"""Shape and rate (V,) of :math:`p(\lambda_v \mid \mathbf M)`."""
    d = M.shape[0]
    return jnp.full(M.shape[1], hyper.c0 + 0.5 * d), hyper.d0 + 0.5 * jnp.sum(M**2, axis=0)


def conditional_alpha(w: Array, h: Array, b: Array, M: Array, hyper: Hyperparameters) -> tuple[Array, Array]:
    r"""Shape and rate of :math:`p(\alpha \mid \mathbf w, \mathbf h, \mathbf b, \mathbf M)`."""
    resid = w - b - h @ M.T
    return hyper.a0 + 0.5 * w.size, hyper.b0 + 0.5 * jnp.sum(resid**2)


def conditional_beta(stats, w: Array, hyper: Hyperparameters) -> tuple[Array, Array]:
    r"""Shape and rate of :math:`p(\beta \mid \mathbf w, \mathbf y)` (learned beta).

    ``stats``: :func:`~lmpromp_ppl.models.conditionals.data_statistics`, or a
    :class:`~lmpromp_ppl.data.core.SharedDesign` with ``w`` in its eigenbasis
    (:math:`\mathbf w'^T\operatorname{diag}(\mathbf g)\mathbf w'` for the quadratic term).
    """
    if isinstance(stats, SharedDesign):
        _, g, cross, sq, count = stats
        quadratic = jnp.sum(g * w**2, axis=-1)
    else:
        gram, cross, sq, count = stats
        quadratic = jnp.einsum("ld,lde,le->l", w, gram, w)
    resid_sq = sq - 2.0 * jnp.sum(w * cross, axis=-1) + quadratic
    return hyper.beta_a0 + 0.5 * jnp.sum(count), hyper.beta_b0 + 0.5 * jnp.sum(resid_sq)


def _locals(key: Array, stats, theta: dict, hyper: Hyperparameters) -> tuple[Array, Array]:
    """(w, h) drawn from their exact joint conditional given the globals of ``theta``."""
    k_w, k_h = jax.random.split(key)
    beta = theta.get("beta", hyper.beta)
    mean, chol = conditional_locals(stats, theta["b"], theta["M"], theta["alpha"], beta, hyper)
    w = _gaussian_draw(k_w, mean, chol)
    mean_h, chol_h = _conditional_h(w, theta["b"], theta["M"], theta["alpha"], hyper.gamma)
    h = _gaussian_draw(k_h, mean_h, jnp.broadcast_to(chol_h, mean_h.shape + chol_h.shape[-1:]))
    return w, h


class RotatedConditionals(NamedTuple):
    r"""Block 1's conditionals on a shared design, in its eigenbasis (:func:`rotated_conditionals`).

    Every covariance is a diagonal plus rank V: a draw is ``mean + scale * e + factor @ f`` with
    ``e`` (d,) and ``f`` (V,) standard normal, at O(d V) per draw and no d x d factorisation.
    """

    mean_b: Array  # (d,) mean of b' | M, alpha, beta, y
    scale_b: Array  # (d,) and
    factor_b: Array  # (d, V): its covariance is diag(scale_b**2) + factor_b factor_b^T
    scale_w: Array  # (d,) and
    factor_w: Array  # (d, V): the covariance of w_i' | b, M, alpha, beta, y_i
    weights_linear: Array  # (L, d) beta c_i', the data's part of each w_i' mean's linear term
    prior_precision_factor: Array  # (d, V) X S^{-1/2}: A' = alpha I - X S^{-1} X^T
    diag: Array  # (d,) D = alpha + beta g
    alpha: Array

    def weights_mean(self, b: Array) -> Array:
        r"""(L, d) means :math:`\mathbf P'^{-1}(\mathbf A'\mathbf b' + \beta\mathbf c_i')` of :math:`\mathbf w_i' \mid \mathbf b', \ldots`."""
        Y = self.prior_precision_factor
        rhs = (self.alpha * b - Y @ (Y.T @ b))[None, :] + self.weights_linear
        # P'^{-1} = D^{-1} + D^{-1} X Q^{-1} X^T D^{-1}, and factor_w factor_w^T = D^{-1} X Q^{-1} X^T D^{-1}
        scaled = rhs / self.diag
        F = self.factor_w
        return scaled + (rhs @ F) @ F.T


def rotated_conditionals(design: SharedDesign, M: Array, alpha: Array, beta: Array,
                         hyper: Hyperparameters) -> RotatedConditionals:
    r"""Block 1's conditionals when every demonstration has the same design, in the eigenbasis
    :math:`\Psi^T\Psi = \mathbf U\operatorname{diag}(\mathbf g)\mathbf U^T` (``M`` = :math:`\mathbf M' = \mathbf U^T\mathbf M`).

    The priors of ``b``, the rows of ``M`` and ``w_i - b - M h_i`` are isotropic, so the rotation
    leaves the model unchanged and makes the Gram matrix diagonal.  With
    :math:`\boldsymbol\kappa = \alpha\beta\mathbf g/(\alpha + \beta\mathbf g)`,
    :math:`\boldsymbol\rho = \alpha\beta/(\alpha + \beta\mathbf g)`,
    :math:`\mathbf Q = \gamma\mathbf I + \mathbf M'^T\operatorname{diag}(\boldsymbol\kappa)\mathbf M'`
    and :math:`\mathbf D = \operatorname{diag}(\alpha + \beta\mathbf g)` (docs/derivation.md,
    *Refreshing the draws by exact conditionals*):

    * :math:`\sum_i\Psi^T\mathbf K_i^{-1}\Psi = L(\operatorname{diag}\boldsymbol\kappa - \mathbf K\mathbf Q^{-1}\mathbf K^T)`,
      :math:`\mathbf K = \operatorname{diag}(\boldsymbol\kappa)\mathbf M'`, and
      :math:`\sum_i\Psi^T\mathbf K_i^{-1}\mathbf y_i = \mathbf r - \mathbf K\mathbf Q^{-1}\mathbf M'^T\mathbf r`,
      :math:`\mathbf r = \boldsymbol\rho\circ\sum_i\mathbf c_i'` (:func:`conditional_b`'s terms, Woodbury
      on :math:`\mathbf K_i = \beta^{-1}\mathbf I + \alpha^{-1}\Psi\Psi^T + \gamma^{-1}\Psi\mathbf M\mathbf M^T\Psi^T`);
      so :math:`\mathbf b'` has precision :math:`\boldsymbol\Delta - L\mathbf K\mathbf Q^{-1}\mathbf K^T`,
      :math:`\boldsymbol\Delta = \lambda_0 + L\boldsymbol\kappa`, and covariance
      :math:`\boldsymbol\Delta^{-1} + \boldsymbol\Delta^{-1}\mathbf K\mathbf E^{-1}\mathbf K^T\boldsymbol\Delta^{-1}`,
      :math:`\mathbf E = (\gamma\mathbf I + \mathbf M'^T\operatorname{diag}(\lambda_0\boldsymbol\kappa/\boldsymbol\Delta)\mathbf M')/L`
      (:math:`\mathbf Q/L - \mathbf K^T\boldsymbol\Delta^{-1}\mathbf K`, written without cancellation);
    * :math:`\mathbf w_i'` has precision :math:`\mathbf P' = \mathbf D - \mathbf X\mathbf S^{-1}\mathbf X^T`
      (:math:`\mathbf X = \alpha\mathbf M'`, :math:`\mathbf S = \gamma\mathbf I + \alpha\mathbf M^T\mathbf M`)
      and covariance :math:`\mathbf D^{-1} + \mathbf D^{-1}\mathbf X\mathbf Q^{-1}\mathbf X^T\mathbf D^{-1}`
      (:math:`\mathbf S - \mathbf X^T\mathbf D^{-1}\mathbf X = \mathbf Q`, as in
      :func:`~lmpromp_ppl.models.collapsed.shared_log_evidence`).

    O(d V^2 + L d V) per draw instead of the two d x d factorisations of the general shared path.
    """
    g, cross = design.eig, design.cross
    num_demos, num_latent = cross.shape[0], M.shape[1]
    eye = jnp.eye(num_latent)
    diag = alpha + beta * g
    kappa = alpha * beta * g / diag
    rho = alpha * beta / diag
    chol_q = jnp.linalg.cholesky(hyper.gamma * eye + M.T @ (kappa[:, None] * M))
    K = kappa[:, None] * M
    r = rho * jnp.sum(cross, axis=0)
    linear = r - K @ jax.scipy.linalg.cho_solve((chol_q, True), M.T @ r)
    delta = hyper.lambda0 + num_demos * kappa
    E = (hyper.gamma * eye + M.T @ ((hyper.lambda0 * kappa / delta)[:, None] * M)) / num_demos
    chol_e = jnp.linalg.cholesky(0.5 * (E + E.T))
    factor_b = solve_triangular(chol_e, (K / delta[:, None]).T, lower=True).T  # Delta^-1 K chol(E)^-T
    mean_b = linear / delta + factor_b @ (factor_b.T @ linear)
    X = alpha * M
    factor_w = solve_triangular(chol_q, (X / diag[:, None]).T, lower=True).T  # D^-1 X chol(Q)^-T
    chol_s = jnp.linalg.cholesky(hyper.gamma * eye + alpha * M.T @ M)
    Y = solve_triangular(chol_s, X.T, lower=True).T  # X chol(S)^-T: X S^-1 X^T = Y Y^T
    return RotatedConditionals(mean_b, jax.lax.rsqrt(delta), factor_b, jax.lax.rsqrt(diag), factor_w, beta * cross,
                               Y, diag, alpha)


def _low_rank_draw(key: Array, mean: Array, scale: Array, factor: Array) -> Array:
    """``mean`` (..., d) plus a draw of N(0, diag(scale**2) + factor factor^T), batched over ``mean``'s leading axes."""
    k_e, k_f = jax.random.split(key)
    e = jax.random.normal(k_e, mean.shape, dtype=mean.dtype)
    f = jax.random.normal(k_f, mean.shape[:-1] + factor.shape[-1:], dtype=mean.dtype)
    return mean + scale * e + f @ factor.T


def _rotated_locals(key: Array, cond: RotatedConditionals, b: Array, M: Array, alpha: Array,
                    gamma: float) -> tuple[Array, Array]:
    """(w', h) from their exact joint conditional given ``b'`` (eigenbasis coordinates)."""
    k_w, k_h = jax.random.split(key)
    w = _low_rank_draw(k_w, cond.weights_mean(b), cond.scale_w, cond.factor_w)
    mean_h, chol_h = _conditional_h(w, b, M, alpha, gamma)
    h = _gaussian_draw(k_h, mean_h, jnp.broadcast_to(chol_h, mean_h.shape + chol_h.shape[-1:]))
    return w, h


def _rotated_offset_and_locals(key: Array, design: SharedDesign, theta: dict,
                               hyper: Hyperparameters) -> tuple[Array, Array, Array]:
    """Block 1 by :func:`rotated_conditionals` (``theta`` and the result in eigenbasis coordinates)."""
    k_b, k_locals = jax.random.split(key)
    M, alpha, beta = theta["M"], theta["alpha"], theta.get("beta", hyper.beta)
    cond = rotated_conditionals(design, M, alpha, beta, hyper)
    b = _low_rank_draw(k_b, cond.mean_b, cond.scale_b, cond.factor_b)
    return (b,) + _rotated_locals(k_locals, cond, b, M, alpha, hyper.gamma)


def sweep(key: Array, theta: dict, stats, hyper: Hyperparameters) -> dict:
    r"""One Gibbs sweep (the module's five blocks) from the globals ``theta`` of one draw; returns the new globals.

    ``stats``: :func:`~lmpromp_ppl.models.conditionals.data_statistics`, or a
    :class:`~lmpromp_ppl.data.core.SharedDesign`, with ``theta``'s ``b`` and ``M`` (and the result's) in
    its eigenbasis coordinates (:func:`rotated_conditionals`).
    """
    keys = jax.random.split(key, 6)
    if isinstance(stats, SharedDesign):
        b, w, h = _rotated_offset_and_locals(keys[0], stats, theta, hyper)
    else:
        beta = theta.get("beta", hyper.beta)
        mean, chol = conditional_b(stats, theta["M"], theta["alpha"], beta, hyper)
        b = _gaussian_draw(keys[0], mean, chol)
        w, h = _locals(keys[1], stats, dict(theta, b=b), hyper)
    mean, chol = conditional_M(w, h, b, theta["alpha"], theta["lam"])
    M = _gaussian_draw(keys[2], mean, jnp.broadcast_to(chol, mean.shape + chol.shape[-1:]))
    lam = _gamma_draw(keys[3], *conditional_lam(M, hyper))
    alpha = _gamma_draw(keys[4], *conditional_alpha(w, h, b, M, hyper))
    new = dict(theta, b=b, M=M, lam=lam, alpha=alpha)
    if hyper.learn_beta:
        new["beta"] = _gamma_draw(keys[5], *conditional_beta(stats, w, hyper))
    return new


@partial(jax.jit, static_argnames=("hyper", "sweeps"))
def _refresh(key: Array, theta: dict, stats, hyper: Hyperparameters, sweeps: int) -> dict:
    rotated = isinstance(stats, SharedDesign)
    if rotated:  # into the eigenbasis once, out after the last sweep
        U = stats.rotation
        theta = dict(theta, b=theta["b"] @ U, M=jnp.einsum("dj,ndv->njv", U, theta["M"]))

    def one(k, t):
        def body(carry, kk):
            return sweep(kk, carry, stats, hyper), None

        k_sweeps, k_locals = jax.random.split(k)
        t, _ = jax.lax.scan(body, t, jax.random.split(k_sweeps, sweeps))
        if rotated:
            cond = rotated_conditionals(stats, t["M"], t["alpha"], t.get("beta", hyper.beta), hyper)
            w, h = _rotated_locals(k_locals, cond, t["b"], t["M"], t["alpha"], hyper.gamma)
        else:
            w, h = _locals(k_locals, stats, t, hyper)
        return dict(t, w=w, h=h)

    n = theta["b"].shape[0]
    out = jax.vmap(one)(jax.random.split(key, n), theta)
    if rotated:
        out = dict(out, b=out["b"] @ U.T, M=jnp.einsum("dj,njv->ndv", U, out["M"]), w=out["w"] @ U.T)
    return out


def check_refresh(sweeps) -> int:
    """The number of sweeps as an int; anything but a non-negative integer is a :class:`LmprompError`."""
    if isinstance(sweeps, bool) or not isinstance(sweeps, (int, np.integer)) or sweeps < 0:
        raise LmprompError(f"refresh sweeps must be a non-negative integer, got {sweeps!r}")
    return int(sweeps)


def refresh(key: Array, draws: dict, data, hyper: Hyperparameters, sweeps: int, *, timed: bool = False):
    r"""``sweeps`` exact-conditional Gibbs sweeps from each draw, then ``w`` and ``h`` from their exact conditional.

    Parameters
    ----------
    key : PRNG key
    draws : site -> (n, ...) draws of the single-type LMProMP's globals ``b`` (n, d), ``M``
        (n, d, V), ``alpha`` (n,), ``lam`` (n, V) and ``beta`` (n,) when ``hyper.learn_beta``;
        other sites are ignored (the locals are drawn anew)
    data : the model inputs the draws were fitted to, in any form
        (:func:`~lmpromp_ppl.models.conditionals.data_statistics`)
    hyper : the fit's hyperparameters
    sweeps : number of sweeps (0 only redraws ``w`` and ``h``)
    timed : also return the seconds of the compiled program and of its compilation (0 when
        already compiled in this process; :func:`lmpromp_ppl.inference.compiled.compiled`)

    Returns
    -------
    dict with the refreshed globals and ``w`` (n, L, d), ``h`` (n, L, V), as float64 arrays
    (with ``timed``: ``(draws, seconds, compile_seconds)``).
    """
    sweeps = check_refresh(sweeps)
    if hyper.num_components != 1:
        raise LmprompError("the Gibbs refresh is for the single-type LMProMP (num_components=1)")
    names = [s for s in GLOBAL_SITES if s != "beta" or hyper.learn_beta]
    missing = [s for s in names if s not in draws]
    if missing:
        raise LmprompError(f"the Gibbs refresh needs draws of {names}; missing {missing}")
    theta = {s: jnp.asarray(draws[s], dtype=jnp.float64) for s in names}
    with jax.ensure_compile_time_eval():  # the data are concrete even when the draws are traced
        design = shared_design(data) if isinstance(data, (ModelData, PhaseData, SharedDesign)) else None
        stats = design if design is not None else tuple(jnp.asarray(a, dtype=jnp.float64) for a in data_statistics(data))
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((key, theta))):  # traced (e.g. eval_shape)
        out = _refresh(key, theta, stats, hyper, sweeps)
        return (out, 0.0, 0.0) if timed else out
    executable, compile_seconds = compiled(_refresh, (key, theta, stats), hyper=hyper, sweeps=sweeps)
    start = time.perf_counter()
    out = jax.block_until_ready(executable(key, theta, stats))
    seconds = time.perf_counter() - start
    return (out, seconds, compile_seconds) if timed else out

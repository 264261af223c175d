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

from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference.compiled import compiled
from lmpromp_ppl.models.conditionals import data_statistics, gaussian_conditional, offset_marginal, woodbury_precision
from lmpromp_ppl.models.hyper import Hyperparameters

__all__ = ["refresh", "sweep", "conditional_b", "conditional_locals", "conditional_M", "conditional_lam",
           "conditional_alpha", "conditional_beta", "shared_conditionals", "SharedConditionals", "GLOBAL_SITES", "REFRESH_SWEEPS", "check_refresh"]

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
    r"""Shape and rate of :math:`p(\beta \mid \mathbf w, \mathbf y)` (learned beta)."""
    gram, cross, sq, count = stats
    resid_sq = sq - 2.0 * jnp.sum(w * cross, axis=-1) + jnp.einsum("ld,lde,le->l", w, gram, w)
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


class SharedConditionals(NamedTuple):
    """Block 1's conditionals on a shared design (:func:`shared_conditionals`)."""

    mean_b: Array  # (d,) mean of b | M, alpha, beta, y
    chol_b: Array  # (d, d) Cholesky factor of its precision
    chol_p: Array  # (d, d) Cholesky factor of P, the weights' conditional precision
    prior_precision: Array  # (d, d) A, the precision of w_i - b with h integrated out

    def weights_mean(self, b: Array, beta: Array, cross: Array) -> Array:
        r"""(L, d) means of :math:`\mathbf w_i \mid \mathbf b, \ldots`: :math:`\mathbf P^{-1}(\mathbf A\mathbf b + \beta\Psi^T\mathbf y_i)`."""
        rhs = (self.prior_precision @ b)[None, :] + beta * cross
        return jax.scipy.linalg.cho_solve((self.chol_p, True), rhs.T).T


def shared_conditionals(stats, M: Array, alpha: Array, beta: Array, hyper: Hyperparameters) -> SharedConditionals:
    r"""Block 1's conditionals when every demonstration has the same :math:`\Psi^T\Psi` (two factorisations).

    With :math:`\mathbf A = (\alpha^{-1}\mathbf I + \gamma^{-1}\mathbf M\mathbf M^T)^{-1}` and
    :math:`\mathbf P = \mathbf A + \beta\Psi^T\Psi` shared, :func:`conditional_b` has precision
    :math:`\lambda_0\mathbf I + L(\mathbf A - \mathbf A\mathbf P^{-1}\mathbf A)` and linear term
    :math:`\mathbf A\mathbf P^{-1}\beta\sum_i\Psi^T\mathbf y_i`, and :func:`conditional_locals`
    has precision :math:`\mathbf P` and means :math:`\mathbf P^{-1}(\mathbf A\mathbf b + \beta\Psi^T\mathbf y_i)`
    (:meth:`SharedConditionals.weights_mean`): two :math:`d \times d` factorisations instead of :math:`2L`.
    """
    gram, cross = stats[0][0], stats[1]
    d = M.shape[0]
    A = woodbury_precision(alpha, M, hyper.gamma)
    chol_p = jnp.linalg.cholesky(A + beta * gram)
    p_inv_a = jax.scipy.linalg.cho_solve((chol_p, True), A)
    precision_b = hyper.lambda0 * jnp.eye(d) + cross.shape[0] * (A - A @ p_inv_a)
    chol_b = jnp.linalg.cholesky(0.5 * (precision_b + precision_b.T))
    linear = A @ jax.scipy.linalg.cho_solve((chol_p, True), beta * jnp.sum(cross, axis=0))
    return SharedConditionals(jax.scipy.linalg.cho_solve((chol_b, True), linear), chol_b, chol_p, A)


def _shared_offset_and_locals(key: Array, stats, theta: dict, hyper: Hyperparameters) -> tuple[Array, Array, Array]:
    """Block 1 by :func:`shared_conditionals`: ``b``, then ``w`` and ``h``."""
    k_b, k_w, k_h = jax.random.split(key, 3)
    M, alpha, beta = theta["M"], theta["alpha"], theta.get("beta", hyper.beta)
    cond = shared_conditionals(stats, M, alpha, beta, hyper)
    b = _gaussian_draw(k_b, cond.mean_b, cond.chol_b)
    mean_w = cond.weights_mean(b, beta, stats[1])
    eps = jax.random.normal(k_w, mean_w.shape, dtype=mean_w.dtype)
    w = mean_w + solve_triangular(cond.chol_p.T, eps.T, lower=False).T
    mean_h, chol_h = _conditional_h(w, b, M, alpha, hyper.gamma)
    h = _gaussian_draw(k_h, mean_h, jnp.broadcast_to(chol_h, mean_h.shape + chol_h.shape[-1:]))
    return b, w, h


def sweep(key: Array, theta: dict, stats, hyper: Hyperparameters, shared: bool = False) -> dict:
    r"""One Gibbs sweep (the module's five blocks) from the globals ``theta`` of one draw; returns the new globals.

    ``shared``: every demonstration has the same :math:`\Psi^T\Psi` (:func:`_shared_offset_and_locals`).
    """
    keys = jax.random.split(key, 6)
    if shared:
        b, w, h = _shared_offset_and_locals(keys[0], stats, theta, hyper)
        theta = dict(theta, b=b)
    else:
        beta = theta.get("beta", hyper.beta)
        mean, chol = conditional_b(stats, theta["M"], theta["alpha"], beta, hyper)
        b = _gaussian_draw(keys[0], mean, chol)
        theta = dict(theta, b=b)
        w, h = _locals(keys[1], stats, theta, hyper)
    mean, chol = conditional_M(w, h, b, theta["alpha"], theta["lam"])
    M = _gaussian_draw(keys[2], mean, jnp.broadcast_to(chol, mean.shape + chol.shape[-1:]))
    lam = _gamma_draw(keys[3], *conditional_lam(M, hyper))
    alpha = _gamma_draw(keys[4], *conditional_alpha(w, h, b, M, hyper))
    new = dict(theta, M=M, lam=lam, alpha=alpha)
    if hyper.learn_beta:
        new["beta"] = _gamma_draw(keys[5], *conditional_beta(stats, w, hyper))
    return new


@partial(jax.jit, static_argnames=("hyper", "sweeps", "shared"))
def _refresh(key: Array, theta: dict, stats, hyper: Hyperparameters, sweeps: int, shared: bool) -> dict:
    def one(k, t):
        def body(carry, kk):
            return sweep(kk, carry, stats, hyper, shared), None

        k_sweeps, k_locals = jax.random.split(k)
        t, _ = jax.lax.scan(body, t, jax.random.split(k_sweeps, sweeps))
        w, h = _locals(k_locals, stats, t, hyper)
        return dict(t, w=w, h=h)

    n = theta["b"].shape[0]
    return jax.vmap(one)(jax.random.split(key, n), theta)


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
        stats = tuple(jnp.asarray(a, dtype=jnp.float64) for a in data_statistics(data))
        gram = np.asarray(stats[0])
    shared = bool(np.all(gram == gram[:1]))
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((key, theta))):  # traced (e.g. eval_shape)
        out = _refresh(key, theta, stats, hyper, sweeps, shared)
        return (out, 0.0, 0.0) if timed else out
    executable, compile_seconds = compiled(_refresh, (key, theta, stats), hyper=hyper, sweeps=sweeps, shared=shared)
    start = time.perf_counter()
    out = jax.block_until_ready(executable(key, theta, stats))
    seconds = time.perf_counter() - start
    return (out, seconds, compile_seconds) if timed else out

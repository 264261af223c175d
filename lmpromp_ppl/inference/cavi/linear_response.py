r"""Linear-response covariances of the global quantities (Giordano, Broderick and Jordan 2015, 2018).

A variational optimum :math:`\eta^*` of the bound :math:`\mathcal L(\eta)` moves when
the log joint is tilted by :math:`t^Tg(\theta)`; the linear-response covariance of
the global quantities :math:`g` is the response of their means to the tilt,

.. math::

    \Sigma_{LR} = \frac{dE_{q_t}[g]}{dt^T}\Big|_{t=0} = J\,H^{-1}J^T,\qquad
    J = \frac{\partial E_q[g]}{\partial\eta^T},\quad H = -\nabla^2_\eta\mathcal L(\eta^*),

which corrects the covariances that a factorised q understates (for a Gaussian
posterior it is exact).  Here (the single type, joint local family of :mod:`.state`):

* :math:`g = (b, \operatorname{vec}M, \log\alpha, \log\lambda_{1..V}, \log\beta)`, with
  :math:`\log\beta` only when beta is learned, M flattened row by row;
* :math:`\eta` = the parameters of the global factors, unconstrained: the means of
  q(b) and q(M), the logarithms of :math:`\sigma_b`, of the Gamma shapes and rates,
  and of the column variances (column-wise q(M)) or the Cholesky factor of
  :math:`\Sigma_M` with its diagonal on the log scale (row-wise q(M));
* the local factors are profiled out: :math:`\mathcal L(\eta)` is the bound at the
  closed-form optimum of every :math:`q(w_i, h_i)` given the global factors
  (:func:`~.updates.update_wh`).  The Hessian of the profiled bound is the Schur
  complement of the full Hessian on the global block, so :math:`J H^{-1}J^T` is the
  linear response of the whole family for the global quantities, with no local
  parameter in :math:`\eta`.

:math:`H^{-1}J^T` is solved by conjugate gradients (``jax.scipy.sparse.linalg.cg``,
one solve per quantity, vmapped) on Hessian-vector products of the profiled bound
(forward-over-reverse autodiff), so no Hessian is formed.  On a shared design the
quantities are taken in the eigenbasis of :math:`\Psi^T\Psi` (:mod:`.eigenbasis`),
where the profiled bound costs :math:`O(LdV^2)`; the covariance is kept there
(:attr:`LinearResponse.basis` rotates draws back).

Draws of the global quantities come from :math:`\mathcal N(E_q[g], \Sigma_{LR})`, the
precisions on the log scale; the local factors are drawn from the joint q as fitted.
``tests/test_linear_response.py`` checks the covariance against the exact posterior
covariance where the family is exact and against finite differences of the tilted
fixed point of the CAVI updates.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.scipy.special import digamma

from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference.cavi.bound import elbo
from lmpromp_ppl.inference.cavi.data import CaviData, SharedGram
from lmpromp_ppl.inference.cavi.eigenbasis import rotates, to_eigenbasis
from lmpromp_ppl.inference.cavi.state import CaviHyper, CaviState
from lmpromp_ppl.inference.cavi.updates import update_wh
from lmpromp_ppl.inference.compiled import compiled

__all__ = [
    "LinearResponse",
    "linear_response",
    "global_means",
    "quantity_names",
    "sample_lr",
    "log_q_lr",
    "log_q_globals",
    "split_quantities",
    "gaussian_draws",
    "CG_TOL",
    "METHODS",
    "response",
]

#: Relative residual at which each conjugate-gradient solve stops.
CG_TOL = 1e-10


class LinearResponse(NamedTuple):
    """The linear-response Gaussian of the global quantities (module docstring).

    Attributes
    ----------
    mean : (n,) :math:`E_q[g]` in the coordinates of ``basis``
    cov : (n, n) :math:`\\Sigma_{LR}` in those coordinates
    basis : (d, d) orthogonal U: b = U b', M = U M' (the identity on the general path)
    residual : () the largest relative residual :math:`\\|HX - J^T\\|/\\|J^T\\|` of the solves (per column)
    """

    mean: Array
    cov: Array
    basis: Array
    residual: Array


def quantity_names(d: int, V: int, learned_beta: bool) -> list[str]:
    """Names of the entries of g, in order: ``b[j]``, ``M[j,v]``, ``log_alpha``, ``log_lam[v]``, ``log_beta``."""
    names = [f"b[{j}]" for j in range(d)] + [f"M[{j},{v}]" for j in range(d) for v in range(V)]
    names += ["log_alpha"] + [f"log_lam[{v}]" for v in range(V)]
    return names + (["log_beta"] if learned_beta else [])


def _check(state: CaviState) -> None:
    if state.resp is not None or state.wh_cov is None:
        raise LmprompError("linear response is derived for the single type in the joint local family "
                           "(cavi.fit(..., local='joint'))")


def _pack(state: CaviState, learned: bool) -> Array:
    """The unconstrained global parameters :math:`\\eta` of the module docstring."""
    V = state.M_mean.shape[2]
    if state.M_var.ndim == 3:
        chol = jnp.linalg.cholesky(state.M_var[0])
        rows, cols = np.tril_indices(V)
        entries = jnp.where(rows == cols, jnp.log(jnp.diagonal(chol)[rows]), chol[rows, cols])
    else:
        entries = jnp.log(state.M_var[0])
    parts = [state.b_mean[0], jnp.log(state.b_var), state.M_mean[0].reshape(-1), entries,
             jnp.log(state.alpha_shape), jnp.log(state.alpha_rate), jnp.log(state.lam_shape[0]),
             jnp.log(state.lam_rate[0])]
    if learned:
        parts += [jnp.log(state.beta_shape)[None], jnp.log(state.beta_rate)[None]]
    return jnp.concatenate(parts)


def _unpack(eta: Array, template: CaviState, learned: bool) -> CaviState:
    """The state with the global factors of ``eta`` (inverse of :func:`_pack`)."""
    d, V = template.M_mean.shape[1:]
    cuts = np.cumsum([d, 1, d * V])
    b, log_b_var, M = eta[: cuts[0]], eta[cuts[0] : cuts[1]], eta[cuts[1] : cuts[2]].reshape(d, V)
    at = int(cuts[2])
    if template.M_var.ndim == 3:
        rows, cols = np.tril_indices(V)
        n = len(rows)
        entries = eta[at : at + n]
        chol = jnp.zeros((V, V)).at[rows, cols].set(jnp.where(rows == cols, jnp.exp(entries), entries))
        M_var = (chol @ chol.T)[None]
    else:
        n = V
        M_var = jnp.exp(eta[at : at + n])[None]
    at += n
    alpha = jnp.exp(eta[at : at + 2])
    lam = jnp.exp(eta[at + 2 : at + 2 + 2 * V]).reshape(2, V)
    fields = dict(b_mean=b[None], b_var=jnp.exp(log_b_var), M_mean=M[None], M_var=M_var,
                  alpha_shape=alpha[:1], alpha_rate=alpha[1:], lam_shape=lam[:1], lam_rate=lam[1:])
    if learned:
        beta = jnp.exp(eta[at + 2 + 2 * V : at + 4 + 2 * V])
        fields.update(beta_shape=beta[0], beta_rate=beta[1])
    return template._replace(**fields)


def global_means(state: CaviState, learned: bool) -> Array:
    """(n,) :math:`E_q[g]`: the means of b and M, and :math:`E[\\log x] = \\psi(a) - \\log r` of each precision."""
    parts = [state.b_mean[0], state.M_mean[0].reshape(-1),
             digamma(state.alpha_shape) - jnp.log(state.alpha_rate),
             digamma(state.lam_shape[0]) - jnp.log(state.lam_rate[0])]
    if learned:
        parts.append((digamma(state.beta_shape) - jnp.log(state.beta_rate))[None])
    return jnp.concatenate(parts)


def _profiled_bound(eta: Array, template: CaviState, data: CaviData, hyper: CaviHyper, learned: bool) -> Array:
    """The bound at the closed-form optimum of the local factors given the global factors ``eta``."""
    state = update_wh(_unpack(eta, template, learned), data, hyper)
    return elbo(state, data, hyper)


def _preconditioner(state: CaviState, learned: bool, hvp) -> tuple:
    """A block-diagonal approximation of H, inverted: the conjugate-gradient preconditioner.

    The Hessian of the bound in the means of q(b) and q(M) is the precision of those
    factors (:math:`\\sigma_b^{-1}I`, :math:`\\Sigma_M^{-1}` per row; column variances for
    the column-wise family) plus the couplings that the linear response adds; the remaining
    few parameters (variances, Gamma shapes and rates) get their exact dense block of H
    from one Hessian-vector product per parameter.
    """
    d, V = state.M_mean.shape[1:]
    size = _pack(state, learned).shape[0]
    head = d + 1 + d * V  # b, log sigma_b, M
    rest = jnp.concatenate([jnp.asarray([d]), jnp.arange(head, size)])  # log sigma_b and everything after M
    probes = jnp.zeros((rest.shape[0], size)).at[jnp.arange(rest.shape[0]), rest].set(1.0)
    block = jax.vmap(hvp)(probes)[:, rest]
    block_inv = jnp.linalg.inv(0.5 * (block + block.T))
    M_cov = state.M_var[0] if state.M_var.ndim == 3 else jnp.diag(state.M_var[0])
    b_var = state.b_var[0]

    def apply(r):
        out = jnp.zeros_like(r)
        out = out.at[:d].set(b_var * r[:d])
        out = out.at[d + 1 : head].set((r[d + 1 : head].reshape(d, V) @ M_cov).reshape(-1))
        return out.at[rest].set(block_inv @ r[rest])

    return apply


def response(state: CaviState, data: CaviData, hyper: CaviHyper, learned: bool, method: str = "dense",
             maxiter: int = 0) -> LinearResponse:
    """The traceable body of :func:`linear_response` (``vmap``-able over replicates, as SBC does).

    On a shared design with the state's covariances in its eigenbasis the solve runs in
    the rotated coordinates (:mod:`.eigenbasis`) and the basis is returned with the result.
    """
    d = state.M_mean.shape[1]
    basis = jnp.eye(d)
    if rotates(state, data):
        basis = data.gram.basis
        state, data = to_eigenbasis(state, data)
    elif isinstance(data.gram, SharedGram):
        raise LmprompError("the state's weight covariances are not stored in the data's eigenbasis")
    maxiter = int(maxiter) or 4 * int(_pack(state, learned).shape[0])
    means, cov, residual = _solve(state, data, hyper, learned, method, maxiter)
    return LinearResponse(means, cov, basis, residual)


def _solve(state: CaviState, data: CaviData, hyper: CaviHyper, learned: bool, method: str, maxiter: int):
    eta = _pack(state, learned)
    negative = lambda e: -_profiled_bound(e, state, data, hyper, learned)  # noqa: E731
    gradient = jax.grad(negative)

    def hvp(v):
        return jax.jvp(gradient, (eta,), (v,))[1]

    means, vjp = jax.vjp(lambda e: global_means(_unpack(e, state, learned), learned), eta)
    rhs = jax.vmap(lambda e: vjp(e)[0])(jnp.eye(means.shape[0]))  # rows of J, i.e. columns of J^T
    if method == "dense":
        # H column by column: one Hessian-vector product per global parameter, batched
        hessian = jax.vmap(hvp)(jnp.eye(eta.shape[0]))
        hessian = 0.5 * (hessian + hessian.T)
        solutions = jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(hessian), True), rhs.T).T
        residuals = jnp.linalg.norm(solutions @ hessian - rhs, axis=1) / jnp.linalg.norm(rhs, axis=1)
    else:
        precondition = _preconditioner(state, learned, hvp)

        def one(b):
            x, _ = jax.scipy.sparse.linalg.cg(hvp, b, tol=CG_TOL, maxiter=maxiter, M=precondition)
            return x, jnp.linalg.norm(hvp(x) - b) / jnp.maximum(jnp.linalg.norm(b), 1e-300)

        solutions, residuals = jax.vmap(one)(rhs)  # (n, dim eta): H^-1 J^T, row by row
    cov = rhs @ solutions.T
    return means, 0.5 * (cov + cov.T), jnp.max(residuals)


#: Ways of solving :math:`H X = J^T` (:func:`linear_response`).
METHODS = ("dense", "cg")


def linear_response(state: CaviState, data: CaviData, hyper: CaviHyper, *, method: str = "dense",
                    maxiter: int | None = None, timed: bool = False):
    """:math:`E_q[g]` and :math:`\\Sigma_{LR}` at a converged state of the joint local family (module docstring).

    ``data`` and ``hyper`` are those of the fit.  ``method`` solves :math:`HX = J^T`:

    * ``"dense"`` (default): H from one Hessian-vector product per global parameter
      (batched), then a Cholesky solve.  H is :math:`p \\times p` with
      :math:`p = d(V + 1) + O(V^2)` global parameters, the size of the covariance it gives;
      it costs p products.
    * ``"cg"``: one preconditioned conjugate-gradient solve per quantity
      (:func:`_preconditioner`), k products each: cheaper only when far fewer quantities
      than parameters are wanted (here there are about as many, so k n > p).

    ``maxiter`` bounds each conjugate-gradient solve (default: four times the number of
    global parameters).  ``timed=True`` returns ``(LinearResponse, compile seconds)``.
    """
    _check(state)
    if method not in METHODS:
        raise LmprompError(f"unknown linear-response method {method!r}; choose from {list(METHODS)}")
    learned = bool(state.beta_learned)
    executable, seconds = compiled(_response_jit, (state, data, hyper), learned=learned, method=method,
                                   maxiter=int(maxiter or 0))
    lr = jax.block_until_ready(executable(state, data, hyper))
    return (lr, seconds) if timed else lr


_response_jit = jax.jit(response, static_argnames=("learned", "method", "maxiter"))


def sample_lr(key: Array, lr: LinearResponse, state: CaviState, num_draws: int, learned_beta: bool) -> dict:
    """Draws of the global quantities from the linear-response Gaussian, the locals from the joint q.

    The sites and shapes of :func:`~.posterior.sample_q` (single type): ``b`` (n, d),
    ``M`` (n, d, V), ``alpha`` (n,), ``lam`` (n, V), ``beta`` (n,) when learned, and
    ``h``, ``w`` from the fitted q(w_i, h_i).
    """
    from lmpromp_ppl.inference.cavi.posterior import sample_q

    k_g, k_l = jax.random.split(key)
    d, V = state.M_mean.shape[1:]
    draws = dict(sample_q(k_l, state, num_draws, learned_beta))
    draws.update(split_quantities(gaussian_draws(k_g, lr, num_draws), lr.basis, d, V, learned_beta))
    return draws


def gaussian_draws(key: Array, lr: LinearResponse, num_draws: int) -> Array:
    """(num_draws, n) draws of g from :math:`\\mathcal N(E_q[g], \\Sigma_{LR})` in the coordinates of ``lr.basis``."""
    z = jax.random.normal(key, (num_draws, lr.mean.shape[0]))
    return lr.mean + z @ jnp.linalg.cholesky(lr.cov + _jitter(lr.cov)).T


def split_quantities(g: Array, basis: Array, d: int, V: int, learned: bool) -> dict:
    """Draws of g (n, size) as the sites ``b``, ``M``, ``alpha``, ``lam`` (and ``beta``), rotated back by ``basis``."""
    c = np.cumsum([d, d * V, 1, V])
    out = {
        "b": g[:, : c[0]] @ basis.T,
        "M": jnp.einsum("dj,njv->ndv", basis, g[:, c[0] : c[1]].reshape(-1, d, V)),
        "alpha": jnp.exp(g[:, c[1]]),
        "lam": jnp.exp(g[:, c[2] : c[3]]),
    }
    if learned:
        out["beta"] = jnp.exp(g[:, c[3]])
    return out


def log_q_globals(lr: LinearResponse, draws: dict) -> Array:
    """log density of the global draws under the linear-response Gaussian (Jacobians of the log scale included).

    ``draws`` has ``b``, ``M``, ``alpha``, ``lam`` and, when learned, ``beta`` with a leading draw axis.
    """
    import numpyro.distributions as dist

    learned = "beta" in draws
    basis = lr.basis
    n = draws["b"].shape[0]
    parts = [draws["b"] @ basis, jnp.einsum("dj,ndv->njv", basis, draws["M"]).reshape(n, -1),
             jnp.log(draws["alpha"])[:, None], jnp.log(draws["lam"])]
    jacobian = -jnp.log(draws["alpha"]) - jnp.sum(jnp.log(draws["lam"]), axis=-1)
    if learned:
        parts.append(jnp.log(draws["beta"])[:, None])
        jacobian = jacobian - jnp.log(draws["beta"])
    gaussian = dist.MultivariateNormal(lr.mean, scale_tril=jnp.linalg.cholesky(lr.cov + _jitter(lr.cov)))
    return gaussian.log_prob(jnp.concatenate(parts, axis=1)) + jacobian


def _jitter(cov: Array) -> Array:
    return 1e-12 * jnp.max(jnp.diagonal(cov)) * jnp.eye(cov.shape[0])


def log_q_lr(lr: LinearResponse, state: CaviState, draws: dict) -> Array:
    """log density of draws under :func:`sample_lr`'s distribution: the global Gaussian and the joint local q."""
    from lmpromp_ppl.inference.cavi.posterior import log_q_locals

    return log_q_globals(lr, draws) + log_q_locals(state, draws)

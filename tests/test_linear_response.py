"""Linear-response covariances (:mod:`lmpromp_ppl.inference.cavi.linear_response`) and the ``cavi_lr`` draws.

* where the family's global block is exact up to a Gaussian posterior (alpha and lam at
  point masses, so M = 0 and the posterior of b is Gaussian), the linear-response
  covariance of b is the exact posterior covariance, which q(b) is not;
* on a general problem it equals the finite-difference response of the tilted fixed
  point of the CAVI updates themselves (an independent route: no Hessian);
* the conjugate-gradient solves converge and the draws have the covariance.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats
from test_cavi import HYPER, HYPER_ARR, small  # noqa: F401  (small is a fixture)

from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference import cavi
from lmpromp_ppl.inference.cavi.linear_response import (
    global_means,
    linear_response,
    log_q_globals,
    quantity_names,
    sample_lr,
)
from lmpromp_ppl.inference.cavi.updates import JOINT_UPDATES
from lmpromp_ppl.models.hyper import Hyperparameters

V = HYPER.latent_dim


def _fit(model_data, hyper, family="rowwise", tol=1e-12):
    fit = cavi.fit(model_data, hyper, jax.random.key(0), local="joint", family=family, tol=tol, max_iter=50000)
    assert fit.converged
    return fit.state


@pytest.mark.parametrize("path", ["shared", "missing"])
def test_linear_response_is_exact_where_the_posterior_is_gaussian(small, path):
    """alpha and lam at point masses (lam huge: M = 0): b | y is Gaussian, and LR recovers its covariance."""
    alpha, lam, point = 100.0, 1e8, 1e9
    hyper = Hyperparameters(beta=HYPER.beta, latent_dim=V, a0=point, b0=point / alpha, c0=point, d0=point / lam)
    model_data = small[path]
    state = _fit(model_data, hyper, tol=1e-10)  # the Gamma terms at shape 1e9 are exact to ~1e-9 nats only
    data = cavi.sufficient_statistics(model_data)
    lr = linear_response(state, data, cavi.hyper_arrays(hyper))
    assert float(lr.residual) < 1e-6
    psi, _, mask = (np.asarray(a) for a in model_data)
    d = psi.shape[2]
    precision = hyper.lambda0 * np.eye(d)
    for i in range(psi.shape[0]):
        rows = psi[i][mask[i] > 0]
        marginal = np.eye(len(rows)) / hyper.beta + rows @ rows.T / alpha
        precision += rows.T @ np.linalg.solve(marginal, rows)
    exact = np.linalg.inv(precision)
    basis = np.asarray(lr.basis)
    lr_b = basis @ np.asarray(lr.cov)[:d, :d] @ basis.T
    np.testing.assert_allclose(lr_b, exact, rtol=1e-4, atol=1e-6 * np.max(np.abs(exact)))
    # resolution: the factor q(b) itself is far from it
    assert np.max(np.abs(float(state.b_var[0]) * np.eye(d) - exact)) > 0.1 * np.max(np.abs(exact))


# --------------------------------------------------------------------------- tilted fixed point
def _tilted_sweeps(state, data, hyper, t_b, t_log_alpha, t_M, sweeps):
    """Plain sweeps of the joint family's updates for the bound plus t . E[g] (b, log alpha, M tilted).

    A linear tilt of E[b] adds t to q(b)'s linear term (its mean moves by sigma_b t); of
    E[log alpha] adds t to q(alpha)'s shape; of E[M] adds t_j to row j's linear term (its mean
    moves by t_j Sigma_M).  Every other update is unchanged.
    """
    def update(s):
        for name, fn in JOINT_UPDATES.items():
            s = fn(s, data, hyper)
            if name == "b":
                s = s._replace(b_mean=s.b_mean + s.b_var[:, None] * t_b[None])
            elif name == "M":
                s = s._replace(M_mean=s.M_mean + jnp.einsum("dv,kvu->kdu", t_M, s.M_var))
            elif name == "alpha":
                s = s._replace(alpha_shape=s.alpha_shape + t_log_alpha)
        return s

    return jax.lax.fori_loop(0, sweeps, lambda _, s: update(s), state)


_tilted = jax.jit(_tilted_sweeps, static_argnames="sweeps")


def test_linear_response_equals_the_finite_difference_of_the_tilted_fixed_point(small):
    model_data = small["missing"]
    state = _fit(model_data, HYPER)
    data = cavi.sufficient_statistics(model_data)
    lr = linear_response(state, data, HYPER_ARR)
    assert float(lr.residual) < 1e-6
    d = state.M_mean.shape[1]
    names = quantity_names(d, V, False)
    n = len(names)
    assert lr.cov.shape == (n, n)
    eps = 1e-4
    columns = {"b[3]": names.index("b[3]"), "log_alpha": names.index("log_alpha"), "M[2,1]": names.index("M[2,1]")}
    for label, column in columns.items():
        tilts = []
        for sign in (1.0, -1.0):
            t_b, t_M, t_a = np.zeros(d), np.zeros((d, V)), 0.0
            if label == "b[3]":
                t_b[3] = sign * eps
            elif label == "log_alpha":
                t_a = sign * eps
            else:
                t_M[2, 1] = sign * eps
            moved = _tilted(state, data, HYPER_ARR, jnp.asarray(t_b), jnp.asarray(t_a), jnp.asarray(t_M), 20000)
            tilts.append(np.asarray(global_means(moved, False)))
        response = (tilts[0] - tilts[1]) / (2 * eps)
        # the covariance is of the general path's coordinates (identity basis): compare directly
        np.testing.assert_allclose(response, np.asarray(lr.cov)[:, column], rtol=2e-3,
                                   atol=2e-3 * float(np.abs(lr.cov[column, column])), err_msg=label)


def test_draws_have_the_linear_response_covariance_and_density(small):
    model_data = small["shared"]
    state = _fit(model_data, HYPER)
    data = cavi.sufficient_statistics(model_data)
    lr = linear_response(state, data, HYPER_ARR)
    num = 20000
    draws = sample_lr(jax.random.key(3), lr, state, num, False)
    log_alpha = np.log(np.asarray(draws["alpha"]))
    names = quantity_names(state.M_mean.shape[1], V, False)
    index = names.index("log_alpha")
    sd = float(np.sqrt(lr.cov[index, index]))
    # Monte Carlo error of a sample sd: sd / sqrt(2 (n - 1))
    assert abs(np.std(log_alpha, ddof=1) - sd) < 4.0 * sd / np.sqrt(2 * (num - 1))
    b = np.asarray(draws["b"]) @ np.asarray(lr.basis)  # in the coordinates of the covariance
    np.testing.assert_allclose(np.mean(b, axis=0), lr.mean[: b.shape[1]],
                               atol=4.0 * float(np.sqrt(np.max(np.diag(lr.cov)))) / np.sqrt(num))
    # the density: a Gaussian in g (scipy) with the Jacobians of the log scale
    few = {k: np.asarray(v[:5]) for k, v in draws.items()}
    g = np.concatenate([few["b"] @ np.asarray(lr.basis),
                        np.einsum("dj,ndv->njv", np.asarray(lr.basis), few["M"]).reshape(5, -1),
                        np.log(few["alpha"])[:, None], np.log(few["lam"])], axis=1)
    reference = (scipy.stats.multivariate_normal(np.asarray(lr.mean), np.asarray(lr.cov)).logpdf(g)
                 - np.log(few["alpha"]) - np.log(few["lam"]).sum(-1))
    np.testing.assert_allclose(np.asarray(log_q_globals(lr, few)), reference, rtol=1e-6)


def test_linear_response_needs_the_joint_family(small):
    state = cavi.fit(small["shared"], HYPER, jax.random.key(0)).state
    with pytest.raises(LmprompError, match="joint local family"):
        linear_response(state, cavi.sufficient_statistics(small["shared"]), HYPER_ARR)


def test_conjugate_gradients_agree_with_the_dense_solve(small):
    model_data = small["missing"]
    state = _fit(model_data, HYPER, family="columnwise")
    data = cavi.sufficient_statistics(model_data)
    dense = linear_response(state, data, HYPER_ARR, method="dense")
    cg = linear_response(state, data, HYPER_ARR, method="cg")
    assert float(cg.residual) < 1e-8 and float(dense.residual) < 1e-8
    np.testing.assert_allclose(np.asarray(cg.cov), np.asarray(dense.cov), rtol=1e-6,
                               atol=1e-8 * float(np.max(np.abs(dense.cov))))
    with pytest.raises(LmprompError, match="unknown linear-response method"):
        linear_response(state, data, HYPER_ARR, method="lu")

r"""The variational families of SVI: the hand-written meanfield guide (CAVI's family, eq. 4.3),
NumPyro's automatic guides, and the conversions between meanfield parameters and a CAVI state.

See :mod:`lmpromp_ppl.inference.svi` for the engine that optimises them.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping

import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
from numpyro import handlers
from numpyro.distributions import constraints
from numpyro.infer.autoguide import AutoLowRankMultivariateNormal, AutoNormal

from lmpromp_ppl.data.core import ModelData, demo_statistics
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.models.hyper import Hyperparameters
from lmpromp_ppl.models.lmpromp import lmpromp_model
from lmpromp_ppl.models.registry import model_function, resolve_collapse

__all__ = [
    "GUIDES",
    "make_guide",
    "meanfield_guide",
    "meanfield_init",
    "meanfield_params_from_cavi",
    "cavi_state_from_meanfield",
]

GUIDES = ("meanfield", "autonormal", "lowrank")


def meanfield_guide(data: ModelData, hyper: Hyperparameters, fixed: Mapping | None = None) -> None:
    r"""Guide of CAVI's family (eq. 4.3) for the full single-type LMProMP.

    Variational parameters (``numpyro.param``; positive ones constrained):
    ``w_loc`` (L, d), ``w_scale_tril`` (L, d, d), ``h_loc`` (L, V),
    ``h_scale_tril`` (L, V, V), ``b_loc`` (d,), ``b_var`` () (:math:`\sigma_b`),
    ``M_loc`` (d, V), ``M_var`` (V,) (:math:`\sigma_{m_v}`), ``alpha_shape``,
    ``alpha_rate`` () (:math:`\bar a, \bar b`), ``lam_shape``, ``lam_rate`` (V,)
    (:math:`\bar c, \bar d_v`), and ``beta_shape``, ``beta_rate`` when
    ``hyper.learn_beta``.  Their initial values come from ``SVI.init``'s
    ``init_params`` (:func:`meanfield_init`).

    ``fixed`` is accepted for the common ``guide(data, fixed)`` signature and
    must be empty.
    """
    if fixed:
        raise LmprompError("the meanfield guide does not support fixed sites")
    num_demos, num_weights = data.num_demos, data.num_weights  # ModelData or SharedDesign
    num_latent = hyper.latent_dim
    eye_d = jnp.eye(num_weights)
    eye_v = jnp.eye(num_latent)
    w_loc = numpyro.param("w_loc", jnp.zeros((num_demos, num_weights)))
    w_tril = numpyro.param("w_scale_tril", jnp.broadcast_to(0.1 * eye_d, (num_demos, num_weights, num_weights)),
                           constraint=constraints.lower_cholesky)
    h_loc = numpyro.param("h_loc", jnp.zeros((num_demos, num_latent)))
    h_tril = numpyro.param("h_scale_tril", jnp.broadcast_to(0.1 * eye_v, (num_demos, num_latent, num_latent)),
                           constraint=constraints.lower_cholesky)
    b_loc = numpyro.param("b_loc", jnp.zeros(num_weights))
    b_var = numpyro.param("b_var", jnp.array(0.01), constraint=constraints.positive)
    M_loc = numpyro.param("M_loc", jnp.zeros((num_weights, num_latent)))
    M_var = numpyro.param("M_var", jnp.full(num_latent, 0.01), constraint=constraints.positive)
    alpha_shape = numpyro.param("alpha_shape", jnp.array(1.0), constraint=constraints.positive)
    alpha_rate = numpyro.param("alpha_rate", jnp.array(1.0), constraint=constraints.positive)
    lam_shape = numpyro.param("lam_shape", jnp.ones(num_latent), constraint=constraints.positive)
    lam_rate = numpyro.param("lam_rate", jnp.ones(num_latent), constraint=constraints.positive)

    numpyro.sample("b", dist.Normal(b_loc, jnp.sqrt(b_var)).to_event(1))
    numpyro.sample("lam", dist.Gamma(lam_shape, lam_rate).to_event(1))
    numpyro.sample("M", dist.Normal(M_loc, jnp.broadcast_to(jnp.sqrt(M_var), M_loc.shape)).to_event(2))
    numpyro.sample("alpha", dist.Gamma(alpha_shape, alpha_rate))
    if hyper.learn_beta:
        beta_shape = numpyro.param("beta_shape", jnp.array(hyper.beta_a0), constraint=constraints.positive)
        beta_rate = numpyro.param("beta_rate", jnp.array(hyper.beta_b0), constraint=constraints.positive)
        numpyro.sample("beta", dist.Gamma(beta_shape, beta_rate))
    with numpyro.plate("demo", num_demos):
        numpyro.sample("h", dist.MultivariateNormal(h_loc, scale_tril=h_tril))
        numpyro.sample("w", dist.MultivariateNormal(w_loc, scale_tril=w_tril))


def meanfield_init(data: ModelData, hyper: Hyperparameters) -> dict[str, np.ndarray]:
    r"""A starting point for :func:`meanfield_guide` in the spirit of Sec. 4.1.1.

    Per-demonstration ridge regression :math:`\hat{\mathbf w}_i = (\beta\Psi_i^T\Psi_i
    + \mathbf I)^{-1}\beta\Psi_i^T \mathbf y_i`; ``b`` their mean; ``M`` and ``h``
    from the leading V principal directions (``h`` scaled to unit variance, the
    thesis's PCA initialisation); then one pass of the Sec. 4.1.1 formulas for the
    covariances and the Gamma factors given these means.
    """
    stats = demo_statistics(data)  # Psi_i^T Psi_i and Psi_i^T y_i, without a dense design for compact inputs
    gram, cross = np.asarray(stats.gram), np.asarray(stats.cross)
    num_demos, num_weights = cross.shape
    num_latent = hyper.latent_dim
    beta = hyper.beta_a0 / hyper.beta_b0 if hyper.learn_beta else hyper.beta
    w_hat = np.linalg.solve(beta * gram + np.eye(num_weights), beta * cross[..., None])[..., 0]
    b = w_hat.mean(axis=0)
    centred = w_hat - b
    _, sing, vt = np.linalg.svd(centred, full_matrices=False)
    sing = np.concatenate([sing, np.zeros(num_latent)])[:num_latent]
    vt = np.concatenate([vt, np.zeros((num_latent, num_weights))])[:num_latent]
    scale = sing / np.sqrt(num_demos)
    M = vt.T * scale
    h = np.where(scale > 0, (centred @ vt.T) / np.where(scale > 0, scale, 1.0), 0.0)
    resid = centred - h @ M.T
    a_bar = hyper.a0 + 0.5 * num_demos * num_weights
    b_bar = hyper.b0 + 0.5 * np.sum(resid**2) + 1e-3 * a_bar  # keeps E[alpha] finite on exact fits
    alpha = a_bar / b_bar
    w_cov = np.linalg.inv(beta * gram + alpha * np.eye(num_weights))
    lam = (hyper.c0 + 0.5 * num_weights) / (hyper.d0 + 0.5 * np.sum(M**2, axis=0))
    h_cov = np.linalg.inv(alpha * M.T @ M + hyper.gamma * np.eye(num_latent))
    init = {
        "w_loc": w_hat,
        "w_scale_tril": np.linalg.cholesky(w_cov),
        "h_loc": h,
        "h_scale_tril": np.broadcast_to(np.linalg.cholesky(h_cov), (num_demos, num_latent, num_latent)).copy(),
        "b_loc": b,
        "b_var": np.asarray(1.0 / (num_demos * alpha + hyper.lambda0)),
        "M_loc": M,
        "M_var": 1.0 / (alpha * np.sum(h**2, axis=0) + lam),
        "alpha_shape": np.asarray(a_bar),
        "alpha_rate": np.asarray(b_bar),
        "lam_shape": np.full(num_latent, hyper.c0 + 0.5 * num_weights),
        "lam_rate": hyper.d0 + 0.5 * np.sum(M**2, axis=0),
    }
    if hyper.learn_beta:
        init["beta_shape"] = np.asarray(hyper.beta_a0)
        init["beta_rate"] = np.asarray(hyper.beta_b0)
    return init


def meanfield_params_from_cavi(state) -> dict[str, np.ndarray]:
    """The :func:`meanfield_guide` parameters of a single-type CAVI state (same factors, eq. 4.3).

    Parameters
    ----------
    state : a K = 1 column-wise :class:`lmpromp_ppl.inference.cavi.CaviState`
        (``beta_shape``/``beta_rate`` are included when it learns beta)

    Returns
    -------
    dict of guide parameters (covariances as Cholesky factors)
    """
    from lmpromp_ppl.inference.cavi import is_mixture, w_covariance

    if is_mixture(state) or state.M_var.ndim != 2:
        raise LmprompError("the meanfield guide has the factors of the single-type column-wise CAVI state only")
    params = {
        "w_loc": np.asarray(state.w_mean),
        "w_scale_tril": np.linalg.cholesky(np.asarray(w_covariance(state))),
        "h_loc": np.asarray(state.h_mean[:, 0]),
        "h_scale_tril": np.linalg.cholesky(np.asarray(state.h_cov[:, 0])),
        "b_loc": np.asarray(state.b_mean[0]),
        "b_var": np.asarray(state.b_var[0]),
        "M_loc": np.asarray(state.M_mean[0]),
        "M_var": np.asarray(state.M_var[0]),
        "alpha_shape": np.asarray(state.alpha_shape[0]),
        "alpha_rate": np.asarray(state.alpha_rate[0]),
        "lam_shape": np.asarray(state.lam_shape[0]),
        "lam_rate": np.asarray(state.lam_rate[0]),
    }
    if bool(state.beta_learned):
        params["beta_shape"] = np.asarray(state.beta_shape)
        params["beta_rate"] = np.asarray(state.beta_rate)
    return params


def cavi_state_from_meanfield(params: Mapping[str, Any]):
    """The CAVI state (K = 1) holding the factors of :func:`meanfield_guide` parameters.

    With it, :func:`lmpromp_ppl.inference.cavi.elbo` evaluates the closed-form
    bound at SVI's parameters.  The weight covariances are full matrices
    (``FullCovariance``), so evaluate it on data prepared with
    ``cavi.sufficient_statistics(data, shared_psi=False)``.  A guide with
    ``beta_shape``/``beta_rate`` gives a state with q(beta).
    """
    from lmpromp_ppl.inference.cavi import FullCovariance, lift_single_type

    p = {k: jnp.asarray(v, jnp.float64) for k, v in params.items()}
    w_tril, h_tril = p["w_scale_tril"], p["h_scale_tril"]
    fields = dict(
        w_mean=p["w_loc"],
        w_cov=FullCovariance(w_tril @ jnp.swapaxes(w_tril, -1, -2)),
        h_mean=p["h_loc"],
        h_cov=h_tril @ jnp.swapaxes(h_tril, -1, -2),
        b_mean=p["b_loc"],
        b_var=p["b_var"],
        M_mean=p["M_loc"],
        M_var=p["M_var"],
        alpha_shape=p["alpha_shape"],
        alpha_rate=p["alpha_rate"],
        lam_shape=p["lam_shape"],
        lam_rate=p["lam_rate"],
    )
    beta = (p["beta_shape"], p["beta_rate"]) if "beta_shape" in p else None
    return lift_single_type(fields, beta=beta)


def make_guide(name: str, model_name: str, data: ModelData, hyper: Hyperparameters, *,
               collapsed: str = "w", rank: int | None = None,
               fixed_names: tuple[str, ...] = ()) -> tuple[Callable, Callable]:
    """The model and guide pair, both called as ``fn(data, fixed)``.

    Parameters
    ----------
    name : ``"meanfield"``, ``"autonormal"`` or ``"lowrank"``
    model_name : ``"promp"``, ``"lmpromp"`` or ``"mixture"``
    data : model inputs (the guides built here take their shapes at run time;
        kept so that every guide factory has the same signature)
    hyper : hyperparameters
    collapsed : for the automatic guides, ``"w"`` (default), ``"wh"`` or
        ``"none"``; the meanfield guide is always on the full model
    rank : rank of the low-rank guide (None: numpyro's default)
    fixed_names : sites that the model is conditioned on (automatic guides only)

    Returns
    -------
    model, guide
    """
    if name not in GUIDES:
        raise LmprompError(f"unknown guide {name!r}; choose from {list(GUIDES)}")
    if name == "meanfield":
        if model_name != "lmpromp":
            raise LmprompError(
                f"the svi_meanfield guide exists for the single-type 'lmpromp' model only, not {model_name!r}"
            )
        if fixed_names:
            raise LmprompError("the meanfield guide does not support fixed sites")

        def full_model(data, fixed):
            lmpromp_model(data, hyper)

        return full_model, lambda data, fixed: meanfield_guide(data, hyper, fixed)
    collapse = resolve_collapse(model_name, collapsed)
    base = model_function(model_name, collapse)

    def model(data, fixed):
        with handlers.condition(data=fixed):
            base(data, hyper)

    if name == "autonormal":
        return model, AutoNormal(model)
    if rank is not None and (isinstance(rank, bool) or int(rank) != rank or rank < 1):
        raise LmprompError(f"rank must be an integer >= 1, got {rank!r}")
    return model, AutoLowRankMultivariateNormal(model, rank=rank)

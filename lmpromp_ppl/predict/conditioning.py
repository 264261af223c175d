r"""Prediction by conditioning: ProMP (Sec. 3.1.2), LMProMP (Sec. 4.1.2), mixture (Sec. 4.2.2).

Parameters are plain dicts of arrays with the site names of docs/cli.md, in
the standardised space of the fit:

* ``"promp"``: ``mu_w`` (d,), ``Sigma_w`` (d, d);
* ``"lmpromp"``: ``b`` (d,), ``M`` (d, V), ``alpha`` ();
* ``"mixture"``: ``pi`` (K,), ``b`` (K, d), ``M`` (K, d, V), ``alpha`` (K,).

``gamma`` is the *precision* of the control variables,
:math:`p(\mathbf{h}) = \mathcal{N}(\mathbf{0}, \gamma^{-1} I_V)` as in the
prior of Sec. 4.1; eqs. (4.4), (4.5) and the :math:`A` above them write
:math:`\gamma` where :math:`\gamma^{-1}` belongs (erratum; they agree only for
:math:`\gamma = 1`, the value used in the thesis).

Every conditioning returns a :class:`Conditioned`: the conditioned weight
distribution as a :class:`~lmpromp_ppl.predict.gaussian.GaussianMixture` (one
component, or one per mixture component weighted by its responsibility), the
conditioned control variables, and the log evidence
:math:`\log p(\mathbf{o})`.  :func:`condition_draws` averages over posterior
draws of any engine.

The conditioning functions are pure and jit-compiled (:func:`condition_draws`
selects the sites it needs, then calls a compiled function); ``model``,
``exact`` and ``reweight`` are static (Python values), everything else is traced, so new
parameter values or a new ``gamma`` of the same shapes do not recompile.
"""

from __future__ import annotations

import math
from functools import partial
from typing import Mapping, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.scipy.special import logsumexp
from jax.typing import ArrayLike

from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.models.registry import MODEL_NAMES as MODELS
from lmpromp_ppl.predict.gaussian import GaussianMixture, condition_gaussian, observation_marginal
from lmpromp_ppl.predict.observations import Observation, empty_observation

__all__ = [
    "MODELS",
    "SITES",
    "Conditioned",
    "condition_promp",
    "condition_lmpromp",
    "condition_mixture",
    "condition",
    "prior",
    "condition_draws",
    "condition_further",
    "num_sample_dims",
]

#: Model names accepted by :func:`condition`.

#: Sites each model's conditioning reads, with their number of (non-sample) dims.
SITES: dict[str, dict[str, int]] = {
    "promp": {"mu_w": 1, "Sigma_w": 2},
    "lmpromp": {"b": 1, "M": 2, "alpha": 0},
    "mixture": {"pi": 1, "b": 2, "M": 3, "alpha": 1},
}


class Conditioned(NamedTuple):
    r"""A predictive distribution conditioned on an :class:`Observation`.

    Attributes
    ----------
    weights : GaussianMixture
        :math:`p(\mathbf{w} | \mathbf{o})`: components (d,) / (d, d) with
        their responsibilities as ``log_weights``.
    latent : GaussianMixture or None
        :math:`p(\mathbf{h} | \mathbf{o})` per component (eqs. 4.4, 4.5);
        ``None`` for the ProMP.
    log_evidence : () array
        :math:`\log p(\mathbf{o})` under the model (0 for no observation).
    """

    weights: GaussianMixture
    latent: GaussianMixture | None
    log_evidence: Array


def _site(params: Mapping[str, ArrayLike], name: str, model: str) -> Array:
    if name not in params:
        raise LmprompError(f"{model} parameters lack site {name!r}; got {sorted(params)}")
    return jnp.asarray(params[name], dtype=jnp.float64)


def _check_weight_dim(observation: Observation, num_weights: int, model: str) -> None:
    if observation.psi.ndim != 2 or observation.psi.shape[1] != num_weights:
        raise LmprompError(
            f"observation has weight dimension {observation.psi.shape[-1]}, "
            f"the {model} parameters have d={num_weights}"
        )


def _single(mean: Array, cov: Array) -> GaussianMixture:
    return GaussianMixture(jnp.zeros((1,)), mean[None], cov[None])


@jax.jit
def condition_promp(params: Mapping[str, ArrayLike], observation: Observation) -> Conditioned:
    r"""ProMP conditioning, eqs. (3.2) and (3.3).

    Parameters
    ----------
    params : dict
        ``mu_w`` (d,) and ``Sigma_w`` (d, d).
    observation : Observation

    Returns
    -------
    Conditioned
        One component :math:`\mathcal{N}(\boldsymbol\mu_{w|o}, \Sigma_{w|o})`;
        ``latent`` is None; ``log_evidence`` is
        :math:`\log\mathcal{N}(\mathbf{o} | \Psi_o\boldsymbol\mu_w, \Sigma_o + \Psi_o\Sigma_w\Psi_o^T)`.
    """
    mean = _site(params, "mu_w", "promp")
    cov = _site(params, "Sigma_w", "promp")
    if mean.ndim != 1 or cov.shape != mean.shape * 2:
        raise LmprompError(f"promp needs mu_w (d,) and Sigma_w (d, d), got {mean.shape} and {cov.shape}")
    _check_weight_dim(observation, mean.shape[0], "promp")
    post_mean, post_cov, log_evidence = condition_gaussian(mean, cov, observation)
    return Conditioned(_single(post_mean, post_cov), None, log_evidence)


def _lmpromp_core(
    b: Array, M: Array, alpha: Array, gamma: Array, observation: Observation, exact: bool
) -> tuple[Array, Array, Array, Array, Array]:
    num_weights, latent_dim = M.shape
    # Weight prior with h integrated out: N(w | b, alpha^-1 I + gamma^-1 M M^T).
    prior_cov = jnp.eye(num_weights) / alpha + M @ M.T / gamma
    marginal = observation_marginal(prior_cov, observation)  # A of Sec. 4.1.2, with gamma^-1
    mean, cov, log_marginal = condition_gaussian(b, prior_cov, observation, marginal)
    latent_gain = observation.psi @ M  # Psi_o M, (N, V)
    residual = observation.values - observation.psi @ b
    latent_mean = marginal.quad(latent_gain, residual) / gamma  # eq. (4.4), gamma^-1
    latent_cov = jnp.eye(latent_dim) / gamma - marginal.quad(latent_gain, latent_gain) / gamma**2  # eq. (4.5)
    latent_cov = 0.5 * (latent_cov + latent_cov.T)
    if not exact:
        # Eqs. (4.6), (4.7); `exact` keeps p(w | o) of the joint (h, w, o), i.e.
        # ProMP conditioning (3.2), (3.3) of the marginal prior computed above.
        mean = b + M @ latent_mean
        cov = jnp.eye(num_weights) / alpha + M @ latent_cov @ M.T
        cov = 0.5 * (cov + cov.T)
    return mean, cov, latent_mean, latent_cov, log_marginal


def _lmpromp_sites(params: Mapping[str, ArrayLike], model: str) -> tuple[Array, Array, Array]:
    b = _site(params, "b", model)
    M = _site(params, "M", model)
    alpha = _site(params, "alpha", model)
    lead = b.shape[:-1]
    if b.ndim < 1 or M.shape != b.shape + M.shape[-1:] or alpha.shape != lead:
        raise LmprompError(
            f"{model} needs b {'(K, d)' if lead else '(d,)'}, M {'(K, d, V)' if lead else '(d, V)'} and "
            f"alpha {'(K,)' if lead else '()'}; got b {b.shape}, M {M.shape}, alpha {alpha.shape}"
        )
    return b, M, alpha


@partial(jax.jit, static_argnames=("exact",))
def condition_lmpromp(
    params: Mapping[str, ArrayLike],
    observation: Observation,
    gamma: ArrayLike = 1.0,
    *,
    exact: bool = True,
) -> Conditioned:
    r"""LMProMP conditioning through the control variables, eqs. (4.4)-(4.7).

    With :math:`p(\mathbf{h}) = \mathcal{N}(\mathbf{0}, \gamma^{-1} I)` and
    :math:`A = \Sigma_o + \Psi_o(\alpha^{-1} I + \gamma^{-1} M M^T)\Psi_o^T`,

    .. math::

        \boldsymbol\mu_{h|o} &= \gamma^{-1} M^T \Psi_o^T A^{-1} (\mathbf{o} - \Psi_o \mathbf{b})
        \quad (4.4) \\
        \Sigma_{h|o} &= \gamma^{-1} I - \gamma^{-2} M^T \Psi_o^T A^{-1} \Psi_o M \quad (4.5) \\
        \boldsymbol\mu_{w|o} &= \mathbf{b} + M \boldsymbol\mu_{h|o} \quad (4.6) \\
        \Sigma_{w|o} &= \alpha^{-1} I + M \Sigma_{h|o} M^T \quad (4.7)

    Eqs. (4.6), (4.7) are :math:`\int p(\mathbf{w}|\mathbf{h}) p(\mathbf{h}|\mathbf{o}) d\mathbf{h}`:
    the weights of a *new* execution that shares :math:`\mathbf{h}` with the
    observed one but draws its own :math:`\alpha^{-1} I` deviation.  They are
    not the conditional of the observed movement's own weights, which also
    learns from :math:`\mathbf{o}` about its :math:`\alpha^{-1} I` part:
    ``exact=True`` returns that conditional,

    .. math::

        \boldsymbol\mu_{w|o} = \mathbf{b} + \Sigma_w \Psi_o^T A^{-1}(\mathbf{o} - \Psi_o\mathbf{b})
        = \mathbf{b} + M\boldsymbol\mu_{h|o} + \alpha^{-1}\Psi_o^T A^{-1}(\mathbf{o} - \Psi_o\mathbf{b}),
        \qquad
        \Sigma_{w|o} = \Sigma_w - \Sigma_w \Psi_o^T A^{-1} \Psi_o \Sigma_w,

    with :math:`\Sigma_w = \alpha^{-1} I + \gamma^{-1} M M^T` (eqs. 3.2, 3.3
    applied to the marginal prior).  Only the exact form passes through
    noiseless observations.

    Parameters
    ----------
    params : dict
        ``b`` (d,), ``M`` (d, V), ``alpha`` ().
    observation : Observation
    gamma : float
        Precision of :math:`\mathbf{h}`.
    exact : bool
        Return the exact :math:`p(\mathbf{w}|\mathbf{o})` instead of eqs. (4.6), (4.7).

    Returns
    -------
    Conditioned
        ``log_evidence`` is :math:`\log\mathcal{N}(\mathbf{o} | \Psi_o\mathbf{b}, A)`.
    """
    b, M, alpha = _lmpromp_sites(params, "lmpromp")
    if b.ndim != 1:
        raise LmprompError(f"lmpromp needs b (d,), got {b.shape}; use model 'mixture' for components")
    _check_weight_dim(observation, b.shape[0], "lmpromp")
    gamma = jnp.asarray(gamma, dtype=jnp.float64)
    mean, cov, latent_mean, latent_cov, log_evidence = _lmpromp_core(b, M, alpha, gamma, observation, exact)
    return Conditioned(_single(mean, cov), _single(latent_mean, latent_cov), log_evidence)


@partial(jax.jit, static_argnames=("exact",))
def condition_mixture(
    params: Mapping[str, ArrayLike],
    observation: Observation,
    gamma: ArrayLike = 1.0,
    *,
    exact: bool = True,
) -> Conditioned:
    r"""Mixture-of-LMProMPs prediction (Sec. 4.2.2, with corrected responsibilities).

    Each component k is conditioned with :func:`condition_lmpromp` and
    weighted by its responsibility for the observations,

    .. math::

        z_k = \frac{\pi_k \mathcal{N}(\mathbf{o} | \Psi_o \mathbf{b}_k, A_k)}
                   {\sum_j \pi_j \mathcal{N}(\mathbf{o} | \Psi_o \mathbf{b}_j, A_j)},
        \qquad A_k = \Sigma_o + \Psi_o(\alpha_k^{-1} I + \gamma^{-1} M_k M_k^T)\Psi_o^T,

    the Bayes posterior of the component given :math:`\mathbf{o}`.  Sec. 4.2.2
    writes :math:`\mathcal{N}(\mathbf{o} | \boldsymbol\mu^{[k]}_{w|o}, \Sigma^{[k]}_{w|o})`,
    a density of the observation under weight-space moments that are already
    conditioned on it (erratum).  The mixture's moments
    (:meth:`GaussianMixture.moments`) include the spread between components
    that the thesis's :math:`\sum_k z_k \Sigma^{[k]}_{w|o}` omits.

    Parameters
    ----------
    params : dict
        ``pi`` (K,), ``b`` (K, d), ``M`` (K, d, V), ``alpha`` (K,).  ``pi`` is
        normalised here; components with ``pi = 0`` get responsibility 0.
    observation : Observation
    gamma : float or (K,) array
        Precision of :math:`\mathbf{h}` (per component, or shared).
    exact : bool
        Per-component exact :math:`p(\mathbf{w}|\mathbf{o}, k)` (see :func:`condition_lmpromp`).

    Returns
    -------
    Conditioned
        K components; ``log_evidence`` is :math:`\log \sum_k \pi_k \mathcal{N}(\mathbf{o} | \Psi_o\mathbf{b}_k, A_k)`.
    """
    b, M, alpha = _lmpromp_sites(params, "mixture")
    pi = _site(params, "pi", "mixture")
    if b.ndim != 2 or pi.shape != b.shape[:1]:
        raise LmprompError(f"mixture needs pi (K,) and b (K, d), got pi {pi.shape} and b {b.shape}")
    _check_weight_dim(observation, b.shape[1], "mixture")
    gamma = jnp.broadcast_to(jnp.asarray(gamma, dtype=jnp.float64), pi.shape)
    mean, cov, latent_mean, latent_cov, log_marginal = jax.vmap(
        lambda b_k, M_k, alpha_k, gamma_k: _lmpromp_core(b_k, M_k, alpha_k, gamma_k, observation, exact)
    )(b, M, alpha, gamma)
    log_joint = jnp.log(pi) - jnp.log(jnp.sum(pi)) + log_marginal
    log_evidence = logsumexp(log_joint)
    log_resp = log_joint - log_evidence
    return Conditioned(
        GaussianMixture(log_resp, mean, cov), GaussianMixture(log_resp, latent_mean, latent_cov), log_evidence
    )


def condition_further(conditioned: Conditioned, via: Observation) -> Conditioned:
    r"""Condition a predictive once more, on ``via`` (via-points), component by component.

    Given :math:`p(\mathbf{w} | \mathbf{o}) = \sum_k z_k \mathcal{N}(\boldsymbol\mu_k, \Sigma_k)`,

    .. math::

        p(\mathbf{w} | \mathbf{o}, \mathbf{v}) = \sum_k z'_k\,
        \mathcal{N}(\mathbf{w} | \boldsymbol\mu_{k|v}, \Sigma_{k|v}), \qquad
        z'_k \propto z_k\, \mathcal{N}(\mathbf{v} | \Psi_v \boldsymbol\mu_k, \Sigma_v + \Psi_v\Sigma_k\Psi_v^T),

    which is the chain rule :math:`p(\mathbf{w}|\mathbf{o},\mathbf{v}) \propto p(\mathbf{w}|\mathbf{o})\,
    p(\mathbf{v}|\mathbf{w})`: the same as conditioning on the rows of
    :math:`\mathbf{o}` and :math:`\mathbf{v}` at once (tests/test_timing.py checks it
    against the joint Gaussian), and it lets via-points be noiseless while the
    observation has more rows than weights.  For the LMProMP this is the exact
    conditional through :math:`\mathbf{h}` (``exact=True``); for the mixture each
    component's responsibility also learns from the via-points.  ``latent`` is
    dropped (``None``): prediction needs the weights.
    """
    weights = conditioned.weights
    means, covs, log_marginal = jax.vmap(lambda m, c: condition_gaussian(m, c, via))(weights.means, weights.covs)
    log_joint = weights.log_weights + log_marginal
    log_via = logsumexp(log_joint)
    return Conditioned(GaussianMixture(log_joint - log_via, means, covs), None, conditioned.log_evidence + log_via)


def _check_model(model: str) -> None:
    if model not in MODELS:
        raise LmprompError(f"unknown model {model!r}; choose from {list(MODELS)}")


@partial(jax.jit, static_argnames=("model", "exact"))
def condition(
    model: str,
    params: Mapping[str, ArrayLike],
    observation: Observation,
    gamma: ArrayLike = 1.0,
    *,
    exact: bool = True,
    via: Observation | None = None,
) -> Conditioned:
    """Plug-in predictive of ``model`` (``"promp"``, ``"lmpromp"`` or ``"mixture"``) given ``observation``.

    Dispatches to :func:`condition_promp` (eqs. 3.2, 3.3; ``gamma`` and
    ``exact`` unused), :func:`condition_lmpromp` (eqs. 4.4-4.7) or
    :func:`condition_mixture` (Sec. 4.2.2); then, with ``via`` (via-points),
    :func:`condition_further`.
    """
    _check_model(model)
    if model == "promp":
        out = condition_promp(params, observation)
    elif model == "lmpromp":
        out = condition_lmpromp(params, observation, gamma, exact=exact)
    else:
        out = condition_mixture(params, observation, gamma, exact=exact)
    return out if via is None else condition_further(out, via)


def _num_weights(model: str, params: Mapping[str, ArrayLike]) -> int:
    site = "mu_w" if model == "promp" else "b"
    return _site(params, site, model).shape[-1]


def prior(model: str, params: Mapping[str, ArrayLike], gamma: ArrayLike = 1.0) -> Conditioned:
    r"""The prior predictive of ``model``: conditioning on no observation.

    ProMP :math:`\mathcal{N}(\boldsymbol\mu_w, \Sigma_w)` (eq. 3.1); LMProMP
    :math:`\mathcal{N}(\mathbf{b}, \alpha^{-1}I + \gamma^{-1}MM^T)` with
    :math:`\mathbf{h} \sim \mathcal{N}(\mathbf{0}, \gamma^{-1}I)`; the mixture
    weights its components by ``pi`` (eq. 4.8).
    """
    _check_model(model)
    return condition(model, params, empty_observation(_num_weights(model, params)), gamma)


def num_sample_dims(model: str, draws: Mapping[str, ArrayLike]) -> int:
    """Number of leading sample dims, (draw,) -> 1 or (chain, draw) -> 2, of posterior draws.

    Raises
    ------
    LmprompError
        If the sites disagree or have neither 1 nor 2 sample dims.
    """
    _check_model(model)
    sample_shapes = {}
    for name, event_dims in SITES[model].items():
        if name not in draws:
            raise LmprompError(f"{model} draws lack site {name!r}; got {sorted(draws)}")
        shape = jnp.shape(draws[name])
        sample_shapes[name] = shape[: max(len(shape) - event_dims, 0)]
    if len(set(sample_shapes.values())) != 1:
        raise LmprompError(f"the sites of the draws have different sample shapes: {sample_shapes}")
    num = len(next(iter(sample_shapes.values())))
    if num not in (1, 2):
        raise LmprompError(f"draws need leading sample dims (draw,) or (chain, draw); found {num}")
    return num


def condition_draws(
    model: str,
    draws: Mapping[str, ArrayLike],
    observation: Observation,
    gamma: ArrayLike = 1.0,
    *,
    exact: bool = True,
    reweight: bool = False,
    via: Observation | None = None,
) -> Conditioned:
    r"""Bayesian predictive: condition every posterior draw and average (any engine).

    With S draws :math:`\theta_s` (arrays with leading dims (draw,) or
    (chain, draw)), each draw is conditioned (:func:`condition`, vectorised
    with :func:`jax.vmap`) and the results are combined into one
    :class:`GaussianMixture` of S x K components,

    .. math::

        p(\mathbf{w} | \mathbf{o}) \approx \sum_s \omega_s \sum_k z_{sk}
        \mathcal{N}(\mathbf{w} | \boldsymbol\mu_{sk}, \Sigma_{sk}),

    so the moments are mean = average of means and variance = average of
    (variance + mean^2) - mean^2.  By default :math:`\omega_s = 1/S` (the
    posterior given the training data).  ``reweight=True`` uses
    :math:`\omega_s \propto p(\mathbf{o} | \theta_s)`, the posterior that also
    conditions the parameters on the new observations.  ``via`` (via-points)
    conditions each draw further (:func:`condition_further`); they do not
    reweight the draws.

    Returns
    -------
    Conditioned
        ``log_evidence`` is :math:`\log \frac1S \sum_s p(\mathbf{o} | \theta_s)`.
    """
    sample_dims = num_sample_dims(model, draws)
    # Only the sites the model reads enter the compiled function (draws of h or
    # w can be large and are not needed).
    flat = {
        name: jnp.reshape(
            jnp.asarray(draws[name], dtype=jnp.float64),
            (-1,) + jnp.shape(draws[name])[sample_dims:],
        )
        for name in SITES[model]
    }
    return _condition_flat_draws(model, flat, observation, gamma, exact, reweight, via)


def _merge_draws(mixture: GaussianMixture | None, log_draw_weights: Array) -> GaussianMixture | None:
    if mixture is None:
        return None
    log_weights = (log_draw_weights[:, None] + mixture.log_weights).reshape(-1)
    size = mixture.means.shape[-1]
    return GaussianMixture(log_weights, mixture.means.reshape(-1, size), mixture.covs.reshape(-1, size, size))


@partial(jax.jit, static_argnames=("model", "exact", "reweight"))
def _condition_flat_draws(
    model: str,
    flat: dict[str, Array],
    observation: Observation,
    gamma: ArrayLike,
    exact: bool,
    reweight: bool,
    via: Observation | None = None,
) -> Conditioned:
    per_draw = jax.vmap(lambda p: condition(model, p, observation, gamma, exact=exact))(flat)
    if via is not None:
        evidence = per_draw.log_evidence
        per_draw = jax.vmap(lambda c: condition_further(c, via))(per_draw)._replace(log_evidence=evidence)
    num_draws = per_draw.log_evidence.shape[0]
    log_mean_evidence = logsumexp(per_draw.log_evidence) - math.log(num_draws)
    if reweight:
        log_draw_weights = per_draw.log_evidence - logsumexp(per_draw.log_evidence)
    else:
        log_draw_weights = jnp.full((num_draws,), -math.log(num_draws))
    return Conditioned(
        _merge_draws(per_draw.weights, log_draw_weights),
        _merge_draws(per_draw.latent, log_draw_weights),
        log_mean_evidence,
    )

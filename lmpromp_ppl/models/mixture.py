r"""The LMProMP mixture for several movement types (thesis Sec. 4.2, eq. 4.8).

Each of the :math:`K` components has the priors of Sec. 4.1; the mixture
weights get a symmetric Dirichlet prior:

.. math::

    \boldsymbol\pi &\sim \mathrm{Dir}(\kappa_0 \mathbf 1_K), \qquad
    \mathbf b_k \sim \mathcal N(\mathbf 0, \lambda_0^{-1} \mathbf I_d), \qquad
    \lambda_{kv} \sim \Gamma(c_0, d_0), \qquad
    \mathbf m_{kv} \sim \mathcal N(\mathbf 0, \lambda_{kv}^{-1} \mathbf I_d), \qquad
    \alpha_k \sim \Gamma(a_0, b_0), \\
    \mathbf h_{ik} &\sim \mathcal N(\mathbf 0, \gamma^{-1} \mathbf I_V), \qquad
    p(\mathbf w_i) = \sum_{k=1}^K \pi_k\,
    \mathcal N(\mathbf w_i | \mathbf b_k + \mathbf M_k \mathbf h_{ik}, \alpha_k^{-1} \mathbf I_d)
    \quad \text{(eq. 4.8)}, \qquad
    \mathbf y_i \sim \mathcal N(\Psi_i \mathbf w_i, \beta^{-1} \mathbf I_S).

Every demonstration has a control variable for every component (the thesis's
:math:`\mathbf h_k^{[i]}`); those of the components a demonstration does not
belong to are drawn from their prior.

Sites and shapes: ``pi`` (K,), ``b`` (K, d), ``lam`` (K, V), ``M`` (K, d, V),
``alpha`` (K,), ``beta`` () when learned, ``h`` (L, K, V), ``w`` (L, d),
``z`` (L,) only when ``marginalize=False``, ``y`` (L, S).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpyro
import numpyro.distributions as dist
from jax import Array

from lmpromp_ppl.data.core import ModelData
from lmpromp_ppl.models.hyper import Hyperparameters
from lmpromp_ppl.models.lmpromp import observation_precision, observe_y, masked_observations

__all__ = ["mixture_model", "component_priors"]


def component_priors(hyper: Hyperparameters, num_weights: int) -> tuple[Array, Array, Array, Array, Array]:
    r"""Sample ``pi`` and the per-component ``b``, ``lam``, ``M``, ``alpha`` (Sec. 4.2).

    Returns
    -------
    pi : (K,), b : (K, d), lam : (K, V), M : (K, d, V), alpha : (K,)
    """
    num_components, num_latent = hyper.num_components, hyper.latent_dim
    pi = numpyro.sample("pi", dist.Dirichlet(jnp.full(num_components, hyper.kappa0)))
    with numpyro.plate("component", num_components):
        b = numpyro.sample(
            "b", dist.Normal(0.0, hyper.lambda0**-0.5).expand([num_weights]).to_event(1)
        )
        lam = numpyro.sample(
            "lam", dist.Gamma(hyper.c0, hyper.d0).expand([num_latent]).to_event(1)
        )
        # column v of M_k has precision lam[k, v]
        scale = jnp.broadcast_to(
            (lam**-0.5)[..., None, :], lam.shape[:-1] + (num_weights, num_latent)
        )
        M = numpyro.sample("M", dist.Normal(0.0, scale).to_event(2))
        alpha = numpyro.sample("alpha", dist.Gamma(hyper.a0, hyper.b0))
    return pi, b, lam, M, alpha


def mixture_model(
    data: ModelData, hyper: Hyperparameters, marginalize: bool = True, observed: bool = True
) -> None:
    r"""NumPyro model of the LMProMP mixture, eq. 4.8 with ``pi ~ Dirichlet(kappa0)``.

    Parameters
    ----------
    data : padded model inputs ``(psi (L, S, d), y (L, S), mask (L, S))``
    hyper : hyperparameters; ``hyper.num_components`` is K
    marginalize : sum the assignments out of ``p(w_i)`` (eq. 4.8, for NUTS); when
        False, an explicit site ``z`` (L,) ``~ Categorical(pi)`` selects the
        component of each ``w_i`` (for checking a bound that has ``q(z)``)
    observed : condition on ``data.y`` (True) or sample ``y`` (prior predictive)
    """
    prepared = masked_observations(data)
    num_demos, _, num_weights = prepared.psi.shape
    hyper.validate_for(num_weights)
    num_components, num_latent = hyper.num_components, hyper.latent_dim

    pi, b, _, M, alpha = component_priors(hyper, num_weights)
    beta = observation_precision(hyper)

    with numpyro.plate("demo", num_demos):
        h = numpyro.sample(
            "h",
            dist.Normal(0.0, hyper.gamma**-0.5).expand([num_components, num_latent]).to_event(2),
        )
        # (L, K, d): the mean of w_i under component k
        loc = b + jnp.einsum("kdv,lkv->lkd", M, h)
        scale = jnp.sqrt(1.0 / alpha)
        if marginalize:
            components = dist.Normal(loc, scale[..., None]).to_event(1)
            w = numpyro.sample(
                "w",
                dist.MixtureSameFamily(
                    dist.Categorical(probs=jnp.broadcast_to(pi, (num_demos, num_components))),
                    components,
                ),
            )
        else:
            z = numpyro.sample("z", dist.Categorical(probs=pi))
            # one-hot selection keeps the model valid under vectorised z
            onehot = jax.nn.one_hot(z, num_components, dtype=loc.dtype)
            loc_z = jnp.sum(onehot[..., None] * loc, axis=-2)
            scale_z = jnp.sum(onehot * scale, axis=-1)
            w = numpyro.sample("w", dist.Normal(loc_z, scale_z[..., None]).to_event(1))
        observe_y(prepared, w, beta, observed)

r"""NUTS on the NumPyro declarations of :mod:`lmpromp_ppl.models` (the reference engine).

:func:`fit_nuts` runs the No-U-Turn sampler (numpyro's functional
``hmc(algo="NUTS")`` kernel: multinomial NUTS with dual-averaging step size
and diagonal or dense mass-matrix adaptation) on the ProMP baseline, the
LMProMP (thesis Sec. 4.1, eq. 4.1) or the LMProMP mixture with the
assignments summed out (Sec. 4.2, eq. 4.8).

Parametrisation
---------------
NUTS is the reference the VI engines are judged against, so it has to be
reliable itself.  The full model is not: with :math:`\mathbf w_i` sampled,
the posterior couples ``L * d`` weights to :math:`\alpha` through the funnel
:math:`\mathbf w_i \sim \mathcal N(\mathbf b + \mathbf M \mathbf h_i, \alpha^{-1} I)`
(orientation figures from the issue: ``L = 20, D = 2, J = 10, V = 3``,
2 chains x (500 + 500): R-hat 1.08, bulk ESS 22 in 70 s).  The default
parametrisation (``collapsed="auto"``, ``noncentered=True``) is

* **collapsed over w and h** (``"wh"``): :math:`\mathbf w_i` and
  :math:`\mathbf h_i` are integrated out analytically,
  :math:`\mathbf y_i \sim \mathcal N(\Psi_i \mathbf b, \beta^{-1} I +
  \Psi_i(\alpha^{-1} I + \gamma^{-1} \mathbf M \mathbf M^T)\Psi_i^T)`
  (:mod:`lmpromp_ppl.models.collapsed`), leaving only ``b``, ``M``, ``alpha``,
  ``lam`` (and ``pi``) to sample; afterwards ``w`` is drawn from the exact
  conditional :math:`p(\mathbf w_i | \theta, \mathbf y_i)` and ``h`` from
  :math:`p(\mathbf h_i | \mathbf w_i, \theta)` once per posterior draw, so
  every result still has the sites ``w`` and ``h``.  ``collapsed="w"``
  integrates out ``w`` only (``h`` sampled), ``collapsed="none"`` samples the
  full model; the ProMP has no ``h`` and uses ``"w"``;
* **non-centred projection**: the columns
  :math:`\mathbf m_v \sim \mathcal N(\mathbf 0, \lambda_v^{-1} I)` are sampled
  as :math:`\mathbf m_v = \lambda_v^{-1/2} \tilde{\mathbf m}_v`,
  :math:`\tilde{\mathbf m}_v \sim \mathcal N(\mathbf 0, I)`
  (``numpyro.infer.reparam.LocScaleReparam(centered=0)`` on site ``M``),
  which removes the funnel between a switched-off column and its precision;
  in the full LMProMP ``w`` is non-centred the same way;
* the ``proper`` hyperparameter preset (Gamma(1e-5, 1e-5) is nearly improper
  and NUTS cannot explore it), and V (and K) restricted to what CAVI kept
  active: a switched-off column has no likelihood information, its
  :math:`\lambda_v` then wanders over its prior, which is harmless for the
  identifiable quantities but costs tree depth.

Measured on ``synthetic:latent?L=20&D=2&J=10&V=3&seed=0`` (standardised,
J = 10, ``preset("proper", latent_dim=3)``), 2 chains x (500 + 500), target
acceptance 0.8, key 0; worst R-hat and smallest bulk / tail ESS over the
elements of ``b``, ``alpha``, sorted ``lam`` and the eigenvalues of
:math:`\mathbf M \mathbf M^T`; no divergences in any run; times on a shared,
heavily loaded 2-core machine (compare them with each other only):

=====================  ===========  ===============  ===============  ==========  =========
collapsed, M           R-hat max    bulk ESS min     tail ESS min     tree depth  seconds
=====================  ===========  ===============  ===============  ==========  =========
``"w"``, centred       1.004        348 (gram_eig)   453 (b)          7-9         340
``"w"``, non-centred   1.005        560 (alpha)      497 (b)          8-9         450
``"wh"``, non-centred  1.008        696 (lam)        433 (b)          7-8         351
=====================  ===========  ===============  ===============  ==========  =========

so ``"wh"`` with a non-centred ``M`` is the default; ``tests/test_nuts_reliability.py``
(marked ``slow``) asserts R-hat <= 1.01 and bulk ESS >= 400 for it.
Identifiable quantities: ``b``, ``alpha``, ``lam`` sorted, and the
eigenvalues of :math:`\mathbf M \mathbf M^T` (:func:`lmpromp_ppl.quantities.invariant_quantities`);
``M`` and ``h`` are identified only up to a rotation and sign of the latent
space, so their R-hat means nothing.

Chains and timing
-----------------
The whole run (initialisation, warm-up, sampling and the draws of ``w``) is
one XLA program, compiled ahead of time (``jax.jit(...).lower(...).compile()``)
and cached per static configuration (model, hyperparameters, options and the
shapes of the data), so ``compile_seconds`` is the tracing and compilation time
(close to 0 when a cached program is reused) and ``seconds`` is the execution
time only.  Chains run in the same program, either one after the other
(``chain_method="sequential"``, ``lax.map``: each chain stops its trees at its
own U-turns) or in lock-step (``"vectorized"``, ``vmap``: every step costs the
longest tree among the chains, but the linear algebra is batched).  On the
2-core CPU machines of this project ``"sequential"`` is the default; XLA uses
both cores inside each chain's linear algebra.
"""

from __future__ import annotations

import time
from typing import Any, Callable, Mapping, NamedTuple

import numpy as np
import jax
import jax.numpy as jnp
from jax import lax
from numpyro import handlers
from numpyro.infer.hmc import hmc
from numpyro.infer.initialization import init_to_uniform, init_to_value
from numpyro.infer.reparam import LocScaleReparam
from numpyro.infer.util import ParamInfo, initialize_model

from lmpromp_ppl._keys import raw_key
from lmpromp_ppl.data.core import ModelData
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference.compiled import lookup, remember
from lmpromp_ppl.models.conditionals import draw_integrated_sites
from lmpromp_ppl.models.hyper import Hyperparameters
from lmpromp_ppl.models.registry import model_function, resolve_collapse

__all__ = [
    "NutsResult",
    "fit_nuts",
]

_STAT_NAMES = ("diverging", "tree_depth", "step_size", "accept_prob", "energy", "num_steps")


class NutsResult(NamedTuple):
    """What :func:`fit_nuts` returns.

    Attributes
    ----------
    samples : site name -> (chain, draw, ...) numpy array, constrained values of
        every latent and deterministic site, plus ``w`` (and ``h``) drawn from
        their exact conditionals when collapsed; sites fixed through ``fixed``
        are not included
    sample_stats : ``diverging``, ``tree_depth``, ``step_size``,
        ``accept_prob``, ``energy``, ``num_steps``, each (chain, draw)
    seconds : execution time of warm-up, sampling and conditional draws,
        excluding compilation
    compile_seconds : tracing and XLA compilation time (about 0 when the
        compiled program was cached from an earlier call)
    options : the engine options, for the result's attributes
    """

    samples: dict[str, np.ndarray]
    sample_stats: dict[str, np.ndarray]
    seconds: float
    compile_seconds: float
    options: dict[str, Any]


def _noncentered_sites(model_name: str, collapse: str, fixed_names: tuple[str, ...]) -> tuple[str, ...]:
    """Sites sampled non-centred: ``M`` (given ``lam``), and ``w`` in the full LMProMP.

    The ProMP's ``w`` is multivariate normal and the mixture's ``w`` a mixture,
    neither a location-scale family, so they stay centred.
    """
    if model_name == "promp":
        return ()
    sites = ("M", "w") if (collapse == "none" and model_name == "lmpromp") else ("M",)
    return tuple(s for s in sites if s not in fixed_names)


def _wrapped_model(model_name: str, collapse: str, hyper: Hyperparameters,
                   noncentered: tuple[str, ...]) -> Callable[[ModelData, dict], None]:
    """``model(data, fixed)``: the declared model, non-centred and conditioned on ``fixed``."""
    base = model_function(model_name, collapse)
    config = {name: LocScaleReparam(centered=0) for name in noncentered}

    def model(data: ModelData, fixed: dict) -> None:
        with handlers.condition(data=fixed), handlers.reparam(config=config):
            base(data, hyper)

    return model


class _Config(NamedTuple):
    """Static configuration of one compiled NUTS program (a cache key)."""

    model_name: str
    collapse: str
    hyper: Hyperparameters
    noncentered: tuple[str, ...]
    num_chains: int
    num_warmup: int
    num_samples: int
    target_accept: float
    max_tree_depth: int
    dense_mass: bool
    chain_method: str


def _build_program(config: _Config) -> Callable:
    """The pure function ``(key, data, fixed, init_values) -> (samples, stats)``."""
    model = _wrapped_model(config.model_name, config.collapse, config.hyper, config.noncentered)

    def program(key, data, fixed, init_values):
        key_init, key_chains, key_cond = jax.random.split(key, 3)
        strategy = init_to_value(values=init_values) if init_values else init_to_uniform
        info = initialize_model(
            jax.random.split(key_init, config.num_chains), model, init_strategy=strategy,
            dynamic_args=True, model_args=(data, fixed),
        )
        init_kernel, sample_kernel = hmc(potential_fn_gen=info.potential_fn, algo="NUTS")
        postprocess = info.postprocess_fn(data, fixed)

        def one_chain(args):
            chain_key, z, pe, z_grad = args
            state = init_kernel(
                ParamInfo(z, pe, z_grad), config.num_warmup,
                target_accept_prob=config.target_accept, max_tree_depth=config.max_tree_depth,
                dense_mass=config.dense_mass, model_args=(data, fixed), rng_key=chain_key,
            )
            # one scan over warm-up and sampling: a single copy of the NUTS
            # kernel in the program (adaptation stops by itself after warm-up)
            def step(s, _):
                s = sample_kernel(s, model_args=(data, fixed))
                stats = {
                    "diverging": s.diverging,
                    # a tree of depth k holds 2^(k-1) to 2^k - 1 leapfrog steps
                    "tree_depth": jnp.floor(jnp.log2(jnp.maximum(s.num_steps, 1))).astype(jnp.int32) + 1,
                    "step_size": s.adapt_state.step_size,
                    "accept_prob": s.accept_prob,
                    "energy": s.energy,
                    "num_steps": s.num_steps.astype(jnp.int32),
                }
                return s, (s.z, stats)

            _, (zs, stats) = lax.scan(step, state, None, length=config.num_warmup + config.num_samples)
            zs, stats = jax.tree_util.tree_map(lambda x: x[config.num_warmup:], (zs, stats))
            return jax.vmap(postprocess)(zs), stats

        chain_keys = jax.random.split(key_chains, config.num_chains)
        args = (chain_keys, *info.param_info)
        if config.chain_method == "vectorized":
            samples, stats = jax.vmap(one_chain)(args)
        else:
            samples, stats = lax.map(one_chain, args)
        samples = {k: v for k, v in samples.items() if not k.endswith("_decentered")}
        if config.collapse != "none":
            flat = {k: v.reshape((-1,) + v.shape[2:]) for k, v in samples.items()}
            num_flat = config.num_chains * config.num_samples
            flat.update({k: jnp.broadcast_to(v, (num_flat,) + jnp.shape(v)) for k, v in fixed.items()})
            extra = draw_integrated_sites(
                config.model_name, config.collapse, key_cond, data, config.hyper, flat
            )
            samples.update({k: v.reshape((config.num_chains, config.num_samples) + v.shape[1:])
                            for k, v in extra.items()})
        return samples, stats

    return program


def _check_positive_int(name: str, value, minimum: int = 1) -> int:
    if isinstance(value, bool) or int(value) != value or value < minimum:
        raise LmprompError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def fit_nuts(
    model_name: str,
    data: ModelData,
    hyper: Hyperparameters,
    key: jax.Array,
    *,
    collapsed: str = "auto",
    noncentered: bool = True,
    num_chains: int = 2,
    num_warmup: int = 500,
    num_samples: int = 500,
    target_accept: float = 0.8,
    max_tree_depth: int = 10,
    dense_mass: bool = False,
    chain_method: str = "sequential",
    progress: bool = False,
    init_values: Mapping[str, Any] | None = None,
    fixed: Mapping[str, Any] | None = None,
) -> NutsResult:
    r"""Sample the posterior of a declared model with NUTS.

    Parameters
    ----------
    model_name : ``"promp"``, ``"lmpromp"`` or ``"mixture"`` (assignments summed out, eq. 4.8)
    data : padded model inputs ``(psi (L, S, d), y (L, S), mask (L, S))``
    hyper : hyperparameters; use ``preset("proper")`` (see the module docstring)
    key : PRNG key (typed or raw)
    collapsed : ``"auto"`` (default: ``"wh"``, or ``"w"`` for the ProMP),
        ``"w"`` (w integrated out, then drawn from :math:`p(\mathbf w | \theta,
        \mathbf y)`), ``"wh"`` (w and h integrated out, then drawn from
        :math:`p(\mathbf w, \mathbf h | \theta, \mathbf y)`), or ``"none"``
        (the full model); see :data:`lmpromp_ppl.models.registry.COLLAPSE_CHOICES`
    noncentered : sample ``M`` (and ``w`` in the full model) non-centred
    num_chains, num_warmup, num_samples : chains, warm-up and kept draws per chain
    target_accept : target acceptance probability of the step-size adaptation
    max_tree_depth : maximum NUTS tree depth (at most ``2**max_tree_depth - 1``
        leapfrog steps per draw)
    dense_mass : adapt a dense rather than a diagonal mass matrix
    chain_method : ``"sequential"`` or ``"vectorized"`` (see the module docstring)
    progress : accepted for interface symmetry; the run is one compiled program
        without a progress bar
    init_values : initial values (constrained) for some sampled sites, the same
        for every chain; the other sites start uniformly in (-2, 2) on the
        unconstrained scale
    fixed : values at which some latent sites are held (the model is
        conditioned on them); they are left out of ``samples``

    Returns
    -------
    NutsResult
    """
    del progress  # one compiled program: nothing to report while it runs
    collapse = resolve_collapse(model_name, collapsed)
    num_chains = _check_positive_int("num_chains", num_chains)
    num_warmup = _check_positive_int("num_warmup", num_warmup, 0)
    num_samples = _check_positive_int("num_samples", num_samples)
    max_tree_depth = _check_positive_int("max_tree_depth", max_tree_depth)
    if not 0.0 < float(target_accept) < 1.0:
        raise LmprompError(f"target_accept must lie in (0, 1), got {target_accept!r}")
    if chain_method not in ("sequential", "vectorized"):
        raise LmprompError(f"chain_method must be 'sequential' or 'vectorized', got {chain_method!r}")
    if not isinstance(hyper, Hyperparameters):
        raise LmprompError("hyper must be a Hyperparameters instance")
    data = ModelData(*(jnp.asarray(a, dtype=jnp.float64) for a in data))
    fixed = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in (fixed or {}).items()}
    init_values = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in (init_values or {}).items()}
    # run the model once on the concrete data: shape and value errors surface
    # here with their own message, not inside tracing
    trace = handlers.trace(handlers.seed(model_function(model_name, collapse), 0)).get_trace(data, hyper)
    latent = {n for n, s in trace.items() if s["type"] == "sample" and not s["is_observed"]}
    for what, values in (("fixed", fixed), ("init_values", init_values)):
        unknown = set(values) - latent
        if unknown:
            raise LmprompError(f"{what} names unknown sites {sorted(unknown)}; latent sites: {sorted(latent)}")
        for name, value in values.items():
            if value.shape != trace[name]["value"].shape:
                raise LmprompError(
                    f"{what}[{name!r}] has shape {value.shape}, expected {trace[name]['value'].shape}"
                )
    config = _Config(
        model_name, collapse, hyper,
        _noncentered_sites(model_name, collapse, tuple(sorted(fixed))) if noncentered else (),
        num_chains, num_warmup, num_samples, float(target_accept), max_tree_depth,
        bool(dense_mass), chain_method,
    )
    args = (raw_key(key), data, fixed, init_values)
    cache_key = (config, jax.tree_util.tree_structure(args),
                 tuple((a.shape, a.dtype) for a in jax.tree_util.tree_leaves(args)))
    start = time.perf_counter()
    compiled = lookup(cache_key)
    if compiled is None:
        compiled = jax.jit(_build_program(config)).lower(*args).compile()
        remember(cache_key, compiled)
    compile_seconds = time.perf_counter() - start
    start = time.perf_counter()
    samples, stats = jax.block_until_ready(compiled(*args))
    seconds = time.perf_counter() - start
    options = {
        "collapsed": collapse, "noncentered": list(config.noncentered),
        "num_chains": num_chains, "num_warmup": num_warmup, "num_samples": num_samples,
        "target_accept": float(target_accept), "max_tree_depth": max_tree_depth,
        "dense_mass": bool(dense_mass), "chain_method": chain_method,
        "fixed": sorted(fixed),
    }
    return NutsResult(
        samples={k: np.asarray(v) for k, v in samples.items()},
        sample_stats={k: np.asarray(stats[k]) for k in _STAT_NAMES},
        seconds=seconds,
        compile_seconds=compile_seconds,
        options=options,
    )

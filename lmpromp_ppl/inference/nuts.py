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
parametrisation (``collapsed="auto"``, ``noncentered=True``, ``init="uniform"``) is

* **collapsed over w and h** (``"wh"``): :math:`\mathbf w_i` and
  :math:`\mathbf h_i` are integrated out analytically,
  :math:`\mathbf y_i \sim \mathcal N(\Psi_i \mathbf b, \beta^{-1} I +
  \Psi_i(\alpha^{-1} I + \gamma^{-1} \mathbf M \mathbf M^T)\Psi_i^T)`
  (:mod:`lmpromp_ppl.models.collapsed`), leaving only ``b``, ``M``, ``alpha``,
  ``lam`` (and ``pi``) to sample; afterwards ``w`` is drawn from the exact
  conditional :math:`p(\mathbf w_i | \theta, \mathbf y_i)` and ``h`` from
  :math:`p(\mathbf h_i | \mathbf w_i, \theta)` once per posterior draw, so
  every result still has the sites ``w`` and ``h``.  ``collapsed="whb"``
  integrates the LMProMP's offset ``b`` out as well
  (:func:`lmpromp_ppl.models.conditionals.offset_marginal`) and draws it
  afterwards from :math:`p(\mathbf b | \theta, \mathbf y)`; ``collapsed="w"``
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
  and NUTS cannot explore it).

``init="cavi"`` starts each chain at its own draw from the CAVI posterior of
the same model (:func:`lmpromp_ppl.inference.warm_start.cavi_start`).

Defaults: shared-design statistics, 4 chains x (500 + 2000), CAVI start, target 0.9
------------------------------------------------------------------------------------
Where every demonstration has the same fully observed design (LASA, GunPoint and
the synthetic sets all do), the potential evaluates the collapsed density from
sufficient statistics in the eigenbasis of :math:`\Psi^T\Psi`
(:func:`lmpromp_ppl.models.registry.model_inputs`,
:func:`lmpromp_ppl.models.collapsed.shared_log_evidence`): on GShape one gradient
takes 0.14 ms instead of 1.05 ms (``"wh"``; 0.07 against 1.21 ms for ``"w"``, 0.15
against 4.0 ms for the mixture), and 2 chains x (500 + 500) take 1.7 s instead of
62.8 s.  With draws that cheap the defaults are ``num_chains=4``, ``num_warmup=500``,
``num_samples=2000``, ``init="auto"`` (the CAVI start for the single-type
LMProMP) and ``target_accept=0.9``.  Measured on the three committed example reports (2 cores, keys 0 and 1;
worst over ``b``, ``alpha``, ``lam``, ``gram_eig``, ``w``, the predictive mean and
s.d., as the compare report checks them; seconds of warm-up and sampling):

=========  =========================================  ===  ======  ========  ========  ===========  =====
data       settings                                    key  R-hat   bulk ESS  tail ESS  divergences  s
=========  =========================================  ===  ======  ========  ========  ===========  =====
GShape     4 x (500 + 1000), uniform start              0   1.008   379       518       0            4.5
GShape     4 x (500 + 1000), uniform start              1   1.009   455       512       0            4.7
GShape     4 x (500 + 2000), uniform start              0   1.003   881       1116      0            7.3
GShape     4 x (500 + 2000), CAVI start (default)       0   1.005   970       842       0            6.9
GShape     4 x (500 + 2000), CAVI start (default)       1   1.005   958       1152      0            6.1
synthetic  4 x (500 + 2000), uniform start              0   1.002   2822      1868      18           22.7
synthetic  4 x (500 + 2000), uniform start              1   1.054   51        19        153          25.2
synthetic  4 x (1000 + 2000), uniform, target 0.9       0   1.002   2508      3615      0            26.3
synthetic  4 x (500 + 2000), CAVI start (default)       0   1.003   3107      4016      0            18.4
synthetic  4 x (500 + 2000), CAVI start (default)       1   1.002   3536      4062      0            15.7
GunPoint   4 x (500 + 2000), CAVI start (default)       0   1.001   3067      4000      0            14.8
GunPoint   4 x (500 + 2000), CAVI start (default)       1   1.002   2800      3883      0            14.1
GShape     the same, target 0.9 (default)               0   1.006   789       775       0            5.9
GShape     the same, target 0.9 (default)               1   1.006   1007      700       0            5.9
synthetic  the same, target 0.9 (default)               0   1.001   3869      3934      0            15.7
synthetic  the same, target 0.9 (default)               1   1.002   3223      4069      0            18.8
=========  =========================================  ===  ======  ========  ========  ===========  =====

(rows above "target 0.9" with the target acceptance 0.8.)  The ``lmpromp compare``
run of ``reports/compare/synthetic-latent`` at target 0.8 had one divergent
transition (R-hat 1.002, bulk ESS 3071); at 0.9 the step size is smaller at no
measurable cost in time.

With four chains a uniform start lets one chain of the synthetic set stall in a
region it leaves only by divergent transitions (key 1); started from CAVI's
posterior every chain begins in the typical set.  GShape's bulk ESS per second
went from 1.6 (the former default below, 71 s) to 134-171.  ``"whb"`` (``b``
integrated out, dense path, 4 x (1000 + 1000)) gives GShape a bulk ESS of 835-844
but takes 192-221 s, since the offset marginal has no shared-design form yet.

The measurements below predate the shared-design statistics (dense path). Measured with 2 chains x 500 draws, worst R-hat and smallest bulk / tail ESS
over the identifiable quantities below (the quantity in brackets), no
divergences; seconds of warm-up plus sampling on the 2-core machine (compare
them with each other only).  GShape is the demo's data
(``lasa:GShape?every=20``, J = 20, d = 40, L = 7, V = 2); *synthetic* is
``synthetic:latent?L=20&D=2&J=10&V=3&seed=0`` (J = 10, d = 20, V = 3);
GunPoint is ``gunpoint:train`` (L = 50, J = 10, d = 10, V = 2), the ``lmpromp
compare`` runs of ``reports/compare/gunpoint`` (the worst quantity there also
covers the predictive mean and s.d.; the ``"whb"`` run shared the machine with
another job part of the time):

=========  ===============================  ===  ======  ================  =============  ==========  ===  ============
data       collapsed, start, warm-up        key  R-hat   bulk ESS          tail ESS       tree depth  s    bulk ESS / s
=========  ===============================  ===  ======  ================  =============  ==========  ===  ============
GShape     ``"wh"``, uniform, 500 (default)  0   1.013   111 (b)           158            4-5         71   1.6
GShape     ``"wh"``, uniform, 500 (default)  1   1.050   63 (b)            73             4-5         75   0.8
GShape     ``"wh"``, CAVI, 500               0   1.017   96 (b)            86             4-5         77   1.3
GShape     ``"wh"``, b held fixed, 200       0   1.008   362               281            4           37   9.8
GShape     ``"whb"``, uniform, 500           0   1.013   246 (alpha)       283            4           69   3.6
GShape     ``"whb"``, CAVI, 500              0   1.014   122 (alpha)       121            4           60   2.0
GShape     ``"whb"``, CAVI, 500              1   1.018   157 (alpha)       70             4           67   2.3
GShape     ``"whb"``, CAVI, 200              0   1.007   234 (alpha)       124            4           46   5.1
synthetic  ``"wh"``, CAVI, 500               0   1.008   539 (b)           353 (b)        6-8         213  2.5
synthetic  ``"whb"``, uniform, 500           0   1.010   217 (alpha)       479            5-7         119  1.8
synthetic  ``"whb"``, CAVI, 500              0   1.012   309 (lam)         157 (lam)      --          --   --
GunPoint   ``"wh"``, uniform, 500 (default)  0   1.011   306 (b)           443            --          524  0.6
GunPoint   ``"whb"``, CAVI, 500              0   1.013   347 (pred. sd)    340 (lam)      --          123  2.8
=========  ===============================  ===  ======  ================  =============  ==========  ===  ============

(b held fixed is not an option: it shows what sampling the offset costs.)
Integrating ``b`` out makes the offset mix best (bulk ESS 640-810 on GShape,
from 63-111), raises GShape's bulk ESS per second 1.3-2.8 times and
GunPoint's about 4.8 times (its likelihood is then evaluated in the
10-dimensional weight space instead of on 150 samples per demonstration), but on
the synthetic set, where ``b`` is not what limits the default, it shortens the
trees and ``alpha`` and ``lam`` mix worse (bulk ESS 217-309 against 539-916),
and the ``slow`` reliability test below fails with it; the CAVI start makes no
consistent difference.  Neither is therefore the default.  The ESS of a single
run varies by a factor of about two between keys.  What limits ``alpha`` and
``lam`` is the trade-off between :math:`\alpha^{-1}` and the column scales of M
(both explain the demonstrations' spread) through ``lam``: on GShape, with
``lam`` held at the CAVI posterior mean (``"whb"``, centred M, key 0), R-hat is
1.002-1.005, bulk ESS 473-782 and tail ESS 499-737 on every quantity.
Integrating the ARD precisions out as well (``"whb"`` with a multivariate
Student-t prior on each column of M, sampled centred; an experiment, not an
option) is worse: R-hat 1.03-1.04 and bulk ESS 54-74 on the eigenvalues of
:math:`\mathbf M\mathbf M^T` (keys 0 and 1), since the switched-off column then
sits in the t's spike at 0, the funnel the non-centred M avoids.  A
parametrisation of the (alpha, lam) trade-off itself is still open.  A dense mass matrix
(``dense_mass=True``) did not finish within 200 s on GShape (warm-up at the
maximum tree depth), and chains in lock-step (``chain_method="vectorized"``)
took 140-240 s against 60-67 s, so the mass matrix stays diagonal and the
chains sequential.  ``tests/test_nuts_reliability.py`` (marked ``slow``)
asserts R-hat <= 1.01 and bulk ESS >= 400 for the default on the synthetic
set.  It passed when first measured, with the ``proper`` preset of that time
(R-hat 1.008, bulk ESS 696, tail ESS 433); with today's preset
(``lambda0 = 0.01``, Gamma(1, 1e-3)) it fails with the default
(R-hat 1.009, bulk ESS 286 on ``b``, tail ESS 434; key 0) and with ``"whb"``
(``alpha``, above).

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
time only; the CAVI fit of the start is timed apart (``options["init_seconds"]``).
Chains run in the same program, either one after the other
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
from lmpromp_ppl.data.core import DemoStatistics, ModelData, as_float64, demo_statistics
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference.compiled import lookup, remember
from lmpromp_ppl.inference.warm_start import START_SITES, WARM_START_MODELS, cavi_start
from lmpromp_ppl.models.conditionals import draw_integrated_sites
from lmpromp_ppl.models.hyper import Hyperparameters
from lmpromp_ppl.models.registry import model_function, model_inputs, resolve_collapse, site_shapes

__all__ = [
    "INIT_CHOICES",
    "NutsResult",
    "fit_nuts",
]

#: Values of ``init``: ``"auto"`` (the default: ``"cavi"`` for the models of
#: :data:`~lmpromp_ppl.inference.warm_start.WARM_START_MODELS`, ``"uniform"`` for
#: the others), ``"uniform"`` (numpyro's ``init_to_uniform`` for every site not in
#: ``init_values``) and ``"cavi"`` (one start per chain drawn from the CAVI posterior).
INIT_CHOICES = ("auto", "uniform", "cavi")

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
    per_chain_init: bool


def _build_program(config: _Config) -> Callable:
    """The pure function ``(key, inputs, data, fixed, init_values) -> (samples, stats)``: the potential
    evaluates ``inputs`` (:func:`~lmpromp_ppl.models.registry.model_inputs`), the conditional draws ``data``."""
    model = _wrapped_model(config.model_name, config.collapse, config.hyper, config.noncentered)

    def program(key, inputs, data, fixed, init_values):
        key_init, key_chains, key_cond = jax.random.split(key, 3)
        init_keys = jax.random.split(key_init, config.num_chains)
        if config.per_chain_init:
            # one start per chain (e.g. draws from a variational posterior)
            infos = [
                initialize_model(
                    init_keys[c], model, init_strategy=init_to_value(values={k: v[c] for k, v in init_values.items()}),
                    dynamic_args=True, model_args=(inputs, fixed),
                )
                for c in range(config.num_chains)
            ]
            stacked = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *[i.param_info for i in infos])
            info = infos[0]._replace(param_info=stacked)
        else:
            strategy = init_to_value(values=init_values) if init_values else init_to_uniform
            info = initialize_model(
                init_keys, model, init_strategy=strategy, dynamic_args=True, model_args=(inputs, fixed),
            )
        init_kernel, sample_kernel = hmc(potential_fn_gen=info.potential_fn, algo="NUTS")
        postprocess = info.postprocess_fn(inputs, fixed)

        def one_chain(args):
            chain_key, z, pe, z_grad = args
            state = init_kernel(
                ParamInfo(z, pe, z_grad), config.num_warmup,
                target_accept_prob=config.target_accept, max_tree_depth=config.max_tree_depth,
                dense_mass=config.dense_mass, model_args=(inputs, fixed), rng_key=chain_key,
            )
            # one scan over warm-up and sampling: a single copy of the NUTS
            # kernel in the program (adaptation stops by itself after warm-up)
            def step(s, _):
                s = sample_kernel(s, model_args=(inputs, fixed))
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


def _decentre(init_values: dict, noncentered: tuple[str, ...], fixed: dict) -> dict:
    """Starts of non-centred sites on the sampled scale: :math:`\\tilde M = M \\lambda^{1/2}` column-wise.

    ``LocScaleReparam(centered=0)`` samples ``M_decentered`` and makes ``M`` deterministic,
    so a start given for ``M`` has to be given for ``M_decentered``.
    """
    values = dict(init_values)
    if "M" in noncentered and "M" in values:
        lam = values.get("lam", fixed.get("lam"))
        if lam is None:
            raise LmprompError("init_values['M'] of a non-centred M needs init_values['lam'] (or a fixed lam)")
        values["M_decentered"] = values.pop("M") * jnp.sqrt(lam)[..., None, :]
    if "w" in noncentered and "w" in values:
        raise LmprompError("init_values['w'] needs noncentered=False in the full model")
    return values


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
    num_chains: int = 4,
    num_warmup: int = 500,
    num_samples: int = 2000,
    target_accept: float = 0.9,
    max_tree_depth: int = 10,
    dense_mass: bool = False,
    chain_method: str = "sequential",
    progress: bool = False,
    init_values: Mapping[str, Any] | None = None,
    fixed: Mapping[str, Any] | None = None,
    init: str = "auto",
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
        :math:`p(\mathbf w, \mathbf h | \theta, \mathbf y)`), ``"whb"`` (b too,
        drawn first from :math:`p(\mathbf b | \theta, \mathbf y)`) or ``"none"``
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
    init_values : initial values (constrained) for some sampled sites, either
        one value per site (the same start for every chain) or, with a leading
        axis of length ``num_chains`` on every site, one start per chain (e.g.
        draws from CAVI's posterior, :func:`lmpromp_ppl.inference.warm_start.cavi_start`);
        the other sites start uniformly in (-2, 2) on the unconstrained scale.
        A start for a non-centred ``M`` needs ``lam`` too
    fixed : values at which some latent sites are held (the model is
        conditioned on them); they are left out of ``samples``
    init : where the chains start (:data:`INIT_CHOICES`); ``"auto"`` (default) is
        ``"cavi"`` for the single-type LMProMP without ``init_values``, and ``"uniform"``
        otherwise; ``"cavi"`` draws one
        start per chain from the CAVI posterior of the same model and
        hyperparameters (:func:`lmpromp_ppl.inference.warm_start.cavi_start`),
        fitted with a key folded from ``key``; ``init_values`` given as well
        override the drawn starts

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
    if init not in INIT_CHOICES:
        raise LmprompError(f"init must be one of {list(INIT_CHOICES)}, got {init!r}")
    if chain_method not in ("sequential", "vectorized"):
        raise LmprompError(f"chain_method must be 'sequential' or 'vectorized', got {chain_method!r}")
    if not isinstance(hyper, Hyperparameters):
        raise LmprompError("hyper must be a Hyperparameters instance")
    if init == "auto":
        init = "cavi" if model_name in WARM_START_MODELS and not init_values else "uniform"
    # the CAVI start fits these (sharing the CAVI engine's compiled program); no dense design is built
    # for compact inputs (the potential and the conditional draws evaluate statistics)
    data = as_float64(data)
    fixed = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in (fixed or {}).items()}
    init_values = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in (init_values or {}).items()}
    shapes = site_shapes(model_function(model_name, collapse), data, hyper)
    latent = set(shapes)
    start_info = None
    if init == "cavi":
        starts, start_info = cavi_start(
            model_name, data, hyper, jax.random.fold_in(raw_key(key), 7), num_chains,
            sites=tuple(sorted((latent - set(fixed)) & set(START_SITES))),
        )
        given = {k: jnp.broadcast_to(v, (num_chains,) + shapes[k])
                 if k in shapes and v.shape == shapes[k] else v for k, v in init_values.items()}
        init_values = {**{k: jnp.asarray(v) for k, v in starts.items()}, **given}
    per_chain = bool(init_values) and all(
        name in shapes and v.shape == (num_chains,) + shapes[name] for name, v in init_values.items()
    )
    for what, values in (("fixed", fixed), ("init_values", init_values)):
        unknown = set(values) - latent
        if unknown:
            raise LmprompError(f"{what} names unknown sites {sorted(unknown)}; latent sites: {sorted(latent)}")
        for name, value in values.items():
            expected = shapes[name]
            if value.shape != expected and not (what == "init_values" and per_chain):
                raise LmprompError(
                    f"{what}[{name!r}] has shape {value.shape}, expected {expected}"
                    + (f" (or {(num_chains,) + expected}, one per chain)" if what == "init_values" else "")
                )
    noncentered_sites = _noncentered_sites(model_name, collapse, tuple(sorted(fixed))) if noncentered else ()
    init_values = _decentre(init_values, noncentered_sites, fixed)
    config = _Config(
        model_name, collapse, hyper, noncentered_sites,
        num_chains, num_warmup, num_samples, float(target_accept), max_tree_depth,
        bool(dense_mass), chain_method, per_chain,
    )
    # the potential evaluates the fastest equal form of the data (shared-design or per-demonstration
    # statistics where possible); the draws of the integrated sites use the per-demonstration statistics
    inputs = model_inputs(model_name, collapse, data)
    conditional = None if collapse == "none" else inputs if isinstance(inputs, DemoStatistics) else demo_statistics(data)
    args = (raw_key(key), inputs, conditional, fixed, init_values)
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
        "fixed": sorted(fixed), "init": init,
    }
    if start_info is not None:
        options["init_seconds"] = start_info["seconds"]
    return NutsResult(
        samples={k: np.asarray(v) for k, v in samples.items()},
        sample_stats={k: np.asarray(stats[k]) for k in _STAT_NAMES},
        seconds=seconds,
        compile_seconds=compile_seconds,
        options=options,
    )

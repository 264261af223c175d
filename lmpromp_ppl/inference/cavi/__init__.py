r"""Hand-derived mean-field variational inference (CAVI) for the LMProMP and the mixture of LMProMPs.

One engine: the state always has a component axis, and the single-type
LMProMP (thesis Sec. 4.1) is K = 1 without q(z) and q(pi).  The row-wise
family for M and a learned noise precision are options of the same state
(:mod:`.state`).  The public shape follows BlackJAX's top-level API:

* :func:`init_state` / :func:`init_mixture_state` -- the thesis's starts (:mod:`.init`);
* :func:`step` -- one sweep of the closed-form updates (:mod:`.updates`), then pruning;
* :func:`run` -- the compiled loop of sweeps to a tolerance (:mod:`.loop`);
* :func:`fit` -- validated options, restarts and the split-and-merge search (:mod:`.fit`, :mod:`.search`);
* :func:`sample_q`, :func:`log_q`, :func:`point_estimate` -- the fitted family (:mod:`.posterior`);
* :func:`elbo` -- the closed-form bound (:mod:`.bound`);
* :func:`fit_cavi_batched` -- many datasets of one shape in one vmapped loop (:mod:`.batch`);
* :func:`fit_lr` -- the engine ``cavi_lr``: the joint local family q(w_i, h_i) (:mod:`.state`),
  linear-response covariances of the global quantities (:mod:`.linear_response`) and their
  importance ratios on the collapsed model (:mod:`.importance`).

Every update is derived in ``docs/derivation.md`` and checked in
``tests/test_cavi.py`` and ``tests/test_cavi_mixture.py`` by autodiff
stationarity of :func:`elbo`, and the bound against a Monte Carlo ELBO of the
NumPyro declaration.
"""

from lmpromp_ppl.inference.cavi.batch import (
    BatchedCaviFit,
    fit_cavi_batched,
    linear_response_batched,
    replicate_state,
    sample_q_batched,
)
from lmpromp_ppl.inference.cavi.bound import elbo
from lmpromp_ppl.inference.cavi.data import (
    CaviData,
    DemoGrams,
    EigenCovariance,
    FullCovariance,
    SharedGram,
    sufficient_statistics,
)
from lmpromp_ppl.inference.cavi.fit import RESAMPLE_CHOICES, CaviLrFit, fit, fit_lr
from lmpromp_ppl.inference.cavi.linear_response import LinearResponse, linear_response, sample_lr
from lmpromp_ppl.inference.cavi.init import init_mixture_state, init_state, init_state_jax, ridge_weights
from lmpromp_ppl.inference.cavi.loop import Resume, RunResult, compiled_iterate, fresh, iterate, run, step, sweep
from lmpromp_ppl.inference.cavi.posterior import (
    active_components,
    active_latent_dims,
    log_q,
    point_estimate,
    responsibilities,
    sample_q,
    w_covariance,
)
from lmpromp_ppl.inference.cavi.restarts import CaviFit
from lmpromp_ppl.inference.cavi.search import SEARCHES
from lmpromp_ppl.inference.cavi.state import (
    ACCELERATIONS,
    FAMILIES,
    LOCAL_FAMILIES,
    CaviHyper,
    CaviInfo,
    CaviState,
    ExpectedStats,
    expected_stats,
    family_of,
    hyper_arrays,
    is_mixture,
    lift_single_type,
    local_of,
    with_joint_locals,
)
from lmpromp_ppl.inference.cavi.updates import (
    JOINT_UPDATES,
    UPDATES,
    prune,
    update_alpha,
    update_b,
    update_beta,
    update_h,
    update_lam,
    update_wh,
    update_M,
    update_pi,
    update_w,
    update_z,
    updates_for,
)

__all__ = [
    "CaviData", "DemoGrams", "SharedGram", "FullCovariance", "EigenCovariance", "sufficient_statistics",
    "FAMILIES", "ACCELERATIONS", "CaviHyper", "hyper_arrays", "CaviState", "CaviInfo", "ExpectedStats", "expected_stats",
    "family_of", "is_mixture", "lift_single_type", "LOCAL_FAMILIES", "local_of", "with_joint_locals",
    "update_w", "update_b", "update_M", "update_h", "update_lam", "update_alpha", "update_beta",
    "update_z", "update_pi", "update_wh", "prune", "UPDATES", "JOINT_UPDATES", "updates_for",
    "elbo", "sweep", "step", "Resume", "fresh", "iterate", "compiled_iterate", "run", "RunResult",
    "ridge_weights", "init_state", "init_state_jax", "init_mixture_state",
    "fit", "CaviFit", "SEARCHES",
    "fit_lr", "CaviLrFit", "RESAMPLE_CHOICES", "LinearResponse", "linear_response", "sample_lr",
    "sample_q", "log_q", "point_estimate", "w_covariance", "responsibilities", "active_components",
    "active_latent_dims",
    "fit_cavi_batched", "BatchedCaviFit", "replicate_state", "sample_q_batched", "linear_response_batched",
]

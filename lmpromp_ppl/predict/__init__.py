r"""Prediction by conditioning for the ProMP, the LMProMP and the mixture (thesis Secs. 3.1.2, 4.1.2, 4.2.2).

Workflow (everything in the standardised space of the fit)::

    obs = observe(phase, values, dofs=[0], noise_sd=0.1, num_dofs=2, num_basis=10)
    post = condition("lmpromp", params, obs, gamma=1.0)           # plug-in
    post = condition_draws("lmpromp", draws, obs, gamma=1.0)      # Bayesian, any engine
    traj = trajectory_distribution(post.weights, query, num_dofs=2, num_basis=10)
    paths = sample_trajectories(key, post.weights, query, 100, num_dofs=2, num_basis=10)
    score = score_heldout(post.weights, remainder)

Modules: :mod:`.observations` (what is observed), :mod:`.gaussian` (Gaussian
mixtures and eqs. 3.2, 3.3), :mod:`.conditioning` (eqs. 4.4-4.7, mixtures,
posterior draws), :mod:`.trajectories` (moments and samples), :mod:`.scoring`
(held-out log density, RMSE).
"""

from lmpromp_ppl.predict.conditioning import (
    MODELS,
    SITES,
    Conditioned,
    condition,
    condition_draws,
    condition_lmpromp,
    condition_mixture,
    condition_promp,
    num_sample_dims,
    prior,
)
from lmpromp_ppl.predict.gaussian import (
    GaussianMixture,
    Marginal,
    condition_gaussian,
    log_marginal_density,
    observation_marginal,
)
from lmpromp_ppl.predict.observations import (
    POSITION,
    VELOCITY,
    Observation,
    concatenate,
    empty_observation,
    observe,
    via_point,
)
from lmpromp_ppl.predict.scoring import HeldoutScore, log_predictive_density, rmse, score_heldout
from lmpromp_ppl.predict.trajectories import (
    TrajectoryDistribution,
    sample_trajectories,
    sample_weights,
    trajectory_distribution,
    unstandardise,
    unstandardise_samples,
)

__all__ = [
    "MODELS",
    "SITES",
    "Conditioned",
    "condition",
    "condition_draws",
    "condition_lmpromp",
    "condition_mixture",
    "condition_promp",
    "num_sample_dims",
    "prior",
    "GaussianMixture",
    "Marginal",
    "condition_gaussian",
    "log_marginal_density",
    "observation_marginal",
    "POSITION",
    "VELOCITY",
    "Observation",
    "concatenate",
    "empty_observation",
    "observe",
    "via_point",
    "HeldoutScore",
    "log_predictive_density",
    "rmse",
    "score_heldout",
    "TrajectoryDistribution",
    "sample_trajectories",
    "sample_weights",
    "trajectory_distribution",
    "unstandardise",
    "unstandardise_samples",
]

r"""Hyperparameters of the LMProMP family (thesis Sec. 4.1, 4.2).

Precision convention: every ``N(., x)`` parameter here is a precision
(``beta``, ``lambda0``, ``gamma``); Gamma distributions are shape/rate,
:math:`\Gamma(x | a, b) \propto x^{a-1} e^{-b x}`.

The dataclass's own defaults, ``Hyperparameters()``, are the thesis's values
(:data:`THESIS`, Sec. 4.1; the algebra is proven for any values).  The
settings that :func:`lmpromp_ppl.fit` uses when given none, :data:`DEFAULT`
(``preset("default")``), are chosen for data
standardised per DoF (the default in lmpromp-ppl) by measurement on real
recordings (LASA, GunPoint; docs/defaults.md and ``reports/real-data/``):

* ``lambda0 = 1`` (the thesis's value): the offset ``b`` has the scale of
  standardised data.  With the well-conditioned default basis
  (:data:`lmpromp_ppl.basis.DEFAULT_NUM_BASIS`, width 1) weights are of order
  one, so this prior costs the mean movement little in ``b`` (the population
  mean lies 0.006-0.045 data s.d. from the demonstrations' mean on LASA) and it
  keeps a mixture component's Occam factor modest, so that the mixture finds
  movement types (with ``lambda0 = 0.01`` a new component's ``b`` costs about
  :math:`\tfrac d2 \log 100` nats more and the bound merges types on one
  component's latent plane).  Under the thesis's width-2 basis, whose weights
  reach 40 on LASA, ``lambda0 = 1`` lets a column of ``M`` absorb the mean
  movement instead (docs/defaults.md);
* ``learn_beta = True`` with ``beta ~ Gamma(1, 0.01)`` (mean 100, an
  Exponential prior on the noise precision): the noise level is learned from
  the data, for every engine.  A fixed ``beta = 100`` (noise s.d. 0.1) is too
  precise for noisy recordings and too loose for smooth ones; ``beta`` is the
  fixed value used when ``learn_beta=False``;
* ``gamma = 1`` and ``a0 = b0 = 1e-5`` as in Sec. 4.1;
* ``c0 = 1, d0 = 1e-3``: c0 = 1 is the sparsity-favouring (Laplace-like)
  choice of Sec. 4.1; the Exponential prior on :math:`\lambda_v` with mean
  1000 adds a single pseudo-observation and is nearly flat over the precisions
  that standardised data support.  The rate must be small for ARD to work:
  the posterior mean obeys :math:`\bar\lambda_v \le (c_0 + d/2)/d_0`, so a
  switched-off column keeps :math:`1/\bar\lambda_v \ge d_0/(c_0 + d/2)`.

:data:`THESIS` keeps the thesis's values (fixed ``beta = 100``) for the
reproduction of its experiments; fits with them and the thesis's basis on real
data are flagged by :mod:`lmpromp_ppl.diagnostics.degeneracy`.

:data:`PROPER` (the default for NUTS and SVI) is :data:`DEFAULT` with two
changes for sampling-based engines.  A proper Gamma(1e-2, 1e-2) prior on
``alpha``: Gamma(1e-5, 1e-5) is nearly improper (its mass sits at 0 and at huge
values), so NUTS cannot explore it and prior simulation produces absurd
precisions.  And the weak offset prior ``lambda0 = 0.01``: with ``lambda0 = 1``
NUTS puts part of LASA GShape's mean movement in ``M h`` (population mean 0.31
data s.d. from the demonstrations' mean, against 0.011 with 0.01).  The ARD
prior stays Gamma(1, 1e-3): with the earlier Gamma(2, 2) a column that the data
do not need keeps a prior scale of order one under NUTS, and the predictive
band of a new LASA Angle demonstration was five times too wide (coverage 1.00,
half-width 1.5 data s.d.; 0.82 and 0.30 with Gamma(1, 1e-3); docs/defaults.md).

:data:`SIMULATION` is for prior and prior-predictive simulation
(:mod:`lmpromp_ppl.models.prior`).  Even PROPER's Gamma(1e-2, 1e-2) puts most
of its mass on precisions below 1e-20, so simulated weights would have standard
deviations beyond 1e10.  SIMULATION uses ``a0 = 3, b0 = 0.2`` (alpha has prior
mean 15, E[1/alpha] = 0.1: residual s.d. about 0.3 of a standardised DoF) and
``c0 = 3, d0 = 2`` (E[1/lam_v] = 1: each column of M has unit scale); shapes
above 2 give the prior predictive finite variances.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from lmpromp_ppl.errors import LmprompError

__all__ = ["Hyperparameters", "DEFAULT", "THESIS", "PROPER", "SIMULATION", "preset"]


@dataclass(frozen=True)
class Hyperparameters:
    """Hyperparameters of the ProMP, LMProMP and mixture models.

    Attributes
    ----------
    beta : observation-noise precision (fixed unless ``learn_beta``)
    lambda0 : prior precision of the offset ``b``
    gamma : prior precision of the control variables ``h``
    a0, b0 : Gamma shape and rate of the weight precision ``alpha``
    c0, d0 : Gamma shape and rate of the column precisions ``lam``
    latent_dim : V, the dimension of ``h``
    num_components : K, mixture components (1 for the single-type model)
    kappa0 : Dirichlet concentration of the mixture weights ``pi``
    learn_beta : give ``beta`` a Gamma(beta_a0, beta_b0) prior and infer it
    beta_a0, beta_b0 : Gamma shape and rate of ``beta`` when learned
    promp_scale : scale of the HalfNormal prior on the per-weight standard
        deviations of the ProMP baseline (:func:`lmpromp_ppl.models.promp.promp_model`)
    lkj_concentration : LKJ concentration of the ProMP baseline's weight correlation
    """

    beta: float = 100.0
    lambda0: float = 1.0
    gamma: float = 1.0
    a0: float = 1e-5
    b0: float = 1e-5
    c0: float = 1.0
    d0: float = 1e-3
    latent_dim: int = 3
    num_components: int = 1
    kappa0: float = 1.0
    learn_beta: bool = False
    beta_a0: float = 1.0
    beta_b0: float = 0.01
    promp_scale: float = 1.0
    lkj_concentration: float = 2.0

    def __post_init__(self):
        for name in ("beta", "lambda0", "gamma", "a0", "b0", "c0", "d0", "kappa0", "beta_a0", "beta_b0",
                     "promp_scale", "lkj_concentration"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or isinstance(value, bool):
                raise LmprompError(f"hyperparameter {name} must be a number, got {value!r}")
            if not value > 0 or value != value or value == float("inf"):
                raise LmprompError(f"hyperparameter {name} must be positive and finite, got {value}")
            object.__setattr__(self, name, float(value))
        for name in ("latent_dim", "num_components"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value < 1:
                raise LmprompError(f"hyperparameter {name} must be an integer >= 1, got {value!r}")
            object.__setattr__(self, name, int(value))
        object.__setattr__(self, "learn_beta", bool(self.learn_beta))

    def validate_for(self, num_weights: int, num_demos: int | None = None) -> "Hyperparameters":
        """Check the latent dimension against the weight dimension d (and L)."""
        if self.latent_dim > num_weights:
            raise LmprompError(
                f"latent dimension V={self.latent_dim} exceeds the weight dimension d={num_weights}"
            )
        if num_demos is not None and num_demos < self.latent_dim:
            raise LmprompError(
                f"fewer demonstrations (L={num_demos}) than latent dimensions (V={self.latent_dim})"
            )
        return self

    def replace(self, **changes) -> "Hyperparameters":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "Hyperparameters":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise LmprompError(f"unknown hyperparameters: {sorted(unknown)}")
        return cls(**d)


THESIS = Hyperparameters()
DEFAULT = THESIS.replace(learn_beta=True)
PROPER = DEFAULT.replace(a0=1e-2, b0=1e-2, lambda0=1e-2)
SIMULATION = THESIS.replace(a0=3.0, b0=0.2, c0=3.0, d0=2.0)


def preset(name: str, **changes) -> Hyperparameters:
    """Named preset, ``"default"``, ``"thesis"``, ``"proper"`` or ``"simulation"``, with changes."""
    presets = {"default": DEFAULT, "thesis": THESIS, "proper": PROPER, "simulation": SIMULATION}
    if name not in presets:
        raise LmprompError(f"unknown hyperparameter preset {name!r}; choose from {sorted(presets)}")
    return presets[name].replace(**changes)

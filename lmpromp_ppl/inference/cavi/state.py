r"""The state of the CAVI engine: one variational family for the single-type LMProMP and the mixture.

Model (thesis Sec. 4.1 and 4.2, eq. 4.8, with the Dirichlet prior of
:func:`lmpromp_ppl.models.mixture.mixture_model`; precisions, Gamma shape/rate):

.. math::

    \pi &\sim \mathrm{Dir}(\kappa_0 1_K), \quad z_i \sim \mathrm{Cat}(\pi), \quad
    b_k \sim \mathcal N(0, \lambda_0^{-1} I_d), \quad
    \lambda_{kv} \sim \Gamma(c_0, d_0), \quad
    m_{kv} \sim \mathcal N(0, \lambda_{kv}^{-1} I_d), \quad
    \alpha_k \sim \Gamma(a_0, b_0), \\
    h_{ik} &\sim \mathcal N(0, \gamma^{-1} I_V), \quad
    w_i \mid z_i = k \sim \mathcal N(b_k + M_k h_{ik}, \alpha_k^{-1} I_d), \quad
    y_i \sim \mathcal N(\Psi_i w_i, \beta^{-1} I), \quad
    \beta \sim \Gamma(\beta_{a0}, \beta_{b0})\ \text{(when learned)}.

The single-type LMProMP (Sec. 4.1) is K = 1 without z and pi: its state has
``resp`` and ``pi_conc`` set to ``None`` and its bound is the mixture's with
K = 1 (the terms in pi and z vanish).  Every state has the component axis.

Variational family (eq. 4.3, Sec. 4.2.1): :math:`q(z_i) = \mathrm{Cat}(r_i)`,
:math:`q(\pi) = \mathrm{Dir}(\hat\kappa)`, per component :math:`q(b_k)`,
:math:`q(M_k)`, :math:`q(\alpha_k)`, :math:`q(\lambda_{kv})`, :math:`q(h_{ik})`
for every i and k, shared :math:`q(w_i)`, and :math:`q(\beta) = \Gamma(\hat a_\beta, \hat b_\beta)`
when beta is learned.  Two families for M (:data:`FAMILIES`):

* ``"columnwise"`` (thesis eq. 4.3, the default):
  :math:`q(m_{kv}) = \mathcal N(\mu_{kv}, \sigma_{kv} I_d)`; ``M_var`` is (K, V);
* ``"rowwise"`` (variational Bayesian PCA): the rows of :math:`M_k` share one full
  covariance, :math:`q(M_k) = \prod_j \mathcal N(m_{k,j\cdot} \mid \mu_{k,j\cdot}, \Sigma_{M_k})`;
  ``M_var`` is (K, V, V).  The column-wise family is the special case of a
  diagonal :math:`\Sigma_{M_k}`.

Two families of the local factors (:data:`LOCAL_FAMILIES`):

* ``"meanfield"`` (thesis eq. 4.3, the default): :math:`q(w_i)\prod_k q(h_{ik})`;
  ``wh_cov`` is ``None``;
* ``"joint"`` (the single type): one joint Gaussian :math:`q(w_i, h_i)` per
  demonstration, kept as :math:`q(h_i) = \mathcal N(\mu_{h_i}, S_i)` (``h_cov``) and
  :math:`q(w_i \mid h_i) = \mathcal N(\mu_{w_i} + C_iS_i^{-1}(h_i - \mu_{h_i}), W_i)`, with
  ``w_cov`` the conditional covariance :math:`W_i` and ``wh_cov`` the cross covariance
  :math:`C_i = \operatorname{Cov}(w_i, h_i)` (L, K, d, V).  The marginal covariance of
  :math:`w_i` is :math:`W_i + C_iS_i^{-1}C_i^T`; every (W, S, C) with W and S positive
  definite is a member, and C = 0 is the mean-field family.  The cut that the
  mean-field family makes between :math:`w_i` and :math:`h_i` is the one that moves
  latent variance into :math:`1/\alpha` (``docs/derivation.md``, structured family).

Removed components (Sec. 4.2.1) are kept in the arrays and switched off by the
boolean ``active`` mask: they get :math:`r_{ik} = 0`, their factors are frozen,
and their terms are left out of the bound (the bound of the declared model for
the family in which a removed component's parameters are distributed as under
their prior).  Derivations and thesis errata: ``docs/derivation.md``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.scipy.special import digamma

from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.inference.cavi.data import Covariance, cov_trace
from lmpromp_ppl.models.hyper import Hyperparameters

__all__ = [
    "FAMILIES",
    "check_family",
    "LOCAL_FAMILIES",
    "check_local",
    "with_joint_locals",
    "local_of",
    "CaviHyper",
    "hyper_arrays",
    "ACCELERATIONS",
    "check_acceleration",
    "CaviState",
    "CaviInfo",
    "family_of",
    "is_mixture",
    "lift_single_type",
    "ExpectedStats",
    "expected_stats",
    "keep_active",
]

#: Names of the families of q(M): the thesis's column-wise isotropic one (default) and the row-wise one.
FAMILIES = ("columnwise", "rowwise")
#: Names of the families of the local factors: the thesis's q(w_i) q(h_i) (default) and the joint q(w_i, h_i).
LOCAL_FAMILIES = ("meanfield", "joint")


def check_family(family: str) -> None:
    """Refuse an unknown family of q(M)."""
    if family not in FAMILIES:
        raise LmprompError(f"unknown family {family!r} for q(M); choose from {list(FAMILIES)}")


def check_local(local: str) -> None:
    """Refuse an unknown family of the local factors."""
    if local not in LOCAL_FAMILIES:
        raise LmprompError(f"unknown local family {local!r}; choose from {list(LOCAL_FAMILIES)}")


class CaviHyper(NamedTuple):
    """Hyperparameters (and the pruning threshold) as float64 scalars, so compiled code is shared across values.

    Attributes
    ----------
    beta : fixed noise precision :math:`\\beta` (ignored when the state has ``q(beta)``)
    lambda0 : prior precision :math:`\\lambda^{[0]}` of ``b``
    gamma : prior precision :math:`\\gamma` of ``h``
    a0, b0 : Gamma shape/rate of :math:`\\alpha`
    c0, d0 : Gamma shape/rate of :math:`\\lambda_v`
    kappa0 : Dirichlet concentration of :math:`\\pi` (mixture)
    beta_a0, beta_b0 : Gamma shape/rate of :math:`\\beta` when learned
    prune_threshold : a component is removed when its expected number of
        demonstrations :math:`N_k = \\sum_i r_{ik}` falls below this (an algorithm
        setting, not part of the model; Sec. 4.2.1)
    transform : 1.0 to follow each sweep by the bound-maximising rescalings of
        :mod:`.transform`, 0.0 for none (an algorithm setting, an array so that
        both share compiled code)
    overrelax : 1.0 to extrapolate along each sweep and keep the extrapolation when
        its bound is higher (:mod:`.accelerate`), 0.0 for plain sweeps
    """

    beta: Array
    lambda0: Array
    gamma: Array
    a0: Array
    b0: Array
    c0: Array
    d0: Array
    kappa0: Array
    beta_a0: Array
    beta_b0: Array
    prune_threshold: Array
    transform: Array
    overrelax: Array


#: The accelerations of the sweeps (``cavi.fit(accelerate=...)``): name -> (transform, overrelax) of :class:`CaviHyper`.
ACCELERATIONS = {"scale": (True, True), "overrelax": (False, True), "none": (False, False)}


def check_acceleration(accelerate: str) -> None:
    """Refuse an unknown name of :data:`ACCELERATIONS`."""
    if accelerate not in ACCELERATIONS:
        raise LmprompError(f"unknown acceleration {accelerate!r}; choose from {list(ACCELERATIONS)}")


def hyper_arrays(hyper: Hyperparameters, prune_threshold: float = 0.5, accelerate: str = "scale") -> CaviHyper:
    """Build :class:`CaviHyper` from a :class:`Hyperparameters` and the algorithm settings.

    ``accelerate`` names the acceleration of the sweeps (:data:`ACCELERATIONS`):
    ``"scale"`` (default), ``"overrelax"`` or ``"none"`` (the thesis's plain CAVI).
    """
    check_acceleration(accelerate)
    transform, overrelax = ACCELERATIONS[accelerate]
    settings = [prune_threshold, float(transform), float(overrelax)]
    values = [getattr(hyper, name) for name in CaviHyper._fields[: -len(settings)]] + settings
    return CaviHyper(*(jnp.asarray(v, jnp.float64) for v in values))


class CaviState(NamedTuple):
    """Parameters of every factor of q (eq. 4.3 and Sec. 4.2.1, with the extensions of the module docstring).

    Attributes
    ----------
    w_mean : (L, d) :math:`\\mu_{w_i}`
    w_cov : :class:`~.data.FullCovariance` or :class:`~.data.EigenCovariance` (inside the
        rotated loop :class:`~.data.DiagonalCovariance`), :math:`\\Sigma_{w_i}`
    h_mean : (L, K, V) :math:`\\mu_{h_{ik}}`
    h_cov : (L, K, V, V) :math:`\\Sigma_{h_{ik}}`
    b_mean : (K, d) :math:`\\mu_{b_k}`
    b_var : (K,) :math:`\\sigma_{b_k}` (variances)
    M_mean : (K, d, V) :math:`\\bar M_k`
    M_var : (K, V) column variances :math:`\\sigma_{kv}` (``"columnwise"``) or
        (K, V, V) the shared row covariance :math:`\\Sigma_{M_k}` (``"rowwise"``)
    alpha_shape, alpha_rate : (K,) :math:`\\bar a_k, \\bar b_k`
    lam_shape, lam_rate : (K, V) :math:`\\bar c_{kv}, \\bar d_{kv}`
    resp : (L, K) responsibilities :math:`r_{ik} = q(z_i = k)`; ``None`` for the single type
    pi_conc : (K,) Dirichlet concentration :math:`\\hat\\kappa` of q(pi); ``None`` for the single type
    beta_shape, beta_rate : () Gamma q(beta), used when ``beta_learned``
    beta_learned : () bool, beta has the factor q(beta) (else the fixed ``hyper.beta``)
    active : (K,) bool, False for removed components
    wh_cov : (L, K, d, V) the cross covariances :math:`C_{ik} = \\operatorname{Cov}(w_i, h_{ik})` of the
        joint local family (``w_cov`` then holds the conditional covariances); ``None``
        for the mean-field family

    Whether beta is learned is an array (not the pytree structure) so that
    fixed and learned beta share compiled code.
    """

    w_mean: Array
    w_cov: Covariance
    h_mean: Array
    h_cov: Array
    b_mean: Array
    b_var: Array
    M_mean: Array
    M_var: Array
    alpha_shape: Array
    alpha_rate: Array
    lam_shape: Array
    lam_rate: Array
    resp: Array | None
    pi_conc: Array | None
    beta_shape: Array
    beta_rate: Array
    beta_learned: Array
    active: Array
    wh_cov: Array | None = None


class CaviInfo(NamedTuple):
    """Per-sweep information: the ELBO after the sweep."""

    elbo: Array


def family_of(state: CaviState) -> str:
    """``"rowwise"`` when ``M_var`` holds (V, V) covariances, else ``"columnwise"``."""
    return "rowwise" if state.M_var.ndim == 3 else "columnwise"


def local_of(state: CaviState) -> str:
    """``"joint"`` when the state has the joint local family (``wh_cov``), else ``"meanfield"``."""
    return "meanfield" if state.wh_cov is None else "joint"


def with_joint_locals(state: CaviState) -> CaviState:
    """The same q in the joint local family (cross covariances 0); the single type only."""
    if state.resp is not None:
        raise LmprompError("the joint local family is derived for the single-type LMProMP, not for the mixture")
    if state.wh_cov is not None:
        return state
    L, d = state.w_mean.shape
    K, V = state.lam_shape.shape
    return state._replace(wh_cov=jnp.zeros((L, K, d, V), jnp.float64))


def is_mixture(state: CaviState) -> bool:
    """Whether the state has q(z) and q(pi) (the mixture) rather than the single type."""
    return state.resp is not None


def lift_single_type(fields: dict, family: str = "columnwise", beta: tuple[float, float] | None = None) -> CaviState:
    """A :class:`CaviState` (K = 1) from the fields of a single-type state without component axis.

    ``fields`` has ``w_mean``, ``w_cov``, ``h_mean`` (L, V), ``h_cov``, ``b_mean`` (d,),
    ``b_var`` (), ``M_mean`` (d, V), ``M_var`` (V,), ``alpha_shape``, ``alpha_rate``,
    ``lam_shape``, ``lam_rate`` (V,), as the thesis writes the family (eq. 4.3) and as fits
    saved before the component axis hold them.  ``family="rowwise"`` turns the column
    variances into a diagonal row covariance (the same distribution); ``beta=(shape, rate)``
    adds q(beta).
    """
    check_family(family)
    shape, rate = (1.0, 1.0) if beta is None else beta
    M_var = _expand(fields["M_var"], 0)
    if family == "rowwise":
        M_var = jax.vmap(jnp.diag)(M_var)
    return CaviState(
        w_mean=fields["w_mean"],
        w_cov=fields["w_cov"],
        h_mean=_expand(fields["h_mean"], 1),
        h_cov=_expand(fields["h_cov"], 1),
        b_mean=_expand(fields["b_mean"], 0),
        b_var=_expand(fields["b_var"], 0),
        M_mean=_expand(fields["M_mean"], 0),
        M_var=M_var,
        alpha_shape=_expand(fields["alpha_shape"], 0),
        alpha_rate=_expand(fields["alpha_rate"], 0),
        lam_shape=_expand(fields["lam_shape"], 0),
        lam_rate=_expand(fields["lam_rate"], 0),
        resp=None,
        pi_conc=None,
        beta_shape=jnp.asarray(shape, jnp.float64),
        beta_rate=jnp.asarray(rate, jnp.float64),
        beta_learned=jnp.asarray(beta is not None),
        active=jnp.ones((1,), jnp.bool_),
    )


def _expand(x, axis: int):
    """``x`` as float64 with a new axis of length 1 at ``axis``.

    Concrete values are expanded in NumPy: on a device array every new shape of
    an indexing op compiles a small program, which a user waits for at each start.
    """
    if isinstance(x, jax.core.Tracer):
        return jnp.expand_dims(jnp.asarray(x, jnp.float64), axis)
    return jnp.asarray(np.expand_dims(np.asarray(x, np.float64), axis))


class ExpectedStats(NamedTuple):
    """Moments of q shared by the updates and the bound.

    Attributes
    ----------
    resp : (L, K) responsibilities, 0 for removed components (ones (L, 1) for the single type)
    alpha_mean, log_alpha_mean : (K,) :math:`\\bar\\alpha_k = \\bar a_k/\\bar b_k`, :math:`E[\\log\\alpha_k]`
    lam_mean, log_lam_mean : (K, V)
    M_col_var : (K, V) :math:`d^{-1}E\\|m_{kv} - \\mu_{kv}\\|^2` (the diagonal of the row covariance)
    MtM : (K, V, V) :math:`E[M_k^TM_k] = \\bar M_k^T\\bar M_k + d\\Sigma_{M_k}`
    hhT : (L, K, V, V) :math:`E[h_{ik}h_{ik}^T]`
    residual_sq : (L, K) :math:`E\\|w_i - b_k - M_kh_{ik}\\|^2` (with the cross covariances of the joint family)
    beta_mean, log_beta_mean : () :math:`E[\\beta]`, :math:`E[\\log\\beta]` (the fixed value when not learned)
    log_pi_mean : (K,) :math:`E[\\log\\pi_k] = \\psi(\\hat\\kappa_k) - \\psi(\\sum_j\\hat\\kappa_j)`, or None

    The log-expectations (``log_alpha_mean``, ``log_lam_mean``, ``log_beta_mean``,
    ``log_pi_mean``) are None unless asked for (``logs=True``): only the bound and the
    update of q(z) need them, and each digamma is a large expression to compile.
    """

    resp: Array
    alpha_mean: Array
    log_alpha_mean: Array
    lam_mean: Array
    log_lam_mean: Array
    M_col_var: Array
    MtM: Array
    hhT: Array
    residual_sq: Array
    beta_mean: Array
    log_beta_mean: Array
    log_pi_mean: Array | None


def expected_stats(state: CaviState, hyper: CaviHyper, *, logs: bool = False) -> ExpectedStats:
    """Moments of q (App. B.1 helper functions 3 and 4 with the factor d kept; App. B.2 per component).

    ``logs=True`` adds the log-expectations (digammas) that the bound and q(z) use.
    """
    L, d = state.w_mean.shape
    K = state.M_mean.shape[0]
    if state.M_var.ndim == 3:
        M_col_var = jnp.diagonal(state.M_var, axis1=-2, axis2=-1)
        M_cov = state.M_var
    else:
        M_col_var = state.M_var
        M_cov = jax.vmap(jnp.diag)(state.M_var)
    MtM = jnp.einsum("kdu,kdv->kuv", state.M_mean, state.M_mean) + d * M_cov
    hhT = state.h_cov + jnp.einsum("iku,ikv->ikuv", state.h_mean, state.h_mean)
    offset = state.w_mean[:, None, :] - state.b_mean[None]
    residual_sq = (
        jnp.sum(offset**2, axis=-1)
        + cov_trace(state.w_cov)[:, None]
        + d * state.b_var[None]
        - 2.0 * jnp.einsum("ikd,kdv,ikv->ik", offset, state.M_mean, state.h_mean)
        + jnp.einsum("kuv,ikvu->ik", MtM, hhT)
    )
    if state.wh_cov is not None:
        # joint family: tr Cov(w_i) gains tr(C S^-1 C^T), and E[(w - b)^T M h] gains tr(M^T C)
        residual_sq = residual_sq + cross_trace(state)[:, None] - 2.0 * jnp.einsum(
            "kdv,ikdv->ik", state.M_mean, state.wh_cov)
    resp = jnp.ones((L, K)) if state.resp is None else jnp.where(state.active[None], state.resp, 0.0)
    learned = state.beta_learned
    beta_mean = jnp.where(learned, state.beta_shape / state.beta_rate, hyper.beta)
    log_alpha_mean = log_lam_mean = log_beta_mean = log_pi_mean = None
    if logs:
        # one digamma over every Gamma and Dirichlet shape: each call is a large expression to compile
        V = state.lam_shape.shape[1]
        shapes = [state.alpha_shape, state.lam_shape.reshape(-1), state.beta_shape[None]]
        if state.resp is not None:
            shapes += [state.pi_conc, jnp.sum(state.pi_conc)[None]]
        psi = digamma(jnp.concatenate(shapes))
        log_alpha_mean = psi[:K] - jnp.log(state.alpha_rate)
        log_lam_mean = psi[K : K + K * V].reshape(K, V) - jnp.log(state.lam_rate)
        log_beta_mean = jnp.where(learned, psi[K + K * V] - jnp.log(state.beta_rate), jnp.log(hyper.beta))
        if state.resp is not None:
            log_pi_mean = psi[K + K * V + 1 : -1] - psi[-1]
    return ExpectedStats(
        resp=resp,
        alpha_mean=state.alpha_shape / state.alpha_rate,
        log_alpha_mean=log_alpha_mean,
        lam_mean=state.lam_shape / state.lam_rate,
        log_lam_mean=log_lam_mean,
        M_col_var=M_col_var,
        MtM=MtM,
        hhT=hhT,
        residual_sq=residual_sq,
        beta_mean=beta_mean,
        log_beta_mean=log_beta_mean,
        log_pi_mean=log_pi_mean,
    )


def cross_solve(state: CaviState) -> Array:
    """(L, d, V) :math:`C_iS_i^{-1}` of the joint local family (single type): the regression of w_i on h_i."""
    C, S = state.wh_cov[:, 0], state.h_cov[:, 0]
    return jnp.swapaxes(jnp.linalg.solve(S, jnp.swapaxes(C, -1, -2)), -1, -2)


def cross_trace(state: CaviState) -> Array:
    """(L,) :math:`\\operatorname{tr}(C_iS_i^{-1}C_i^T)`, the part of tr Cov(w_i) that the joint family adds to W_i."""
    return jnp.einsum("idv,idv->i", cross_solve(state), state.wh_cov[:, 0])


def keep_active(active: Array, new: Array, old: Array) -> Array:
    """``new`` for active components (leading K axis), ``old`` (frozen) for removed ones."""
    mask = active.reshape(active.shape + (1,) * (new.ndim - 1))
    return jnp.where(mask, new, old)

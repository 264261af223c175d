r"""Synthetic demonstrations with known ground truth.

Every generator is a pure function of its arguments: all randomness comes from
``np.random.default_rng(seed)``.  The ground truth is returned as numpy arrays
in :attr:`Demonstrations.metadata`.  Weight vectors follow the layout of
:mod:`lmpromp_ppl.basis` (DoF-major weights, time-major observations) and
trajectories are generated through :func:`lmpromp_ppl.basis.design_matrix`
with the basis width :data:`GENERATOR_WIDTH` (2, the thesis's), fixed here so
that the datasets do not change with the fitting defaults.

Generators (the names used in ``synthetic:<name>?key=value&...``):

``latent``
    The LMProMP generative model of thesis Eq. (4.1) with Sec. 3.1's
    likelihood: :func:`latent_manifold`.
``clusters``
    Four movement types whose weight vectors form four clusters in a 2-D
    subspace of the weight space, as in thesis Sec. 5.1 / Fig. 5.3:
    :func:`four_clusters`.
``reaching``
    A bimodal obstacle-avoiding reaching task in 7 dimensions (3 positions
    and a unit quaternion), in the spirit of thesis Sec. 5.4 / Fig. 5.2:
    :func:`obstacle_reaching`; :func:`count_collisions` counts trajectories
    that hit the obstacle.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike

from lmpromp_ppl.basis import THESIS_WIDTH, design_matrix
from lmpromp_ppl.data.core import Demonstrations
from lmpromp_ppl.errors import DataError

__all__ = [
    "latent_manifold",
    "four_clusters",
    "obstacle_reaching",
    "count_collisions",
    "GENERATORS",
]


def _check_int(generator: str, name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise DataError(f"synthetic:{generator}: {name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _check_positive(generator: str, name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise DataError(f"synthetic:{generator}: {name} must be a number, got {value!r}")
    if not (np.isfinite(value) and value > 0):
        raise DataError(f"synthetic:{generator}: {name} must be positive and finite, got {value!r}")
    return float(value)


def _check_seed(generator: str, seed) -> int:
    return _check_int(generator, "seed", seed, 0)


def _query(params: dict) -> str:
    return "&".join(f"{key}={value}" for key, value in params.items())


#: Basis width of the generators (independent of :data:`lmpromp_ppl.basis.DEFAULT_WIDTH`).
GENERATOR_WIDTH = THESIS_WIDTH


def _trajectories(phase: np.ndarray, weights: np.ndarray, num_dofs: int, num_basis: int) -> np.ndarray:
    """Noise-free positions ``Psi w`` for each weight vector: (L, T, D)."""
    psi = np.asarray(design_matrix(phase, num_dofs, num_basis, GENERATOR_WIDTH))
    return (weights @ psi.T).reshape(weights.shape[0], phase.shape[0], num_dofs)


def latent_manifold(
    L: int = 20,
    D: int = 2,
    J: int = 10,
    V: int = 3,
    T: int = 50,
    alpha: float = 100.0,
    beta: float = 400.0,
    seed: int = 0,
    duration: float = 1.0,
    spread: float = 0.0,
) -> Demonstrations:
    r"""Demonstrations drawn from the LMProMP generative model.

    With :math:`d = DJ` weights (thesis Eq. (4.1) and Sec. 3.1):

    .. math::

        \mathbf b \sim \mathcal N(0, I_d), \quad
        \mathbf M = U \operatorname{diag}(s_1, \dots, s_V), \quad
        \mathbf h^{[i]} \sim \mathcal N(0, I_V), \\
        \mathbf w^{[i]} \sim \mathcal N(\mathbf b + \mathbf M \mathbf h^{[i]}, \alpha^{-1} I_d), \quad
        \mathbf y^{[i]} \sim \mathcal N(\Psi \mathbf w^{[i]}, \beta^{-1} I_{TD}),

    where :math:`U` has orthonormal columns (a random rotation) and the
    column scales :math:`s_v = 2 \cdot 2^{-v}` (2, 1, 0.5, ...) decrease, so
    that the eigenvalues :math:`s_v^2` of :math:`M M^T` are well separated
    from each other and from the weight noise :math:`\alpha^{-1}`.

    Parameters
    ----------
    L : number of demonstrations (>= 2)
    D : degrees of freedom
    J : basis functions per DoF (>= 2)
    V : latent dimension, at most ``D * J``
    T : samples per demonstration at equally spaced phases in [0, 1] (>= 2)
    alpha : weight precision
    beta : observation-noise precision
    seed : seed of ``np.random.default_rng``
    duration, spread : demonstration i lasts
        :math:`T_i = \text{duration} \cdot e^{\text{spread}\, \epsilon_i}`,
        :math:`\epsilon_i \sim \mathcal N(0, 1)` (drawn after everything else, so
        the positions do not depend on them); times ``T_i * linspace(0, 1, T)``

    Returns
    -------
    Demonstrations
        Times = phases ``linspace(0, 1, T)`` by default; ``metadata`` holds
        ``durations`` (L,) and ``b`` (d,),
        ``M`` (d, V), ``h`` (L, V), ``w`` (L, d), ``alpha``, ``beta`` and
        ``num_basis`` (= J).
    """
    name = "latent"
    L = _check_int(name, "L", L, 2)
    D = _check_int(name, "D", D, 1)
    J = _check_int(name, "J", J, 2)
    V = _check_int(name, "V", V, 1)
    T = _check_int(name, "T", T, 2)
    alpha = _check_positive(name, "alpha", alpha)
    beta = _check_positive(name, "beta", beta)
    seed = _check_seed(name, seed)
    duration = _check_positive(name, "duration", duration)
    if isinstance(spread, bool) or not isinstance(spread, (int, float, np.floating, np.integer)) or not (
        np.isfinite(spread) and 0 <= spread <= 1
    ):
        raise DataError(f"synthetic:{name}: spread must be a number in [0, 1], got {spread!r}")
    spread = float(spread)
    d = D * J
    if V > d:
        raise DataError(f"synthetic:{name}: V must be at most D * J = {d}, got {V}")
    rng = np.random.default_rng(seed)
    b = rng.standard_normal(d)
    directions, _ = np.linalg.qr(rng.standard_normal((d, V)))
    scales = 2.0 * 0.5 ** np.arange(V)
    M = directions * scales
    h = rng.standard_normal((L, V))
    w = b + h @ M.T + rng.standard_normal((L, d)) / np.sqrt(alpha)
    phase = np.linspace(0.0, 1.0, T)
    y = _trajectories(phase, w, D, J) + rng.standard_normal((L, T, D)) / np.sqrt(beta)
    params = dict(L=L, D=D, J=J, V=V, T=T, alpha=alpha, beta=beta, seed=seed)
    if duration != 1.0 or spread != 0.0:
        params.update(duration=duration, spread=spread)
    durations = duration * np.exp(spread * rng.standard_normal(L)) if spread > 0 else np.full(L, duration)
    return Demonstrations(
        times=tuple(phase * durations[i] if duration != 1.0 or spread > 0 else phase for i in range(L)),
        positions=tuple(y),
        name=f"synthetic:{name}?{_query(params)}",
        metadata={
            "b": b,
            "M": M,
            "h": h,
            "w": w,
            "alpha": np.asarray(alpha),
            "beta": np.asarray(beta),
            "num_basis": np.asarray(J),
            "durations": durations,
        },
    )


def four_clusters(
    L: int = 40,
    D: int = 1,
    J: int = 8,
    T: int = 50,
    radius: float = 1.5,
    spread: float = 0.3,
    alpha: float = 400.0,
    beta: float = 400.0,
    seed: int = 0,
) -> Demonstrations:
    r"""Four movement types as four clusters in a 2-D subspace of the weights.

    As in thesis Sec. 5.1 (Fig. 5.3) the weight vectors lie on four clusters
    in a plane of a weight space with :math:`d = DJ \ge 6`.  With an offset
    :math:`\mathbf b \sim \mathcal N(0, I_d)` and orthonormal
    :math:`U = [\mathbf u_1, \mathbf u_2]`, cluster :math:`k = 0, \dots, 3` is
    centred at :math:`\mathbf b + r U (\cos\theta_k, \sin\theta_k)^T` with
    :math:`\theta_k = k\pi/2`, so the centres lie on a circle: the union of the
    clusters is a non-linear manifold that one Gaussian prior averages over.
    Within a cluster the plane coordinates spread with standard deviation
    ``spread`` along the circle and ``spread / 4`` across it, and every weight
    gets isotropic noise of precision ``alpha``:

    .. math::

        \mathbf w^{[i]} = \mathbf b + U \mathbf c^{[i]}
            + \boldsymbol\epsilon^{[i]}, \quad
        \boldsymbol\epsilon^{[i]} \sim \mathcal N(0, \alpha^{-1} I_d), \quad
        \mathbf y^{[i]} \sim \mathcal N(\Psi \mathbf w^{[i]}, \beta^{-1} I).

    Demonstration ``i`` belongs to cluster ``i % 4``.

    Parameters
    ----------
    L : number of demonstrations (>= 4, so every cluster is demonstrated)
    D, J : DoF and basis functions per DoF, with ``D * J >= 6``
    T : samples per demonstration at equally spaced phases in [0, 1]
    radius : distance of the cluster centres from ``b`` in the plane
    spread : within-cluster standard deviation along the circle
    alpha : precision of the off-plane weight noise
    beta : observation-noise precision
    seed : seed of ``np.random.default_rng``

    Returns
    -------
    Demonstrations
        Labels ``"0"`` to ``"3"`` (cluster index); ``metadata`` holds ``b``
        (d,), ``subspace`` U (d, 2), ``centres`` (4, d), ``coords`` (L, 2)
        (plane coordinates c), ``cluster`` (L,) int, ``w`` (L, d), ``alpha``,
        ``beta`` and ``num_basis``.
    """
    name = "clusters"
    L = _check_int(name, "L", L, 4)
    D = _check_int(name, "D", D, 1)
    J = _check_int(name, "J", J, 2)
    T = _check_int(name, "T", T, 2)
    radius = _check_positive(name, "radius", radius)
    spread = _check_positive(name, "spread", spread)
    alpha = _check_positive(name, "alpha", alpha)
    beta = _check_positive(name, "beta", beta)
    seed = _check_seed(name, seed)
    d = D * J
    if d < 6:
        raise DataError(f"synthetic:{name}: the weight space needs D * J >= 6, got {d}")
    rng = np.random.default_rng(seed)
    b = rng.standard_normal(d)
    subspace, _ = np.linalg.qr(rng.standard_normal((d, 2)))
    angles = np.arange(4) * np.pi / 2
    radial = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    tangent = np.stack([-np.sin(angles), np.cos(angles)], axis=1)
    cluster = np.arange(L) % 4
    along, across = rng.standard_normal((2, L))
    coords = (
        radius * radial[cluster]
        + spread * along[:, None] * tangent[cluster]
        + 0.25 * spread * across[:, None] * radial[cluster]
    )
    w = b + coords @ subspace.T + rng.standard_normal((L, d)) / np.sqrt(alpha)
    phase = np.linspace(0.0, 1.0, T)
    y = _trajectories(phase, w, D, J) + rng.standard_normal((L, T, D)) / np.sqrt(beta)
    params = dict(L=L, D=D, J=J, T=T, radius=radius, spread=spread, alpha=alpha, beta=beta, seed=seed)
    return Demonstrations(
        times=tuple(phase for _ in range(L)),
        positions=tuple(y),
        labels=cluster.astype(str),
        name=f"synthetic:{name}?{_query(params)}",
        metadata={
            "b": b,
            "subspace": subspace,
            "centres": b + radius * radial @ subspace.T,
            "coords": coords,
            "cluster": cluster,
            "w": w,
            "alpha": np.asarray(alpha),
            "beta": np.asarray(beta),
            "num_basis": np.asarray(J),
        },
    )


def _quaternion(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) of a yaw about z followed by a pitch about y."""
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    # (cy, 0, 0, sy) * (cp, 0, sp, 0) (Hamilton product)
    return np.stack([cy * cp, -sy * sp, cy * sp, cp * sy], axis=-1)


def obstacle_reaching(
    L: int = 20,
    T: int = 100,
    radius: float = 0.08,
    noise: float = 0.002,
    seed: int = 0,
) -> Demonstrations:
    r"""A bimodal reaching task around a spherical obstacle, in 7 dimensions.

    In the spirit of thesis Sec. 5.4 (Fig. 5.2): an end effector moves from
    near the start :math:`(0, 0, 0)` to a goal near :math:`(0.6, 0, 0)` (metres;
    x forward, y left, z up) while a sphere of radius ``radius`` centred at
    :math:`(0.3, 0, 0)` blocks the straight line.  Each demonstration passes
    the obstacle either on the left (:math:`y > 0`) or on the right, with a
    random clearance of 3 to 8 cm, along a minimum-jerk time profile
    :math:`\sigma(\tau) = 10\tau^3 - 15\tau^4 + 6\tau^5`:

    .. math::

        \mathbf p(\tau) = \mathbf s + (\mathbf g - \mathbf s)\sigma
            + a (1 - (2\sigma - 1)^4) \mathbf e_y + 0.05 \sin(\pi\sigma) \mathbf e_z,

    where the lateral amplitude :math:`a` puts the mid-point at
    :math:`\pm(r + \text{clearance})` beside the obstacle centre and the
    flat-topped profile keeps the path there while it passes the obstacle.  The
    orientation is the unit quaternion (w, x, y, z) of a yaw that turns
    smoothly towards the goal's heading with a side-dependent swing and a
    small pitch.  Positions get Gaussian noise of s.d. ``noise``; the
    quaternions stay exactly unit-norm.  Durations vary between 1.8 and 2.2 s.

    Parameters
    ----------
    L : number of demonstrations (>= 2); half pass left, half right (shuffled)
    T : samples per demonstration (>= 2)
    radius : obstacle radius (between 0 and 0.12 m)
    noise : standard deviation of the position noise (>= 0)
    seed : seed of ``np.random.default_rng``

    Returns
    -------
    Demonstrations
        DoF ``x, y, z, qw, qx, qy, qz``; labels ``"left"``/``"right"``;
        ``metadata`` holds ``obstacle_centre`` (3,), ``obstacle_radius``,
        ``start`` (L, 3), ``goal`` (L, 3), ``clearance`` (L,) and ``side``
        (L,) (+1 left, -1 right).  Use :func:`count_collisions`.
    """
    name = "reaching"
    L = _check_int(name, "L", L, 2)
    T = _check_int(name, "T", T, 2)
    radius = _check_positive(name, "radius", radius)
    if radius > 0.12:
        raise DataError(f"synthetic:{name}: radius must be at most 0.12, got {radius}")
    if isinstance(noise, bool) or not isinstance(noise, (int, float, np.floating, np.integer)) or not (
        np.isfinite(noise) and noise >= 0
    ):
        raise DataError(f"synthetic:{name}: noise must be a finite number >= 0, got {noise!r}")
    noise = float(noise)
    seed = _check_seed(name, seed)
    rng = np.random.default_rng(seed)
    centre = np.array([0.3, 0.0, 0.0])
    side = np.where(rng.permutation(np.arange(L) % 2) == 0, 1.0, -1.0)
    start = rng.uniform(-0.02, 0.02, (L, 3)) * np.array([1.0, 1.0, 0.0])
    goal = np.array([0.6, 0.0, 0.0]) + rng.uniform(-1.0, 1.0, (L, 3)) * np.array([0.05, 0.1, 0.0])
    clearance = rng.uniform(0.03, 0.08, L)
    duration = rng.uniform(1.8, 2.2, L)
    swing = rng.uniform(0.2, 0.4, L)
    tau = np.linspace(0.0, 1.0, T)
    sigma = 10 * tau**3 - 15 * tau**4 + 6 * tau**5
    bump = np.sin(np.pi * sigma)
    # flat-topped lateral profile: stays near its peak while passing the obstacle
    plateau = 1.0 - (2.0 * sigma - 1.0) ** 4
    times, positions = [], []
    for i in range(L):
        # mid-point of the straight line is (start + goal) / 2; shift it to side * (radius + clearance)
        lateral = side[i] * (radius + clearance[i]) - 0.5 * (start[i, 1] + goal[i, 1])
        path = start[i] + np.outer(sigma, goal[i] - start[i])
        path[:, 1] += lateral * plateau
        path[:, 2] += 0.05 * bump
        path += noise * rng.standard_normal((T, 3))
        heading = np.arctan2(goal[i, 1] - start[i, 1], goal[i, 0] - start[i, 0])
        yaw = heading * sigma + side[i] * swing[i] * bump
        pitch = 0.2 * bump
        positions.append(np.concatenate([path, _quaternion(yaw, pitch)], axis=1))
        times.append(duration[i] * tau)
    params = dict(L=L, T=T, radius=radius, noise=noise, seed=seed)
    return Demonstrations(
        times=tuple(times),
        positions=tuple(positions),
        labels=np.where(side > 0, "left", "right"),
        dof_names=("x", "y", "z", "qw", "qx", "qy", "qz"),
        name=f"synthetic:{name}?{_query(params)}",
        metadata={
            "obstacle_centre": centre,
            "obstacle_radius": np.asarray(radius),
            "start": start,
            "goal": goal,
            "clearance": clearance,
            "side": side,
        },
    )


def count_collisions(positions: Sequence[ArrayLike] | ArrayLike, metadata: dict) -> int:
    """Number of trajectories that enter the obstacle of :func:`obstacle_reaching`.

    A trajectory collides when any straight segment between consecutive
    samples comes closer to ``metadata["obstacle_centre"]`` than
    ``metadata["obstacle_radius"]`` (so a coarse sampling cannot step over
    the obstacle).

    Parameters
    ----------
    positions : sequence of (T_i, >= 3) arrays, or an (L, T, >= 3) / (T, >= 3) array
        Trajectories whose first three columns are x, y, z (e.g.
        ``demos.positions`` or predicted mean trajectories).
    metadata : dict with ``obstacle_centre`` (3,) and ``obstacle_radius``
    """
    try:
        centre = np.asarray(metadata["obstacle_centre"], dtype=np.float64).reshape(3)
        radius = float(metadata["obstacle_radius"])
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"metadata has no obstacle_centre (3,) and obstacle_radius: {exc}") from None
    if isinstance(positions, np.ndarray) and positions.ndim == 2:
        positions = [positions]
    count = 0
    for k, trajectory in enumerate(positions):
        p = np.asarray(trajectory, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] < 3:
            raise DataError(f"trajectory {k} must have shape (T, >= 3), got {p.shape}")
        p = p[:, :3]
        start, step = p[:-1], np.diff(p, axis=0)
        length2 = np.sum(step**2, axis=1)
        u = np.clip(np.sum((centre - start) * step, axis=1) / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
        closest = np.concatenate([start + u[:, None] * step, p[-1:]], axis=0)
        count += bool(np.any(np.linalg.norm(closest - centre, axis=1) < radius))
    return count


GENERATORS: dict[str, Callable[..., Demonstrations]] = {
    "latent": latent_manifold,
    "clusters": four_clusters,
    "reaching": obstacle_reaching,
}
"""The generators behind ``synthetic:<name>``."""

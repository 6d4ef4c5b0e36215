"""Inverse kinematics: joint angles that put the tip (flange) at a given pose.

Damped least squares (Levenberg-Marquardt, optimistix) on the pose residual

    r(q) = [p(q) - p*;  log(R*^T R(q))]     (metres; radians, the SO(3) log map),

from several starts at once (``vmap``): the given start ``q0`` and further starts spread
over the joint ranges. Each solution's revolute angles are shifted by multiples of 2 pi
into the joint limits where that is possible (KUKA A4/A6 span 700 deg), and the solution
closest to ``q0`` in joint travel time (``sum ((q - q0) / v_max)^2``) among those that
reach the pose within the limits is returned.

Reachability is reported, never hidden: the result says whether the pose was reached and
``limit_excess`` by how much each joint would leave its range; :func:`reach_distance` is
the smallest distance from the target position to any flange position the arm can reach
(a position-only solve with the same compiled solver, orientation and limits ignored).
:func:`solve_ik` raises a ``ValueError`` naming the pose and the distance out of reach;
inside ``jit`` use :func:`inverse_kinematics` and read the result's fields.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float

from .chain import KinematicChain
from .kinematics import forward_kinematics

__all__ = [
    "IKResult",
    "describe_pose",
    "inverse_kinematics",
    "pose_residual",
    "reach_distance",
    "require_reachable",
    "solve_ik",
]


class IKResult(eqx.Module):
    """An inverse-kinematics solution and how well it reaches the target.

    Attributes:
        q: (n,) the configuration [rad] (the best found, even when not a solution).
        position_error: distance of its tip from the target position [m].
        rotation_error: angle between its tip and the target orientation [rad].
        reachable: the errors are below the tolerances (joint limits aside).
        within_limits: ``q`` inside every joint's range.
        success: reachable and within the limits.
        limit_excess: (n,) how far each joint of ``q`` lies outside its range [rad] (0
            inside).
        starts: (S, n) the starts of the solver (for :func:`reach_distance`).
        converged: (S,) the solver's convergence flag per start.
    """

    q: Float[Array, " n"]
    position_error: Float[Array, ""]
    rotation_error: Float[Array, ""]
    reachable: Bool[Array, ""]
    within_limits: Bool[Array, ""]
    success: Bool[Array, ""]
    limit_excess: Float[Array, " n"]
    starts: Float[Array, "S n"]
    converged: Bool[Array, " S"]


def pose_residual(
    chain: KinematicChain, q: Float[ArrayLike, " n"], T_target: Float[ArrayLike, "4 4"]
) -> Float[Array, " 6"]:
    """``[p(q) - p*; log(R*^T R(q))]`` (6,): position [m] and rotation [rad] errors."""
    T = forward_kinematics(chain, q)
    T_target = jnp.asarray(T_target, T.dtype)
    dR = T_target[:3, :3].T @ T[:3, :3]
    return jnp.concatenate([T[:3, 3] - T_target[:3, 3], jaxlie.SO3.from_matrix(dR).log()])


def _wrap_into_limits(chain: KinematicChain, q, q0):
    """Shift revolute angles by multiples of 2 pi: inside the limits if possible, then
    closest to ``q0``."""
    shifts = 2 * jnp.pi * jnp.arange(-2, 3, dtype=q.dtype)  # (5,)
    cand = q[:, None] + shifts[None, :]  # (n, 5)
    lo, hi = chain.lower[:, None], chain.upper[:, None]
    excess = jnp.maximum(lo - cand, 0) + jnp.maximum(cand - hi, 0)
    score = excess * 1e6 + jnp.abs(cand - q0[:, None])
    best = jnp.take_along_axis(cand, jnp.argmin(score, axis=1)[:, None], axis=1)[:, 0]
    revolute = jnp.asarray([t == "revolute" for t in chain.joint_types])
    return jnp.where(revolute, best, q)


def _excess(chain, q):
    return jnp.maximum(chain.lower - q, 0) + jnp.maximum(q - chain.upper, 0)


def _starts(chain: KinematicChain, q0, n_starts: int, key):
    """``q0`` and ``n_starts - 1`` starts drawn uniformly inside the joint ranges."""
    u = jax.random.uniform(key, (n_starts - 1, chain.n), q0.dtype)
    return jnp.concatenate([q0[None], chain.lower + u * (chain.upper - chain.lower)])


def _weighted_residual(chain, q, T_target, rotation_weight):
    r = pose_residual(chain, q, T_target)
    return r.at[3:].multiply(rotation_weight)


@eqx.filter_jit
def _solve_starts(chain, T_target, q_starts, rotation_weight, max_steps):
    """Levenberg-Marquardt from every start (S, n); ``rotation_weight`` 0 solves for the
    position only (one compiled program serves both)."""
    solver = optx.LevenbergMarquardt(rtol=1e-13, atol=1e-15)

    def solve(q_init):
        sol = optx.least_squares(
            lambda q, w: _weighted_residual(chain, q, T_target, w),
            solver,
            q_init,
            args=rotation_weight,
            max_steps=max_steps,
            throw=False,
        )
        return sol.value, sol.result == optx.RESULTS.successful

    return jax.vmap(solve)(q_starts)


def inverse_kinematics(
    chain: KinematicChain,
    T_target: Float[ArrayLike, "4 4"],
    q0: Float[ArrayLike, " n"] | None = None,
    *,
    starts: int = 8,
    key: Array | None = None,
    position_tol: float = 1e-9,
    rotation_tol: float = 1e-9,
    max_steps: int = 100,
) -> IKResult:
    """Joint angles whose tip pose ``FK(q)`` equals ``T_target`` (4, 4) (base frame).

    Args:
        chain: the robot.
        T_target: (4, 4) target tip (flange) pose in the base frame.
        q0: (n,) start and preferred configuration (default: mid-range).
        starts: starts in all (``q0`` plus ``starts - 1`` drawn with ``key``).
        key: PRNG key of the extra starts (default: ``PRNGKey(0)``, deterministic).
        position_tol [m], rotation_tol [rad]: the pose counts as reached below these
            (raised to 64 machine epsilons of the chain's dtype, times ``1 + |p|`` for
            the position: 1e-9 cannot be met in float32, where they are ~2e-5 m, 8e-6 rad).
        max_steps: Levenberg-Marquardt steps per start.

    Returns:
        An :class:`IKResult`. The solver is one compiled program per robot and number of
        starts (shared with :func:`reach_distance`); the function also runs inside ``jit``.
    """
    dtype = chain.origins.dtype
    T_target = jnp.asarray(T_target, dtype)
    q0 = 0.5 * (chain.lower + chain.upper) if q0 is None else jnp.asarray(q0, dtype)
    key = jax.random.PRNGKey(0) if key is None else key
    q_starts = _starts(chain, q0, starts, key)
    qs, converged = _solve_starts(chain, T_target, q_starts, jnp.ones((), dtype), max_steps)
    floor = 64 * jnp.finfo(dtype).eps
    position_tol = jnp.maximum(position_tol, floor * (1 + jnp.linalg.norm(T_target[:3, 3])))
    rotation_tol = jnp.maximum(rotation_tol, floor)
    return _select(chain, T_target, q0, qs, q_starts, converged, position_tol, rotation_tol)


@eqx.filter_jit
def _select(chain, T_target, q0, qs, q_starts, converged, position_tol, rotation_tol):
    """The best solution: shifted into the limits, reached, inside, least travel."""
    qs = jax.vmap(lambda q: _wrap_into_limits(chain, q, q0))(qs)
    res = jax.vmap(lambda q: pose_residual(chain, q, T_target))(qs)
    pos_err = jnp.linalg.norm(res[:, :3], axis=1)
    rot_err = jnp.linalg.norm(res[:, 3:], axis=1)
    reached = (pos_err <= position_tol) & (rot_err <= rotation_tol)
    excess = jax.vmap(lambda q: _excess(chain, q))(qs)
    inside = jnp.all(excess == 0, axis=1)
    travel = jnp.sum(((qs - q0) / chain.velocity) ** 2, axis=1)
    # rank: reached within limits, then reached, then by error; ties by travel time
    score = jnp.where(
        reached & inside,
        travel,
        jnp.where(reached, 1e6 + jnp.sum(excess, axis=1), 1e12 + pos_err + rot_err),
    )
    i = jnp.argmin(score)
    return IKResult(
        q=qs[i],
        position_error=pos_err[i],
        rotation_error=rot_err[i],
        reachable=reached[i],
        within_limits=inside[i],
        success=reached[i] & inside[i],
        limit_excess=excess[i],
        starts=q_starts,
        converged=converged,
    )


def reach_distance(
    chain: KinematicChain, T_target: Float[ArrayLike, "4 4"], q_starts: Float[ArrayLike, "S n"]
) -> Float[Array, ""]:
    """Distance [m] from the target position to the closest flange position the arm
    reaches from the given starts (orientation and joint limits ignored; ~0 when the
    position is reachable): how far a pose lies out of reach."""
    dtype = chain.origins.dtype
    T_target = jnp.asarray(T_target, dtype)
    qs, _ = _solve_starts(chain, T_target, jnp.asarray(q_starts, dtype), jnp.zeros((), dtype), 100)
    res = jax.vmap(lambda q: pose_residual(chain, q, T_target)[:3])(qs)
    return jnp.min(jnp.linalg.norm(res, axis=1))


def describe_pose(T: Float[ArrayLike, "4 4"]) -> str:
    """A pose as ``X, Y, Z [mm]; A, B, C [deg]`` (KUKA intrinsic Z-Y'-X'') for messages."""
    T = np.asarray(T, float)
    R = T[:3, :3]
    a = np.degrees(np.arctan2(R[1, 0], R[0, 0]))
    b = np.degrees(np.arctan2(-R[2, 0], np.hypot(R[0, 0], R[1, 0])))
    c = np.degrees(np.arctan2(R[2, 1], R[2, 2]))
    x, y, z = 1000 * T[:3, 3]
    return f"X {x:.1f} Y {y:.1f} Z {z:.1f} mm, A {a:.1f} B {b:.1f} C {c:.1f} deg"


def require_reachable(
    result: IKResult, chain: KinematicChain, T_target: Float[ArrayLike, "4 4"], what: str = "pose"
) -> None:
    """Raise ``ValueError`` unless ``result`` reaches ``T_target`` within the joint limits.

    The message names ``what`` (e.g. ``"start pose"``), the pose, and either the distance
    out of reach or the joints whose ranges the pose needs to leave (host side).
    """
    if bool(result.success):
        return
    pose = describe_pose(T_target)
    if not bool(result.reachable):
        reach = float(reach_distance(chain, T_target, result.starts))
        if reach > 1e-6:
            raise ValueError(
                f"{what}: {pose} is out of reach of {chain.name}: the position lies "
                f"{1000 * reach:.1f} mm beyond the positions the flange can reach"
            )
        raise ValueError(
            f"{what}: {pose} is not reachable by {chain.name} in this orientation (closest: "
            f"{1000 * float(result.position_error):.3f} mm and "
            f"{np.degrees(float(result.rotation_error)):.3f} deg away)"
        )
    q = np.degrees(np.asarray(result.q))
    lo, hi = np.degrees(np.asarray(chain.lower)), np.degrees(np.asarray(chain.upper))
    bad = [
        f"{chain.joint_names[j]} = {q[j]:.1f} deg (limits {lo[j]:.0f} .. {hi[j]:.0f})"
        for j in np.flatnonzero(np.asarray(result.limit_excess) > 0)
    ]
    raise ValueError(
        f"{what}: {pose} is reachable by {chain.name} only outside its joint limits: "
        + ", ".join(bad)
    )


def solve_ik(
    chain: KinematicChain,
    T_target: Float[ArrayLike, "4 4"],
    q0: Float[ArrayLike, " n"] | None = None,
    *,
    what: str = "pose",
    **kwargs,
) -> Array:
    """:func:`inverse_kinematics` for one pose on the host: the configuration (n,), or a
    ``ValueError`` naming ``what``, the pose and why it cannot be reached."""
    T_target = np.asarray(T_target, float)
    if T_target.shape != (4, 4) or not np.all(np.isfinite(T_target)):
        raise ValueError(f"{what}: expected a finite (4, 4) pose, got shape {T_target.shape}")
    result = inverse_kinematics(chain, T_target, q0, **kwargs)
    require_reachable(result, chain, T_target, what)
    return result.q

"""A serial kinematic chain: the plain description the JAX kinematics consume.

A chain is what a URDF says about the joints between a base link and a tip link, with the
fixed joints folded in: for joint ``i``, the fixed transform ``origins[i]`` from the
previous joint's moving frame to this joint's frame, its unit axis ``axes[i]`` and its
type; then the fixed transform ``tip`` to the tip frame (the flange). Parsing URDF files is
the edge's job (:func:`jaxtraj.io.urdf.read_urdf`); the core never reads files.

Joint limits: position (``lower``, ``upper`` [rad or m]) and speed (``velocity``) are the
datasheet's (URDF's); acceleration and jerk are not published by robot makers and default
to the documented assumptions of :mod:`.limits` (override with :meth:`KinematicChain.with_limits`).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .limits import default_acceleration, default_jerk

__all__ = ["JOINT_TYPES", "KinematicChain", "kinematic_chain"]

JOINT_TYPES = ("revolute", "prismatic")


class KinematicChain(eqx.Module):
    """A serial chain of ``n`` one-axis joints from a base frame to a tip frame.

    Attributes:
        origins: (n, 4, 4) ``T_prev_joint``: joint ``i``'s frame in the previous joint's
            moving frame (the base frame for joint 0), fixed joints folded in.
        axes: (n, 3) unit joint axes in the joint frames.
        tip: (4, 4) the tip frame in the last joint's moving frame.
        lower, upper: (n,) position limits [rad or m].
        velocity: (n,) speed limits [rad/s or m/s] (datasheet).
        acceleration: (n,) acceleration limits [rad/s^2] (assumed unless given).
        jerk: (n,) jerk limits [rad/s^3] (assumed unless given).
        name: the robot's name; joint_names: (n,) joint names; joint_types: (n,) each
            ``"revolute"`` or ``"prismatic"`` (static).
    """

    origins: Float[Array, "n 4 4"]
    axes: Float[Array, "n 3"]
    tip: Float[Array, "4 4"]
    lower: Float[Array, " n"]
    upper: Float[Array, " n"]
    velocity: Float[Array, " n"]
    acceleration: Float[Array, " n"]
    jerk: Float[Array, " n"]
    name: str = eqx.field(static=True)
    joint_names: tuple[str, ...] = eqx.field(static=True)
    joint_types: tuple[str, ...] = eqx.field(static=True)

    @property
    def n(self) -> int:
        """Number of joints."""
        return len(self.joint_names)

    def with_limits(
        self,
        *,
        lower: Float[ArrayLike, " n"] | None = None,
        upper: Float[ArrayLike, " n"] | None = None,
        velocity: Float[ArrayLike, " n"] | None = None,
        acceleration: Float[ArrayLike, " n"] | None = None,
        jerk: Float[ArrayLike, " n"] | None = None,
    ) -> KinematicChain:
        """The same chain with some limits replaced (each (n,), SI units, radians)."""
        new = {
            "lower": lower,
            "upper": upper,
            "velocity": velocity,
            "acceleration": acceleration,
            "jerk": jerk,
        }
        values = {}
        for key, value in new.items():
            old = getattr(self, key)
            values[key] = old if value is None else _limit_array(key, value, self.n, old.dtype)
        _check_limits(values["lower"], values["upper"], values)
        return eqx.tree_at(
            lambda c: (c.lower, c.upper, c.velocity, c.acceleration, c.jerk),
            self,
            tuple(values[k] for k in new),
        )

    def within_limits(self, q: Float[ArrayLike, " n"], tol: float = 0.0) -> Array:
        """Whether the configuration ``q`` is inside the position limits (+ ``tol``)."""
        q = jnp.asarray(q)
        return jnp.all((q >= self.lower - tol) & (q <= self.upper + tol), axis=-1)

    def outside_limits(self, q: Float[ArrayLike, "... n"], tol: float = 0.0) -> np.ndarray:
        """Indices (k, q.ndim) of the values of ``q`` outside the position limits by more
        than ``tol``, in order (host side; the last index is the axis): what an error
        message names."""
        q = np.asarray(q)
        lo, hi = np.asarray(self.lower), np.asarray(self.upper)
        return np.argwhere((q < lo - tol) | (q > hi + tol))


def _limit_array(name: str, value, n: int, dtype) -> Array:
    arr = np.asarray(value, dtype=float)
    if arr.shape != (n,):
        raise ValueError(f"{name}: expected shape ({n},) (one value per joint), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: expected finite values, got {arr.tolist()}")
    return jnp.asarray(arr, dtype)


def _check_limits(lower, upper, values) -> None:
    lo, hi = np.asarray(lower), np.asarray(upper)
    if np.any(lo >= hi):
        j = int(np.flatnonzero(lo >= hi)[0])
        raise ValueError(f"lower, upper: joint {j} has lower {lo[j]} >= upper {hi[j]}")
    for key in ("velocity", "acceleration", "jerk"):
        v = np.asarray(values[key])
        if np.any(v <= 0):
            raise ValueError(f"{key}: limits must be > 0, got {v.tolist()}")


def kinematic_chain(
    name: str,
    joint_names: tuple[str, ...] | list[str],
    origins: Float[ArrayLike, "n 4 4"],
    axes: Float[ArrayLike, "n 3"],
    tip: Float[ArrayLike, "4 4"],
    lower: Float[ArrayLike, " n"],
    upper: Float[ArrayLike, " n"],
    velocity: Float[ArrayLike, " n"],
    acceleration: Float[ArrayLike, " n"] | None = None,
    jerk: Float[ArrayLike, " n"] | None = None,
    joint_types: tuple[str, ...] | list[str] | None = None,
    dtype=None,
) -> KinematicChain:
    """Build and check a :class:`KinematicChain` (host side).

    Args:
        name: the robot's name.
        joint_names: (n,) joint names (KUKA: A1..A6).
        origins: (n, 4, 4) fixed transforms ``T_prev_joint`` (rigid: rotation part
            orthonormal).
        axes: (n, 3) joint axes (normalised here; must be non-zero).
        tip: (4, 4) tip frame in the last joint's moving frame.
        lower, upper, velocity: (n,) position [rad] and speed [rad/s] limits.
        acceleration, jerk: (n,) limits; default: the assumptions of
            :func:`~jaxtraj.robot.limits.default_acceleration` and
            :func:`~jaxtraj.robot.limits.default_jerk`.
        joint_types: (n,) ``"revolute"`` (default) or ``"prismatic"``.
        dtype: float dtype of the arrays (default: float64 if enabled, else float32).
    """
    joint_names = tuple(str(j) for j in joint_names)
    n = len(joint_names)
    if n == 0:
        raise ValueError("joint_names: a chain needs at least one joint, got none")
    joint_types = ("revolute",) * n if joint_types is None else tuple(joint_types)
    if len(joint_types) != n or any(t not in JOINT_TYPES for t in joint_types):
        raise ValueError(f"joint_types: expected {n} of {JOINT_TYPES}, got {joint_types}")
    dtype = jnp.zeros(0).dtype if dtype is None else dtype
    origins = np.asarray(origins, dtype=float)
    if origins.shape != (n, 4, 4):
        raise ValueError(f"origins: expected shape ({n}, 4, 4), got {origins.shape}")
    tip = np.asarray(tip, dtype=float)
    if tip.shape != (4, 4):
        raise ValueError(f"tip: expected shape (4, 4), got {tip.shape}")
    for label, T in [*((f"origins[{i}]", o) for i, o in enumerate(origins)), ("tip", tip)]:
        R = T[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-9) or not np.allclose(T[3], [0, 0, 0, 1]):
            raise ValueError(f"{label}: expected a rigid transform (orthonormal rotation)")
    axes = np.asarray(axes, dtype=float)
    if axes.shape != (n, 3):
        raise ValueError(f"axes: expected shape ({n}, 3), got {axes.shape}")
    norms = np.linalg.norm(axes, axis=1)
    if np.any(norms < 1e-12):
        raise ValueError(f"axes: joint {int(np.argmin(norms))} has a zero axis")
    axes = axes / norms[:, None]
    velocity = _limit_array("velocity", velocity, n, dtype)
    values = {
        "velocity": velocity,
        "acceleration": default_acceleration(velocity)
        if acceleration is None
        else _limit_array("acceleration", acceleration, n, dtype),
    }
    if jerk is None:
        values["jerk"] = default_jerk(values["acceleration"])
    else:
        values["jerk"] = _limit_array("jerk", jerk, n, dtype)
    lower = _limit_array("lower", lower, n, dtype)
    upper = _limit_array("upper", upper, n, dtype)
    _check_limits(lower, upper, values)
    return KinematicChain(
        origins=jnp.asarray(origins, dtype),
        axes=jnp.asarray(axes, dtype),
        tip=jnp.asarray(tip, dtype),
        lower=lower,
        upper=upper,
        velocity=values["velocity"],
        acceleration=jnp.asarray(values["acceleration"], dtype),
        jerk=jnp.asarray(values["jerk"], dtype),
        name=str(name),
        joint_names=joint_names,
        joint_types=joint_types,
    )

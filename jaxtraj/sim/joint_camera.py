"""A camera carried along a sampled joint path, as a smooth JAX trajectory.

A designed path (``jaxtraj design``'s ``joint_path.csv``: times and axis values) is a
sequence of configurations; the simulation needs the camera pose at every IMU sample
and its first and second time derivatives. :func:`cubic_spline` interpolates the samples
with a natural cubic spline (continuous acceleration, so the simulated accelerometer
sees no jumps inside the path) and continues linearly beyond the ends (the IMU and the
robot log start before the first image and end after the last); :func:`joint_path_camera`
maps it through forward kinematics to the camera pose ``T_w_c = T_w_base FK(q(t)) T_f_c``.

Pure JAX (no file access): the samples come in as arrays.
"""

from __future__ import annotations

from collections.abc import Callable

import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import ArrayLike, Float

from ..robot.chain import KinematicChain
from ..robot.kinematics import camera_pose

__all__ = ["cubic_spline", "joint_path_camera"]


def _second_derivatives(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Second derivatives (N, ...) of the natural cubic spline through ``(t_i, y_i)``."""
    n = len(t)
    h = np.diff(t)
    M = np.zeros_like(y)
    if n < 3:
        return M
    A = np.zeros((n - 2, n - 2))
    i = np.arange(n - 2)
    A[i, i] = (h[:-1] + h[1:]) / 3.0
    A[i[1:], i[1:] - 1] = h[1:-1] / 6.0
    A[i[:-1], i[:-1] + 1] = h[1:-1] / 6.0
    slope = np.diff(y, axis=0) / h.reshape((-1,) + (1,) * (y.ndim - 1))
    M[1:-1] = np.linalg.solve(A, (slope[1:] - slope[:-1]).reshape(n - 2, -1)).reshape(
        slope[1:].shape
    )
    return M


def cubic_spline(
    t: Float[ArrayLike, " N"], y: Float[ArrayLike, "N ..."]
) -> Callable[[Float[ArrayLike, ""]], jnp.ndarray]:
    """The natural cubic spline through the samples ``(t_i, y_i)`` as a JAX callable.

    Between the samples it has continuous first and second derivatives (zero second
    derivative at the ends); before the first and after the last sample it continues
    along the end tangent. The callable takes a scalar time and is differentiable in it
    (``jax.jacfwd`` twice gives the acceleration).

    Args:
        t: (N,) strictly increasing sample times, N >= 2.
        y: (N, ...) values.

    Raises:
        ValueError: fewer than two samples, times not strictly increasing, or shapes
            that disagree.
    """
    t = np.asarray(t, float)
    y = np.asarray(y, float)
    if t.ndim != 1 or t.size < 2 or y.shape[:1] != t.shape:
        raise ValueError(
            f"t, y: expected (N,) times and (N, ...) values with N >= 2, got {t.shape}, {y.shape}"
        )
    if np.any(np.diff(t) <= 0):
        raise ValueError("t: expected strictly increasing times")
    M = jnp.asarray(_second_derivatives(t, y))
    tk, yk = jnp.asarray(t), jnp.asarray(y)
    n = t.size

    def spline(s):
        u = jnp.clip(s, tk[0], tk[-1])
        i = jnp.clip(jnp.searchsorted(tk, u, side="right") - 1, 0, n - 2)
        h = tk[i + 1] - tk[i]
        a, b = (tk[i + 1] - u) / h, (u - tk[i]) / h
        curve = (a**3 - a) * M[i] + (b**3 - b) * M[i + 1]
        value = a * yk[i] + b * yk[i + 1] + curve * h**2 / 6
        bend = (1 - 3 * a**2) * M[i] + (3 * b**2 - 1) * M[i + 1]
        slope = (yk[i + 1] - yk[i]) / h + bend * h / 6
        return value + slope * (s - u)

    return spline


def joint_path_camera(
    chain: KinematicChain,
    times: Float[ArrayLike, " N"],
    q: Float[ArrayLike, "N n"],
    T_f_c: Float[ArrayLike, "4 4"],
    T_w_base: Float[ArrayLike, "4 4"] | None = None,
) -> Callable:
    """The camera trajectory ``t -> (p_w_c (3,), q_w_c (4,) wxyz)`` of a robot moving
    through the sampled configurations ``q`` (joints interpolated by :func:`cubic_spline`).

    Args:
        chain: the camera robot.
        times: (N,) strictly increasing times [s].
        q: (N, n) joint values [rad, m].
        T_f_c: (4, 4) the camera in the flange (hand-eye).
        T_w_base: (4, 4) the robot base in the world; default identity.
    """
    q = np.asarray(q, float)
    if q.ndim != 2 or q.shape[1] != chain.n:
        raise ValueError(f"q: expected (N, {chain.n}) joint values, got {q.shape}")
    joints = cubic_spline(times, q)
    T_f_c = jnp.asarray(T_f_c, float)
    T_w_base = jnp.eye(4) if T_w_base is None else jnp.asarray(T_w_base, float)

    def trajectory(t):
        T = camera_pose(chain, joints(t), T_f_c, T_w_base)
        return T[:3, 3], jaxlie.SO3.from_matrix(T[:3, :3]).wxyz

    return trajectory

"""Poses at arbitrary times on SE(3), camera poses and projection matrices.

Between two stored poses ``T_a`` (time ``t_a``) and ``T_b`` the pose at ``t`` is the
geodesic ``T_a Exp(s Log(T_a^-1 T_b))``, ``s = (t - t_a) / (t_b - t_a)``; times outside
the stored span are clamped to the first/last pose. The filter stores a state at every
IMU sample (and at every image event when the image times were put into the stream, in
which case the answer at those times is exact).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
from jaxtyping import Array, ArrayLike, Float

from .._checks import check_finite, check_shape
from ..camera import projection_matrix
from .eskf import FusionResult
from .events import identity_se3

__all__ = ["camera_poses_at", "interpolate_poses", "projection_matrices"]


def interpolate_poses(
    t: Float[ArrayLike, " K"],
    p: Float[ArrayLike, "K 3"],
    q: Float[ArrayLike, "K 4"],
    times: Float[ArrayLike, " F"],
) -> tuple[Float[Array, "F 3"], Float[Array, "F 4"]]:
    """Poses ``(p, q)`` (``T_w_x``) at ``times`` by SE(3) geodesic interpolation.

    Args:
        t: (K,) non-decreasing times of the known poses [s] (repeated times: the last
            pose with that time wins).
        p, q: (K, 3) positions [m] and (K, 4) quaternions (w, x, y, z).
        times: (F,) query times [s], any order; clamped to ``[t[0], t[-1]]``.

    Returns:
        ``(p, q)`` with shapes (F, 3), (F, 4).
    """
    check_shape("t", t, (None,), "times of the known poses")
    k = jnp.shape(t)[0]
    check_shape("p", p, (k, 3), "positions of the known poses")
    check_shape("q", q, (k, 4), "quaternions (w, x, y, z) of the known poses")
    check_shape("times", times, (None,), "query times")
    check_finite("times", times)
    return _interpolate(jnp.asarray(t), jnp.asarray(p), jnp.asarray(q), jnp.asarray(times))


@jax.jit
def _interpolate(t, p, q, times):
    k = t.shape[0]
    times = times.astype(t.dtype)
    i = jnp.clip(jnp.searchsorted(t, times, side="right") - 1, 0, k - 1)
    j = jnp.minimum(i + 1, k - 1)
    span = t[j] - t[i]
    s = jnp.clip(jnp.where(span > 0, (times - t[i]) / jnp.where(span > 0, span, 1.0), 0.0), 0, 1)
    T = jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3(q), p)
    Ta = jax.tree_util.tree_map(lambda a: a[i], T)
    Tb = jax.tree_util.tree_map(lambda a: a[j], T)
    delta = (Ta.inverse() @ Tb).log()
    Ts = Ta @ jaxlie.SE3.exp(s[:, None] * delta)
    return Ts.translation(), Ts.rotation().wxyz


def camera_poses_at(
    result: FusionResult,
    times: Float[ArrayLike, " F"],
    T_i_c: jaxlie.SE3 | None = None,
) -> tuple[Float[Array, "F 3 3"], Float[Array, "F 3"]]:
    """Camera poses ``(R_c_w, t_c_w)`` at ``times`` from a filtered or smoothed stream.

    ``T_w_c = T_w_i T_i_c`` with ``T_w_i`` interpolated on SE(3); the returned world-to-
    camera form is what :func:`jaxtraj.projection_matrix` and the reconstruction take.

    Args:
        result: a :class:`~jaxtraj.fusion.FusionResult` for one stream.
        times: (F,) image times on the IMU clock [s].
        T_i_c: the camera in the IMU frame; identity if None.

    Returns:
        ``R_c_w`` (F, 3, 3) and ``t_c_w`` (F, 3) with ``x_c = R_c_w x_w + t_c_w``.
    """
    if result.t.ndim != 1:
        raise ValueError(f"result: expected one stream (E,), got t of shape {result.t.shape}")
    p, q = interpolate_poses(result.t, result.x.p, result.x.q, times)
    return _camera_from_imu(p, q, identity_se3(p.dtype) if T_i_c is None else T_i_c)


@jax.jit
def _camera_from_imu(p, q, T_i_c):
    T_w_i = jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3(q), p)
    T_c_w = (T_w_i @ T_i_c).inverse()
    return T_c_w.rotation().as_matrix(), T_c_w.translation()


def projection_matrices(
    result: FusionResult,
    times: Float[ArrayLike, " F"],
    K: Float[ArrayLike, "3 3"],
    T_i_c: jaxlie.SE3 | None = None,
) -> Float[Array, "F 3 4"]:
    """The (F, 3, 4) projection matrices ``K [R_c_w | t_c_w]`` at the image ``times``
    (see :func:`camera_poses_at`); the input of :func:`jaxtraj.reconstruct`."""
    check_shape("K", K, (3, 3), "camera matrix")
    R_c_w, t_c_w = camera_poses_at(result, times, T_i_c)
    K = jnp.asarray(K, R_c_w.dtype)
    return jax.vmap(lambda R, t: projection_matrix(K, R, t))(R_c_w, t_c_w)

"""Pinhole camera with OpenCV's distortion model.

Conventions (OpenCV): camera frame x right, y down, z forward; pixel (0, 0) is the
centre of the top-left pixel. ``R_c_w, t_c_w`` map world points into the camera frame,
``x_c = R_c_w x_w + t_c_w``. Distortion coefficients are ``(k1, k2, p1, p2[, k3])``.

All functions work on one camera; batch with ``jax.vmap``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

__all__ = [
    "camera_centre",
    "distort",
    "look_at",
    "project",
    "projection_matrix",
    "undistort_points",
]


def projection_matrix(
    K: Float[ArrayLike, "3 3"], R_c_w: Float[ArrayLike, "3 3"], t_c_w: Float[ArrayLike, " 3"]
) -> Float[Array, "3 4"]:
    """The 3x4 projection matrix ``P = K [R_c_w | t_c_w]`` of an undistorted camera."""
    K, R_c_w, t_c_w = jnp.asarray(K), jnp.asarray(R_c_w), jnp.asarray(t_c_w)
    return K @ jnp.concatenate([R_c_w, t_c_w[:, None]], axis=1)


def camera_centre(P: Float[ArrayLike, "3 4"]) -> Float[Array, " 3"]:
    """The camera centre C with ``P [C; 1] = 0`` (assumes a finite camera).

    ``C = -M^-1 p4`` by the adjugate of ``M = P[:, :3]`` (cross products of its rows): no
    LAPACK call, so it stays cheap inside vmapped, jit-compiled programs."""
    P = jnp.asarray(P)
    m1, m2, m3 = P[0, :3], P[1, :3], P[2, :3]
    a1, a2, a3 = jnp.cross(m2, m3), jnp.cross(m3, m1), jnp.cross(m1, m2)
    return -(P[0, 3] * a1 + P[1, 3] * a2 + P[2, 3] * a3) / jnp.dot(m1, a1)


def look_at(
    position_w: Float[ArrayLike, " 3"],
    target_w: Float[ArrayLike, " 3"],
    up_w: Float[ArrayLike, " 3"] = (0.0, 0.0, 1.0),
) -> tuple[Float[Array, "3 3"], Float[Array, " 3"]]:
    """Pose ``(R_c_w, t_c_w)`` of a camera at ``position_w`` whose optical axis (z) points
    at ``target_w``; image y points along ``-up_w`` projected on the image plane.

    ``up_w`` must not be parallel to the viewing direction.
    """
    position_w = jnp.asarray(position_w)
    target_w = jnp.asarray(target_w, position_w.dtype)
    up_w = jnp.asarray(up_w, position_w.dtype)
    z = target_w - position_w
    z = z / jnp.linalg.norm(z)
    x = jnp.cross(z, up_w)  # image x to the right when y points down
    x = x / jnp.linalg.norm(x)
    y = jnp.cross(z, x)
    R_w_c = jnp.stack([x, y, z], axis=1)
    R_c_w = R_w_c.T
    return R_c_w, -R_c_w @ position_w


def distort(xy: Float[ArrayLike, "*n 2"], dist: Float[ArrayLike, " d"]) -> Float[Array, "*n 2"]:
    """Apply OpenCV's radial-tangential distortion to normalised image coordinates."""
    xy = jnp.asarray(xy)
    dist = jnp.asarray(dist, xy.dtype)
    d = jnp.zeros(5, xy.dtype).at[: dist.shape[0]].set(dist[:5])
    k1, k2, p1, p2, k3 = d
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return jnp.stack([xd, yd], axis=-1)


def project(
    K: Float[ArrayLike, "3 3"],
    R_c_w: Float[ArrayLike, "3 3"],
    t_c_w: Float[ArrayLike, " 3"],
    points_w: Float[ArrayLike, "*n 3"],
    dist: Float[ArrayLike, " d"] | None = None,
) -> Float[Array, "*n 2"]:
    """Pixel coordinates of world points (OpenCV ``projectPoints`` semantics)."""
    K = jnp.asarray(K)
    points_c = jnp.einsum("ij,...j->...i", jnp.asarray(R_c_w), jnp.asarray(points_w)) + t_c_w
    xy = points_c[..., :2] / points_c[..., 2:3]
    if dist is not None:
        xy = distort(xy, dist)
    return xy @ K[:2, :2].T + K[:2, 2]


def undistort_points(
    uv: Float[ArrayLike, "*n 2"],
    K: Float[ArrayLike, "3 3"],
    dist: Float[ArrayLike, " d"],
    iterations: int = 10,
) -> Float[Array, "*n 2"]:
    """Remove lens distortion from pixel coordinates; returns ideal pixels (same K).

    Inverts :func:`distort` by Gauss-Newton on the normalised coordinates, which is
    accurate to far below a micro-pixel for ordinary lenses in a few iterations (OpenCV's
    fixed-point ``undistortPoints`` is the reference in the tests).
    """
    uv = jnp.asarray(uv)
    K = jnp.asarray(K, uv.dtype)
    Kinv2 = jnp.linalg.inv(K[:2, :2])
    target = (uv - K[:2, 2]) @ Kinv2.T

    jac = jax.vmap(jax.jacfwd(lambda p: distort(p, dist)))

    def step(xy, _):
        flat = xy.reshape(-1, 2)
        r = distort(flat, dist) - target.reshape(-1, 2)
        J = jac(flat)
        # 2x2 solve in closed form: batched over pixels, a LAPACK solve would be a
        # batched LAPACK call (deadlocked on 2 cores with jaxlib 0.10, see jaxtraj._spd)
        det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
        delta = (
            jnp.stack(
                [
                    J[:, 1, 1] * r[:, 0] - J[:, 0, 1] * r[:, 1],
                    J[:, 0, 0] * r[:, 1] - J[:, 1, 0] * r[:, 0],
                ],
                axis=-1,
            )
            / det[:, None]
        )
        return (flat - delta).reshape(xy.shape), None

    xy, _ = jax.lax.scan(step, target, None, length=iterations)
    return xy @ K[:2, :2].T + K[:2, 2]

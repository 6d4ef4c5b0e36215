"""Camera poses at the image times for simulated robot cells.

Every path returns a :class:`CameraPath` ``(R_c_w (F, 3, 3), t_c_w (F, 3))`` (OpenCV
camera frame, ``x_c = R_c_w x_w + t_c_w``) whose cameras look at the workpiece point, so
the point stays in front of the camera and near the image centre. The world is Z-up
(``up = +z`` for :func:`jaxtraj.look_at`; straight-down views fall back to ``+y``).

* :func:`static_camera` - one fixed camera.
* :func:`following_camera` - the camera trails the point at a fixed offset: every ray is
  parallel, so a trajectory-basis reconstruction is exactly degenerate.
* :func:`random_discontinuous_camera` - the paper's section-5 camera: an independent
  random position on a shell around the current point at every image.
* :func:`orbit_camera` - a circle around the workpiece's mean position.
* :func:`smooth_random_camera` - a smooth, robot-like path at a given constant speed.

The two random paths are jit-compiled (numeric options traced, ``n_grid`` static) and
vmap over keys; all paths are differentiable in their numeric parameters.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._checks import check_shape
from ..camera import look_at, projection_matrix

__all__ = [
    "CameraPath",
    "following_camera",
    "orbit_camera",
    "random_discontinuous_camera",
    "smooth_random_camera",
    "static_camera",
]


class CameraPath(eqx.Module):
    """Camera poses at F image times.

    Attributes:
        R_c_w: (F, 3, 3) world-to-camera rotations.
        t_c_w: (F, 3) world-to-camera translations [m].
    """

    R_c_w: Float[Array, "F 3 3"]
    t_c_w: Float[Array, "F 3"]

    @property
    def centres(self) -> Float[Array, "F 3"]:
        """(F, 3) camera centres in the world, ``-R_c_w^T t_c_w`` [m]."""
        return -jnp.einsum("fji,fj->fi", self.R_c_w, self.t_c_w)

    def projection_matrices(self, K: Float[ArrayLike, "3 3"]) -> Float[Array, "F 3 4"]:
        """(F, 3, 4) projection matrices ``K [R_c_w | t_c_w]``."""
        K = jnp.asarray(K, self.R_c_w.dtype)
        return jax.vmap(projection_matrix, in_axes=(None, 0, 0))(K, self.R_c_w, self.t_c_w)


def _look_at(position, target):
    """:func:`jaxtraj.look_at` with up = +z, or +y when looking (nearly) straight up/down."""
    d = target - position
    vertical = jnp.abs(d[2]) > 0.99 * jnp.linalg.norm(d)
    up = jnp.where(vertical, jnp.array([0.0, 1.0, 0.0], d.dtype), jnp.array([0.0, 0.0, 1.0]))
    return look_at(position, target, up.astype(d.dtype))


_look_at_many = jax.vmap(_look_at)


def _perpendicular_frame(v):
    """Two unit vectors ``(e1, e2)`` with ``(e1, e2, v/|v|)`` right-handed orthonormal."""
    v = v / jnp.linalg.norm(v)
    helper = jnp.where(
        jnp.abs(v[0]) > 0.9, jnp.array([0.0, 1.0, 0.0]), jnp.array([1.0, 0.0, 0.0])
    ).astype(v.dtype)
    e1 = jnp.cross(helper, v)
    e1 = e1 / jnp.linalg.norm(e1)
    return e1, jnp.cross(v, e1)


def _points(points) -> Array:
    check_shape("points", points, (None, 3), "(F, 3) workpiece point per image")
    points = jnp.asarray(points)
    return points.astype(jnp.result_type(points.dtype, jnp.float32))


def _check_range(name: str, rng, positive: bool = True) -> None:
    if isinstance(rng, (tuple, list)):
        if len(rng) != 2 or not rng[0] <= rng[1] or (positive and not rng[0] > 0):
            raise ValueError(f"{name}: expected (low, high) with 0 < low <= high, got {rng}")


def static_camera(
    position: Float[ArrayLike, " 3"], target: Float[ArrayLike, " 3"], F: int
) -> CameraPath:
    """One camera at ``position`` looking at ``target``, repeated for F images."""
    check_shape("position", position, (3,), "camera centre in the world [m]")
    check_shape("target", target, (3,), "point the optical axis goes through [m]")
    if not isinstance(F, int) or F < 1:
        raise ValueError(f"F: expected a positive int number of images, got {F!r}")
    position = jnp.asarray(position)
    position = position.astype(jnp.result_type(position.dtype, jnp.float32))
    R, t = _look_at(position, jnp.asarray(target, position.dtype))
    return CameraPath(jnp.broadcast_to(R, (F, 3, 3)), jnp.broadcast_to(t, (F, 3)))


def following_camera(points: Float[ArrayLike, "F 3"], offset: Float[ArrayLike, " 3"]) -> CameraPath:
    """A camera at ``point + offset`` looking at the point, with a constant orientation.

    All rays are parallel to ``offset``: the camera path equals the point path plus a
    constant, which lies in every trajectory basis containing constants, so the
    reconstruction is exactly degenerate (paper section 6).

    Args:
        points: (F, 3) workpiece point [m].
        offset: (3,) camera centre minus point [m], non-zero.
    """
    points = _points(points)
    check_shape("offset", offset, (3,), "camera centre minus point [m]")
    offset = jnp.asarray(offset, points.dtype)
    R, _ = _look_at(offset, jnp.zeros(3, points.dtype))
    t = -(points + offset) @ R.T
    return CameraPath(jnp.broadcast_to(R, (points.shape[0], 3, 3)), t)


def random_discontinuous_camera(
    key: PRNGKeyArray,
    points: Float[ArrayLike, "F 3"],
    *,
    standoff: tuple[float, float] = (0.5, 1.5),
    axis: Float[ArrayLike, " 3"] = (0.0, 0.0, 1.0),
    cone_angle: float = 1.0,
    max_aim: float = 0.1,
) -> CameraPath:
    """The paper's section-5 camera: an independent random viewpoint at every image.

    Camera ``i`` sits at ``points[i] + r_i d_i`` with the stand-off ``r_i`` uniform in
    ``standoff`` and the direction ``d_i`` uniform on the spherical cap of half-angle
    ``cone_angle`` around ``axis`` (default: above the workpiece). It looks at the point
    shifted sideways by a random aim error, so the angle between the optical axis and the
    ray to the point is at most ``max_aim`` (about ``f tan(max_aim)`` pixels from the
    principal point: 70 px for the default intrinsics).

    Args:
        key: a ``jax.random`` key.
        points: (F, 3) workpiece point [m].
        standoff: (low, high) camera-to-point distance [m].
        axis: (3,) centre direction of the cone of viewpoints (need not be unit).
        cone_angle: half-angle of the cone [rad], in [0, pi].
        max_aim: largest angle of the point off the optical axis [rad], in [0, pi/2).
    """
    points = _points(points)
    _check_range("standoff", standoff)
    check_shape("axis", axis, (3,), "direction of the cone of viewpoints")
    if isinstance(max_aim, (int, float)) and not 0 <= max_aim < 0.5 * np.pi:
        raise ValueError(f"max_aim: expected an angle in [0, pi/2), got {max_aim}")
    return _random_camera(key, points, *map(jnp.asarray, (standoff, axis, cone_angle, max_aim)))


@eqx.filter_jit
def _random_camera(key, points, standoff, axis, cone_angle, max_aim):
    F, dtype = points.shape[0], points.dtype
    u = jax.random.uniform(key, (5, F), dtype)  # one draw: cheap to compile
    lo, hi = standoff.astype(dtype)
    r = lo + (hi - lo) * u[0]
    cos_cone = jnp.cos(jnp.asarray(cone_angle, dtype))
    cos_t = cos_cone + (1.0 - cos_cone) * u[1]
    sin_t = jnp.sqrt(jnp.maximum(1.0 - cos_t**2, 0.0))
    phi = 2 * jnp.pi * u[2]
    a = jnp.asarray(axis, dtype)
    a = a / jnp.linalg.norm(a)
    e1, e2 = _perpendicular_frame(a)
    d = (
        (sin_t * jnp.cos(phi))[:, None] * e1
        + (sin_t * jnp.sin(phi))[:, None] * e2
        + cos_t[:, None] * a
    )
    position = points + r[:, None] * d
    # Aim error: an angle uniform over the disk of radius max_aim, in a random direction.
    alpha = jnp.asarray(max_aim, dtype) * jnp.sqrt(u[3])
    psi = 2 * jnp.pi * u[4]
    f1, f2 = jax.vmap(_perpendicular_frame)(d)
    side = jnp.cos(psi)[:, None] * f1 + jnp.sin(psi)[:, None] * f2
    target = points + (r * jnp.tan(alpha))[:, None] * side
    R, t = _look_at_many(position, target)
    return CameraPath(R, t)


def orbit_camera(
    points: Float[ArrayLike, "F 3"],
    *,
    radius: float,
    angular_speed: float,
    height: float,
    times: Float[ArrayLike, " F"],
    phase: float = 0.0,
    centre: Float[ArrayLike, " 3"] | None = None,
) -> CameraPath:
    """A camera circling the workpiece at constant angular speed, looking at the point.

    Centre ``i`` is ``c + (radius cos(w t_i + phase), radius sin(w t_i + phase), height)``
    with ``c`` the mean of ``points`` (or ``centre``) and ``w = angular_speed``.

    Args:
        points: (F, 3) workpiece point [m].
        radius: horizontal radius of the circle [m].
        angular_speed: [rad/s].
        height: height of the circle above ``c`` [m].
        times: (F,) image times [s].
        phase: angle at ``t = 0`` [rad].
        centre: (3,) centre of the circle; default the mean of ``points``.
    """
    points = _points(points)
    F, dtype = points.shape[0], points.dtype
    check_shape("times", times, (F,), "one time per image")
    c = jnp.mean(points, axis=0) if centre is None else jnp.asarray(centre, dtype)
    if centre is not None:
        check_shape("centre", centre, (3,), "centre of the circle [m]")
    angle = jnp.asarray(angular_speed, dtype) * jnp.asarray(times, dtype) + phase
    radius = jnp.asarray(radius, dtype)
    ring = jnp.stack(
        [radius * jnp.cos(angle), radius * jnp.sin(angle), jnp.full(F, height, dtype)], axis=1
    )
    R, t = _look_at_many(c + ring, points)
    return CameraPath(R, t)


def smooth_random_camera(
    key: PRNGKeyArray,
    points: Float[ArrayLike, "F 3"],
    times: Float[ArrayLike, " F"],
    *,
    speed: float,
    standoff: tuple[float, float] = (0.8, 1.2),
    elevation: tuple[float, float] = (0.4, 1.0),
    centre: Float[ArrayLike, " 3"] | None = None,
    n_grid: int = 2048,
) -> CameraPath:
    """A smooth robot-like camera path moving at constant ``speed``, looking at the point.

    The centre moves on a random smooth arc around ``c`` (the mean of ``points`` unless
    ``centre`` is given): with ``s`` the azimuth travelled,
    ``C(s) = c + r(s) (cos e(s) cos(a0 + sign s), cos e(s) sin(a0 + sign s), sin e(s))``,
    ``r(s)`` oscillating over ``standoff`` and the elevation ``e(s)`` over ``elevation``
    at random rates and phases. The arc is re-parametrised by arc length so that the
    camera centre moves at exactly ``speed`` m/s (up to the ``n_grid`` interpolation);
    ``speed = 0`` gives a static camera. Slow speeds give the near-degenerate smooth
    camera paths of real robots; fast ones approach an orbit.

    Args:
        key: a ``jax.random`` key.
        points: (F, 3) workpiece point [m].
        times: (F,) image times [s], increasing.
        speed: camera-centre speed [m/s], >= 0.
        standoff: (low, high) distance of the camera from ``c`` [m].
        elevation: (low, high) elevation angle of the camera above ``c`` [rad].
        centre: (3,) centre of the arc; default the mean of ``points``.
        n_grid: samples of the arc-length table (static).
    """
    points = _points(points)
    F, dtype = points.shape[0], points.dtype
    check_shape("times", times, (F,), "one time per image")
    _check_range("standoff", standoff)
    _check_range("elevation", elevation, positive=False)
    if isinstance(elevation, (tuple, list)) and not max(map(abs, elevation)) < 0.5 * np.pi:
        raise ValueError(f"elevation: expected angles inside (-pi/2, pi/2), got {elevation}")
    if isinstance(speed, (int, float)) and speed < 0:
        raise ValueError(f"speed: expected a speed >= 0 in m/s, got {speed}")
    if centre is not None:
        check_shape("centre", centre, (3,), "centre of the arc [m]")
    c = jnp.mean(points, axis=0) if centre is None else jnp.asarray(centre, dtype)
    times = jnp.asarray(times, dtype)
    args = map(jnp.asarray, (speed, standoff, elevation))
    return _smooth_camera(key, points, times, c, *args, n_grid)


@eqx.filter_jit
def _smooth_camera(key, points, times, c, speed, standoff, elevation, n_grid):
    dtype = points.dtype
    speed, standoff, elevation = (x.astype(dtype) for x in (speed, standoff, elevation))
    u = jax.random.uniform(key, (6,), dtype)
    a0 = 2 * jnp.pi * u[0]
    sign = jnp.where(u[1] < 0.5, 1.0, -1.0).astype(dtype)
    rates = 0.5 + 1.5 * u[2:4]
    phases = 2 * jnp.pi * u[4:6]
    r_mid, r_half = 0.5 * (standoff[0] + standoff[1]), 0.5 * (standoff[1] - standoff[0])
    e_mid, e_half = 0.5 * (elevation[0] + elevation[1]), 0.5 * (elevation[1] - elevation[0])

    def centre_at(s):
        r = r_mid + r_half * jnp.sin(rates[0] * s + phases[0])
        e = e_mid + e_half * jnp.sin(rates[1] * s + phases[1])
        az = a0 + sign * s
        return c + r[:, None] * jnp.stack(
            [jnp.cos(e) * jnp.cos(az), jnp.cos(e) * jnp.sin(az), jnp.sin(e)], axis=1
        )

    # Arc-length table: horizontal speed alone is at least r_min cos(e_max) per radian.
    length = speed * (times[-1] - times[0])
    slowest = standoff[0] * jnp.cos(jnp.max(jnp.abs(elevation)))
    s_grid = jnp.linspace(0.0, 1.0, n_grid, dtype=dtype) * (length / slowest + 1e-9)
    steps = jnp.linalg.norm(jnp.diff(centre_at(s_grid), axis=0), axis=1)
    arc = jnp.concatenate([jnp.zeros(1, dtype), jnp.cumsum(steps)])
    s = jnp.interp(speed * (times - times[0]), arc, s_grid)
    R, t = _look_at_many(centre_at(s), points)
    return CameraPath(R, t)

"""A camera path in the robot's joint space, and the cell's limits on it.

The path is ``q(t) = q0 + sum_j B_j(t) theta_j``: a clamped quintic B-spline whose first
three control points are pinned at the start configuration ``q0``, so the robot starts
exactly there and from rest (``q'(t0) = q''(t0) = 0``); ``theta`` ((m - 3), n) moves the
other control points. The camera pose follows from the robot, orientation included:
``T_w_c(t) = T_w_base FK(q(t)) T_f_c``.

Why a B-spline and not the DCT of the workpiece model: (1) local support: a control point
moves the path only over a few knot spans, which keeps the optimisation well conditioned;
(2) degree 5 makes position to jerk continuous and lets start-at-rest hold by construction
while the end stays free (every DCT vector has zero slope at both ends, which would force
the robot to stop at the end of the recording, not on its way to the assembly); (3) a
camera path inside the span of the reconstruction's own DCT basis is exactly the
degenerate case (eta -> 0), which a DCT path model invites.

Constraints (normalised, feasible where ``g <= 0``; ``0.1`` means 10 % past the limit):

* ``joint_position``, ``joint_velocity``, ``joint_acceleration``, ``joint_jerk`` - on
  the fine grid, ``((q - mid) / half_range)^2 - 1`` and ``(d^k q / limit)^2 - 1`` per joint;
* ``field_of_view`` - every plausible workpiece point at most ``half_fov - fov_margin`` off
  the optical axis (images);
* ``standoff`` - camera-to-prediction distance in ``[d_min, d_max]`` (images);
* ``keep_out`` - camera centre and flange at least ``keep_out_radius`` from the predicted
  workpiece point (grid; the prediction interpolated linearly), checked on the chords
  between consecutive grid points, not only at them (a fast pass can fall between);
* ``floor`` - every joint frame, the flange and the camera at least ``floor_clearance``
  above the floor plane ``z = floor_z`` (grid);
* ``end`` - optional: camera centre at the end time within ``end_tolerance`` of
  ``predicted[-1] + end_offset`` (the approach position for the assembly);
* ``depth_determined`` - optional (``max_depth_uncertainty``): every plausible workpiece
  trajectory's relative depth uncertainty ``kappa`` (:func:`jaxtraj.depth_uncertainty`,
  prior order ``depth_order``) at most that bound at the images, so that
  :func:`jaxtraj.estimate_points`, which flags tracks above its ``max_depth_uncertainty``
  (0.08) as not determined by the data, reports the designed path's tracks ``OK``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._checks import check_shape
from .._linalg import matmul_small
from ..depth import depth_uncertainty
from ..robot.chain import KinematicChain
from ..robot.kinematics import joint_frames, link_positions
from .bspline import bspline_basis, clamped_knots
from .constraints import _off_axis

__all__ = ["JOINT_CONSTRAINTS", "JointPathModel", "RobotCell", "joint_constraint_values"]

JOINT_CONSTRAINTS = (
    "joint_position",
    "joint_velocity",
    "joint_acceleration",
    "joint_jerk",
    "field_of_view",
    "standoff",
    "keep_out",
    "floor",
    "end",
    "depth_determined",
)

N_PINNED = 3  # control points pinned at q0: start at q0, at rest, zero acceleration


class RobotCell(eqx.Module):
    """The camera robot in its cell (SI units, radians).

    Attributes:
        chain: the camera robot (its joint limits are the path's limits).
        T_w_base: (4, 4) robot base in the world; T_f_c: (4, 4) hand-eye (camera in
            flange).
        K: (3, 3) camera matrix.
        standoff: (2,) allowed camera-to-workpiece distance [m].
        half_fov: half of the camera's smaller field of view [rad]; fov_margin [rad].
        keep_out_radius: no camera or flange closer to the workpiece [m].
        floor_z, floor_clearance: the floor plane's height and the clearance kept [m].
        end_offset: (3,) camera end position relative to the last prediction [m];
            end_tolerance [m]; use_end: whether the end constraint applies (static).
        max_depth_uncertainty: bound on ``kappa`` of the plausible trajectories (static;
            None: no such constraint); depth_order: the prior order of that ``kappa``.
    """

    chain: KinematicChain
    T_w_base: Float[Array, "4 4"] = eqx.field(converter=jnp.asarray)
    T_f_c: Float[Array, "4 4"] = eqx.field(converter=jnp.asarray)
    K: Float[Array, "3 3"] = eqx.field(converter=jnp.asarray)
    standoff: Float[Array, " 2"] = eqx.field(converter=jnp.asarray, default=(0.5, 1.5))
    half_fov: Float[ArrayLike, ""] = 0.33
    fov_margin: Float[ArrayLike, ""] = 0.05
    keep_out_radius: Float[ArrayLike, ""] = 0.35
    floor_z: Float[ArrayLike, ""] = 0.0
    floor_clearance: Float[ArrayLike, ""] = 0.1
    end_offset: Float[Array, " 3"] = eqx.field(converter=jnp.asarray, default=(0.0, 0.0, 0.6))
    end_tolerance: Float[ArrayLike, ""] = 0.05
    use_end: bool = eqx.field(static=True, default=False)
    max_depth_uncertainty: float | None = eqx.field(static=True, default=None)
    depth_order: int = eqx.field(static=True, default=2)


#: longest time between two points of the default limit-check grid [s]. A constraint rises
#: between grid points ``h`` apart by at most ``h^2 / 8`` times its second derivative; the
#: design's 1 % margin (``design_joint_path(grid_margin=)``) covers that only on a fine
#: enough grid. With 12 images over 10 s and 10 points per image interval (0.091 s apart), an
#: active floor constraint of the built-in cell rose 2.8 mm (2.8 % of its 0.1 m clearance)
#: between them on one host; 0.02 s apart the same curvature gives 0.13 mm. The built-in
#: cell's 60 images over 10 s with 10 points per interval are 0.017 s apart.
MAX_GRID_STEP = 0.02


class JointPathModel(eqx.Module):
    """The joint path model of one recording (a pytree; ``theta`` is passed separately).

    Attributes:
        times: (F,) image times [s]; grid: (G,) times of the limit checks [s].
        basis_images: (F, m - 3) position basis at the images (pinned columns dropped).
        basis_grid: (4, G, m - 3) position, velocity, acceleration, jerk basis on the grid.
        q0: (n,) start configuration [rad].
        geometry_stride: the floor and keep-out constraints (forward kinematics of every
            joint frame) use every ``geometry_stride``-th grid point.
    """

    times: Float[Array, " F"]
    grid: Float[Array, " G"]
    basis_images: Float[Array, "F p"]
    basis_grid: Float[Array, "4 G p"]
    q0: Float[Array, " n"]
    geometry_stride: int = eqx.field(static=True, default=1)

    @classmethod
    def create(
        cls,
        times: Float[ArrayLike, " F"],
        q0: Float[ArrayLike, " n"],
        *,
        n_control: int = 12,
        degree: int = 5,
        grid_per_image: int | None = None,
        geometry_stride: int = 1,
    ) -> JointPathModel:
        """A model with ``n_control`` control points per joint over ``[times[0], times[-1]]``.

        Args:
            times: (F,) increasing image times [s].
            q0: (n,) start configuration [rad] (the robot is at rest there).
            n_control: B-spline control points per joint (>= degree + 2); more is more
                agile.
            degree: B-spline degree (>= 3 so that jerk exists; default quintic).
            grid_per_image: limit-check samples per image interval (the grid has
                ``grid_per_image * (F - 1) + 1`` points, the image times among them);
                default :meth:`default_grid_per_image`: at least 10 and at most
                :data:`MAX_GRID_STEP` apart.
        """
        t = np.asarray(times, float)
        check_shape("times", t, (None,), "(F,) image times")
        if t.size < 2 or np.any(np.diff(t) <= 0):
            raise ValueError("times: expected at least 2 strictly increasing image times")
        check_shape("q0", q0, (None,), "(n,) start configuration")
        if degree < 3:
            raise ValueError(f"degree: expected >= 3 (jerk must exist), got {degree}")
        if n_control < degree + 2:
            raise ValueError(f"n_control: expected >= degree + 2 = {degree + 2}, got {n_control}")
        if grid_per_image is None:
            grid_per_image = cls.default_grid_per_image(t)
        if grid_per_image < 1:
            raise ValueError(f"grid_per_image: expected >= 1, got {grid_per_image}")
        if geometry_stride < 1 or grid_per_image % geometry_stride:
            raise ValueError(
                f"geometry_stride: expected a divisor of grid_per_image={grid_per_image}, "
                f"got {geometry_stride}"
            )
        knots = clamped_knots(t[0], t[-1], n_control, degree)
        grid = np.interp(
            np.linspace(0, t.size - 1, grid_per_image * (t.size - 1) + 1), np.arange(t.size), t
        )
        dtype = jnp.result_type(jnp.asarray(q0).dtype, jnp.float32)
        b_img = bspline_basis(t, knots, degree)[:, N_PINNED:]
        b_grid = np.stack([bspline_basis(grid, knots, degree, d)[:, N_PINNED:] for d in range(4)])
        return cls(
            jnp.asarray(t, dtype),
            jnp.asarray(grid, dtype),
            jnp.asarray(b_img, dtype),
            jnp.asarray(b_grid, dtype),
            jnp.asarray(q0, dtype),
            geometry_stride,
        )

    @staticmethod
    def default_grid_per_image(times: Float[ArrayLike, " F"]) -> int:
        """Limit-check samples per image interval of the default grid: 10, or more where
        the images are further apart than ``10 *`` :data:`MAX_GRID_STEP`."""
        longest = float(np.max(np.diff(np.asarray(times, float))))
        return max(10, int(np.ceil(longest / MAX_GRID_STEP - 1e-9)))

    @property
    def shape(self) -> tuple[int, int]:
        """Shape of ``theta``: (free control points, joints)."""
        return (self.basis_images.shape[1], self.q0.shape[0])

    def joints(self, theta: Float[ArrayLike, "p n"], derivative: int = 0) -> Float[Array, "G n"]:
        """Joint positions (``derivative`` 0) or their derivatives 1-3 on the grid."""
        d = self.basis_grid[derivative] @ jnp.asarray(theta)
        return self.q0 + d if derivative == 0 else d

    def joints_at_images(self, theta: Float[ArrayLike, "p n"]) -> Float[Array, "F n"]:
        """Joint positions (F, n) at the image times [rad]."""
        return self.q0 + self.basis_images @ jnp.asarray(theta)

    def fit(self, q_grid: Float[ArrayLike, "G n"]) -> Float[Array, "p n"]:
        """Parameters whose path is closest (least squares on the grid) to given joint
        values (e.g. a heuristic path); the start stays pinned at ``q0``."""
        return jnp.linalg.lstsq(self.basis_grid[0], jnp.asarray(q_grid) - self.q0)[0]


def camera_poses(cell: RobotCell, q: Float[Array, "T n"]) -> Float[Array, "T 4 4"]:
    """Camera poses ``T_w_c = T_w_base FK(q) T_f_c`` (T, 4, 4) of configurations (T, n)."""
    frames = jax.vmap(lambda qq: joint_frames(cell.chain, qq)[-1])(q)
    return matmul_small(matmul_small(cell.T_w_base, frames), cell.T_f_c)


def projection_matrices(cell: RobotCell, T_w_c: Float[Array, "F 4 4"]) -> Float[Array, "F 3 4"]:
    """(F, 3, 4) projection matrices ``K [R_c_w | t_c_w]`` of camera poses."""
    R_c_w = jnp.swapaxes(T_w_c[:, :3, :3], 1, 2)
    t_c_w = -jnp.sum(R_c_w * T_w_c[:, None, :3, 3], axis=2)
    return matmul_small(cell.K, jnp.concatenate([R_c_w, t_c_w[:, :, None]], axis=2))


def _swept_distance(r: Float[Array, "G 3"]) -> Float[Array, " G-1"]:
    """Closest approach to the origin of the relative position ``r`` between consecutive
    grid points (the chord ``r_i -> r_i+1``), so that a fast pass through the keep-out
    sphere between two grid points is seen (the point distances alone missed passes that
    went 9 % of the radius inside it on a 10x finer grid)."""
    a, d = r[:-1], jnp.diff(r, axis=0)
    dd = jnp.sum(d * d, axis=1)
    s = jnp.clip(-jnp.sum(a * d, axis=1) / jnp.maximum(dd, 1e-30), 0.0, 1.0)
    return jnp.linalg.norm(a + s[:, None] * d, axis=1)


def joint_constraint_values(
    model: JointPathModel,
    theta: Float[ArrayLike, "p n"],
    cell: RobotCell,
    predicted: Float[ArrayLike, "F 3"],
    samples: Float[ArrayLike, "S F 3"],
) -> dict[str, Array]:
    """Normalised constraint values per constraint (flat arrays; feasible where ``<= 0``)."""
    theta = jnp.asarray(theta)
    dtype = theta.dtype
    chain = cell.chain
    predicted = jnp.asarray(predicted, dtype)
    mid, half = 0.5 * (chain.upper + chain.lower), 0.5 * (chain.upper - chain.lower)
    q = model.joints(theta)
    values = {"joint_position": jnp.square((q - mid) / half) - 1.0}
    for d, (name, limit) in enumerate(
        [
            ("joint_velocity", chain.velocity),
            ("joint_acceleration", chain.acceleration),
            ("joint_jerk", chain.jerk),
        ],
        start=1,
    ):
        values[name] = jnp.square(model.joints(theta, d) / limit) - 1.0
    # geometry on the grid: every joint frame, the flange and the camera
    # (positions only, with the geometric Jacobian as their derivative: link_positions)
    stride = model.geometry_stride
    n = chain.origins.shape[0]
    cam_in_flange = cell.T_f_c[None, :3, 3]
    pos = jax.vmap(lambda qq: link_positions(chain, qq, cam_in_flange))(q[::stride])
    pos = jnp.sum(cell.T_w_base[:3, :3] * pos[:, :, None, :], axis=3) + cell.T_w_base[:3, 3]
    # pos: (G / stride, n + 2, 3): every joint frame's origin, the flange, the camera
    x_grid = jax.vmap(lambda c: jnp.interp(model.grid[::stride], model.times, c), 1, 1)(predicted)
    values["floor"] = (cell.floor_z + cell.floor_clearance - pos[:, :, 2]) / cell.floor_clearance
    dist = jnp.stack(
        [_swept_distance(pos[:, n + 1] - x_grid), _swept_distance(pos[:, n] - x_grid)], axis=1
    )
    values["keep_out"] = (cell.keep_out_radius - dist) / cell.keep_out_radius
    # camera at the images
    T_w_c = camera_poses(cell, model.joints_at_images(theta))
    c = T_w_c[:, :3, 3]
    d = jnp.linalg.norm(c - predicted, axis=1)
    d_lo, d_hi = cell.standoff[0], cell.standoff[1]
    values["standoff"] = jnp.stack([(d_lo - d) / d_lo, (d - d_hi) / d_hi], axis=1)
    R_c_w = jnp.swapaxes(T_w_c[:, :3, :3], 1, 2)
    t_c_w = -jnp.sum(R_c_w * c[:, None, :], axis=2)
    ang = jax.vmap(lambda x: jax.vmap(_off_axis)(R_c_w, t_c_w, x))(jnp.asarray(samples, dtype))
    values["field_of_view"] = ang / (cell.half_fov - cell.fov_margin) - 1.0
    if cell.use_end:
        target = predicted[-1] + cell.end_offset
        end = jnp.linalg.norm(c[-1] - target) / cell.end_tolerance - 1.0
    else:
        end = -jnp.ones((), dtype)
    values["end"] = jnp.reshape(end, (1,))
    if cell.max_depth_uncertainty is not None:
        kappa = jax.vmap(lambda x: depth_uncertainty(x, c, model.times, cell.depth_order))(
            jnp.asarray(samples, dtype)
        )
        values["depth_determined"] = kappa / cell.max_depth_uncertainty - 1.0
    else:
        values["depth_determined"] = -jnp.ones(1, dtype)
    return {name: jnp.ravel(values[name]) for name in JOINT_CONSTRAINTS}

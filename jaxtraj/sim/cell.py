"""A simulated robot cell with known ground truth, from motion to sensor data.

Robot 1 moves a workpiece (a plate with ArUco markers) along a smooth random 6-DoF
path. Robot 2 carries the camera, an IMU beside it, and reports its flange pose ``T_w_f``
every few milliseconds with a latency. The camera sweeps over the workpiece on a smooth
random path (sinusoids of random frequency and phase, as a robot moving between
viewpoints) and looks at the workpiece's work area; images are taken at irregular times.
Before the run, the camera robot shows the camera a calibration target lying on the table
from several flange poses (for intrinsic and hand-eye calibration).

:func:`simulate_cell` returns the truth and the sensor streams as NumPy arrays
(:class:`SimulatedCell`); :mod:`jaxtraj.sim.recording` renders the images and writes a
recording folder from it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from ..camera import look_at
from ..fusion.events import RobotNoise
from ..fusion.imu import ImuNoise
from ..fusion.simulate import imu_trajectory, simulate_recording
from ..io.records import PoseStream, matrix_to_quat
from .trajectories import rigid_motion, sample_times

__all__ = ["CellConfig", "SimulatedCell", "pose_matrix", "simulate_cell"]


def pose_matrix(R, t) -> np.ndarray:
    """(..., 4, 4) homogeneous transforms from rotations (..., 3, 3) and translations (..., 3)."""
    R, t = np.asarray(R, float), np.asarray(t, float)
    T = np.zeros((*R.shape[:-2], 4, 4))
    T[..., :3, :3], T[..., :3, 3], T[..., 3, 3] = R, t, 1.0
    return T


def _x64():
    """A context with float64 enabled (the simulation is float64 whatever the caller uses)."""
    ctx = getattr(jax, "enable_x64", None)
    if ctx is not None:
        return ctx(True)
    from jax.experimental import enable_x64  # older jax

    return enable_x64()


def _rot(rotvec) -> np.ndarray:
    return np.asarray(jaxlie.SO3.exp(jnp.asarray(rotvec, float)).as_matrix())


@dataclass(frozen=True)
class CellConfig:
    """Everything that defines a simulated cell. Lengths [m], times [s], angles [rad].

    Attributes:
        n_images, duration: images taken at irregular times over ``[0, duration]``.
        image_size, focal_px, dist: the camera (OpenCV model, principal point at the
            image centre plus ``principal_offset``).
        marker_ids, marker_grid, marker_size, marker_spacing: the workpiece plate.
        assembly_point: the point of the workpiece the robot needs (object frame).
        work_centre, work_extent, max_angle: workpiece path (bounding box centre and size,
            largest rotation from its start orientation).
        camera_height: mean height of the camera above ``work_centre``.
        camera_amplitude: (3,) amplitude of the camera sweep per world axis.
        camera_freq: (low, high) range of the sweep frequencies [Hz].
        imu_rate [Hz], robot_period [s], robot_latency [s]: sensor timing.
        imu_noise, robot_noise: sensor noise (filter models).
        T_f_c, T_i_c: (4, 4) hand-eye transform and camera-in-IMU transform.
        calibration_views: flange poses from which the calibration target is seen.
        pixel_noise, blur_px: image noise (grey levels) and optical blur [px].
    """

    n_images: int = 150
    duration: float = 10.0
    image_size: tuple[int, int] = (640, 480)
    focal_px: float = 700.0
    principal_offset: tuple[float, float] = (3.5, -2.0)
    dist: tuple[float, ...] = (-0.12, 0.06, 4e-4, -3e-4, 0.0)
    marker_ids: tuple[int, ...] = (0, 1, 2, 3, 4, 5)
    marker_grid: tuple[int, int] = (3, 2)
    marker_size: float = 0.06
    marker_spacing: float = 0.06
    assembly_point: tuple[float, float, float] = (0.05, -0.02, 0.0)
    work_centre: tuple[float, float, float] = (0.0, 0.0, 0.0)
    work_extent: float = 0.3
    max_angle: float = 0.25
    camera_height: float = 0.85
    camera_amplitude: tuple[float, float, float] = (0.3, 0.3, 0.1)
    camera_freq: tuple[float, float] = (0.15, 0.4)
    imu_rate: float = 200.0
    robot_period: float = 0.008
    robot_latency: float = 0.004
    imu_noise: ImuNoise = field(default_factory=ImuNoise.xsens_mti)
    robot_noise: RobotNoise = field(default_factory=RobotNoise.kuka_class)
    T_f_c: np.ndarray = field(
        default_factory=lambda: pose_matrix(_rot([0.02, -0.03, 1.5]), [0.01, 0.06, 0.09])
    )
    T_i_c: np.ndarray = field(
        default_factory=lambda: pose_matrix(_rot([0.0, 0.0, -1.5708]), [0.03, 0.0, -0.01])
    )
    calibration_views: int = 12
    pixel_noise: float = 1.5
    blur_px: float = 0.6

    def __post_init__(self):
        if self.n_images < 8:
            raise ValueError(f"n_images: expected at least 8 images, got {self.n_images}")
        if not self.duration > 0:
            raise ValueError(f"duration: expected a positive time in s, got {self.duration}")
        if len(self.marker_ids) != self.marker_grid[0] * self.marker_grid[1]:
            raise ValueError(
                f"marker_ids: expected {self.marker_grid[0] * self.marker_grid[1]} ids for "
                f"the grid {self.marker_grid}, got {len(self.marker_ids)}"
            )
        if self.calibration_views < 3:
            raise ValueError(f"calibration_views: expected >= 3, got {self.calibration_views}")

    @property
    def K(self) -> np.ndarray:
        """(3, 3) true camera matrix."""
        w, h = self.image_size
        cx = (w - 1) / 2 + self.principal_offset[0]
        cy = (h - 1) / 2 + self.principal_offset[1]
        return np.array([[self.focal_px, 0, cx], [0, self.focal_px, cy], [0, 0, 1.0]])


@dataclass(frozen=True)
class SimulatedCell:
    """Truth and sensor data of a simulated cell (NumPy, float64).

    Attributes:
        config: the :class:`CellConfig`.
        times: (F,) image times [s].
        object_pose: ``T_w_o`` at the image times; camera_pose: ``T_w_c`` at the image times.
        imu_t, gyro, accel: IMU samples (N,), (N, 3), (N, 3).
        robot: flange poses ``T_w_f`` stamped on the robot clock (latency included).
        calibration_flange: flange poses ``T_w_f`` of the calibration views (times = index).
        T_w_t: (4, 4) pose of the calibration target on the table.
    """

    config: CellConfig
    times: np.ndarray
    object_pose: PoseStream
    camera_pose: PoseStream
    imu_t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    robot: PoseStream
    calibration_flange: PoseStream
    T_w_t: np.ndarray


def _camera_trajectory(config: CellConfig, key):
    """A JAX callable ``t -> (p_w_c, q_w_c)``: the camera's smooth sweep over the work area."""
    u = jax.random.uniform(key, (4, 3), jnp.float64)
    lo, hi = config.camera_freq
    freq = lo + (hi - lo) * u[0]
    phase = 2 * jnp.pi * u[1]
    aim_freq = 0.5 * freq[::-1]
    aim_phase = 2 * jnp.pi * u[2]
    amp = jnp.asarray(config.camera_amplitude)
    centre = jnp.asarray(config.work_centre) + jnp.array([0.0, 0.0, config.camera_height])
    aim_amp = 0.3 * config.work_extent * jnp.array([1.0, 1.0, 0.0])

    def traj(t):
        p = centre + amp * jnp.sin(2 * jnp.pi * freq * t + phase)
        aim = jnp.asarray(config.work_centre) + aim_amp * jnp.sin(
            2 * jnp.pi * aim_freq * t + aim_phase
        )
        R_c_w, _ = look_at(p, aim, up_w=jnp.array([0.0, 1.0, 0.0]))
        return p, jaxlie.SO3.from_matrix(R_c_w.T).wxyz

    return traj


def _calibration_views(config: CellConfig, rng: np.random.Generator):
    """Camera poses ``T_w_c`` looking at a target on the table from varied angles."""
    T_w_t = pose_matrix(_rot([0.0, 0.0, 0.3]), [0.6, -0.4, -0.05])
    target = T_w_t[:3, 3]
    poses = []
    for k in range(config.calibration_views):
        az = 2 * np.pi * k / config.calibration_views + rng.uniform(-0.3, 0.3)
        tilt = rng.uniform(0.25, 0.6)
        r = rng.uniform(0.65, 0.9)
        pos = target + r * np.array(
            [np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)]
        )
        aim = target + rng.uniform(-0.15, 0.15, 3) * np.array([1, 1, 0])  # board off-centre
        R_c_w, t_c_w = (
            np.asarray(a) for a in look_at(pos, aim, up_w=(np.cos(az), np.sin(az), 0.0))
        )
        # roll the camera about its axis so the target appears at varied angles
        roll = _rot([0.0, 0.0, rng.uniform(-0.5, 0.5)])
        R_c_w, t_c_w = roll @ R_c_w, roll @ t_c_w
        poses.append(np.linalg.inv(pose_matrix(R_c_w, t_c_w)))
    return T_w_t, np.stack(poses)


def _pose_stream(times, T) -> PoseStream:
    return PoseStream(times, T[:, :3, 3], matrix_to_quat(T[:, :3, :3]))


def _check_given_motion(config: CellConfig, times, camera, object_pose):
    """Checks of :func:`simulate_cell`'s optional motions (host side, NumPy)."""
    given = (times is not None, camera is not None, object_pose is not None)
    if any(given) and not all(given):
        raise ValueError("times, camera, object_pose: give all three or none")
    if times is None:
        return None, None
    times = np.asarray(times, float)
    if times.shape != (config.n_images,) or np.any(np.diff(times) <= 0):
        raise ValueError(
            f"times: expected {config.n_images} strictly increasing image times, got "
            f"shape {times.shape}"
        )
    if times[0] < 0 or times[-1] > config.duration:
        raise ValueError(
            f"times: expected image times within [0, duration = {config.duration}] s, got "
            f"{times[0]:.3f} .. {times[-1]:.3f}"
        )
    R, p = (np.asarray(a, float) for a in object_pose)
    if R.shape != (times.size, 3, 3) or p.shape != (times.size, 3):
        raise ValueError(
            f"object_pose: expected rotations ({times.size}, 3, 3) and positions "
            f"({times.size}, 3), got {R.shape}, {p.shape}"
        )
    return times, (R, p)


def simulate_cell(
    config: CellConfig | None = None,
    seed: int = 0,
    *,
    times=None,
    camera=None,
    object_pose=None,
) -> SimulatedCell:
    """Simulate the motions and sensor streams of a robot cell (float64, NumPy out).

    Args:
        config: the cell; default :class:`CellConfig()`.
        seed: random seed (workpiece path, camera sweep, image times, sensor noise).
        times, camera, object_pose: a given scenario instead of the random one (all three
            or none): (n_images,) image times within ``[0, duration]``; the camera as a
            JAX callable ``t -> (p_w_c (3,), q_w_c (4,) wxyz)`` defined (and twice
            differentiable) from 0.5 s before 0 to 0.5 s after ``duration``, e.g.
            :func:`jaxtraj.sim.joint_camera.joint_path_camera`; the workpiece pose
            ``(R_w_o (F, 3, 3), p_w_o (F, 3))`` at the image times.

    Returns:
        a :class:`SimulatedCell`; images are rendered later from its poses.
    """
    config = CellConfig() if config is None else config
    given_times, given_object = _check_given_motion(config, times, camera, object_pose)
    with _x64():
        key = jax.random.PRNGKey(seed)
        k_t, k_obj, k_cam, k_rec = jax.random.split(key, 4)
        if given_times is None:
            times = sample_times(k_t, config.n_images, float(config.duration))
            R_w_o, p_w_o = rigid_motion(
                k_obj,
                times,
                centre=jnp.asarray(config.work_centre, jnp.float64),
                extent=config.work_extent,
                max_angle=config.max_angle,
            )
            camera = _camera_trajectory(config, k_cam)
        else:
            times = jnp.asarray(given_times)
            R_w_o, p_w_o = given_object
        p_w_c, q_w_c = jax.vmap(camera)(times)
        T_i_c = jaxlie.SE3.from_matrix(jnp.asarray(config.T_i_c))
        T_f_c = jaxlie.SE3.from_matrix(jnp.asarray(config.T_f_c))
        # the sensor streams cover a margin around the images (the filter needs a run-in)
        margin = 0.5
        shifted = imu_trajectory(lambda t: camera(t - margin), T_i_c)
        rec = simulate_recording(
            k_rec,
            shifted,
            duration=config.duration + 2 * margin,
            imu_noise=config.imu_noise,
            robot_noise=config.robot_noise,
            imu_rate=config.imu_rate,
            robot_period=config.robot_period,
            latency=config.robot_latency,
            T_f_c=T_f_c,
            T_i_c=T_i_c,
        )
        times_np = np.asarray(times)
        object_pose = PoseStream(
            times_np,
            np.asarray(p_w_o),
            matrix_to_quat(R_w_o),
        )
        camera_pose = PoseStream(times_np, np.asarray(p_w_c), np.asarray(q_w_c))
        robot = PoseStream(
            np.asarray(rec.robot.t) - margin, np.asarray(rec.robot.p), np.asarray(rec.robot.q)
        )
        imu_t = np.asarray(rec.imu.t) - margin
        gyro, accel = np.asarray(rec.imu.gyro), np.asarray(rec.imu.accel)
    rng = np.random.default_rng(seed + 7919)
    T_w_t, T_w_c_cal = _calibration_views(config, rng)
    T_w_f_cal = T_w_c_cal @ np.linalg.inv(config.T_f_c)
    calibration_flange = _pose_stream(np.arange(len(T_w_f_cal), dtype=float), T_w_f_cal)
    return SimulatedCell(
        config=config,
        times=times_np,
        object_pose=object_pose,
        camera_pose=camera_pose,
        imu_t=imu_t,
        gyro=gyro,
        accel=accel,
        robot=robot,
        calibration_flange=calibration_flange,
        T_w_t=T_w_t,
    )

"""Pipeline step ``fuse``: the camera's absolute pose at every image time.

IMU samples and the robot controller's flange poses go through the error-state Kalman
filter and the RTS smoother (:mod:`jaxtraj.fusion`); the camera pose
``T_w_c = T_w_i T_i_c`` is read off the smoothed stream at the image times. A robot
latency of ``None`` is estimated by maximum likelihood first.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import jaxlie
import numpy as np

from ..fusion.eskf import eskf, initial_covariance, initial_state
from ..fusion.events import IMAGE, ImuData, RobotNoise, RobotPoses, build_events
from ..fusion.imu import ImuNoise
from ..fusion.interpolate import camera_poses_at
from ..fusion.latency import estimate_latency
from ..fusion.smoother import rts_smoother
from ..io.records import PoseStream, matrix_to_quat

__all__ = ["FusedCameraPath", "fuse_camera_path"]


@dataclass(frozen=True)
class FusedCameraPath:
    """Camera poses at the image times, from IMU and robot data (NumPy).

    Attributes:
        times: (F,) image times [s].
        R_c_w, t_c_w: (F, 3, 3), (F, 3) world-to-camera poses (what the solver takes).
        pose: the same as a :class:`~jaxtraj.io.records.PoseStream` of ``T_w_c``.
        position_sigma: (F,) RMS per-axis standard deviation of the IMU position [m].
        orientation_sigma: (F,) RMS per-axis standard deviation of the orientation [rad].
        latency: the robot latency used [s]; latency_estimated: whether it was estimated.
        nis_mean: mean normalised innovation squared of the pose updates (about 6 when
            the noise settings fit the data; much larger means they do not).
        num_imu, num_robot: samples used.
    """

    times: np.ndarray
    R_c_w: np.ndarray
    t_c_w: np.ndarray
    pose: PoseStream
    position_sigma: np.ndarray
    orientation_sigma: np.ndarray
    latency: float
    latency_estimated: bool
    nis_mean: float
    num_imu: int
    num_robot: int


def _se3(T) -> jaxlie.SE3 | None:
    return None if T is None else jaxlie.SE3.from_matrix(jnp.asarray(T, jnp.float64))


def fuse_camera_path(
    imu_t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    robot: PoseStream,
    image_times: np.ndarray,
    *,
    T_f_c: np.ndarray | None,
    T_i_c: np.ndarray | None,
    imu_noise: ImuNoise,
    robot_noise: RobotNoise,
    latency: float | None = None,
    gravity_w=(0.0, 0.0, -9.81),
    smooth: bool = True,
) -> FusedCameraPath:
    """Fuse IMU and robot poses and return the camera poses at ``image_times``.

    Args:
        imu_t, gyro, accel: (N,), (N, 3), (N, 3) IMU samples [s, rad/s, m/s^2].
        robot: flange poses ``T_w_f`` stamped on the robot clock.
        image_times: (F,) image times [s], inside the IMU span.
        T_f_c, T_i_c: (4, 4) hand-eye and camera-in-IMU transforms (None: identity).
        imu_noise, robot_noise: the sensor noise models.
        latency: robot latency [s]; None estimates it (maximum likelihood).
        gravity_w: gravity in the world frame [m/s^2].
        smooth: run the RTS smoother after the filter (offline; recommended).

    Raises:
        ValueError: image times outside the IMU span, or a diverged filter.
    """
    image_times = np.asarray(image_times, float)
    if image_times[0] < imu_t[0] or image_times[-1] > imu_t[-1]:
        raise ValueError(
            f"image times [{image_times[0]:.3f}, {image_times[-1]:.3f}] s are not inside the "
            f"IMU samples' span [{imu_t[0]:.3f}, {imu_t[-1]:.3f}] s"
        )
    imu = ImuData(t=jnp.asarray(imu_t), gyro=jnp.asarray(gyro), accel=jnp.asarray(accel))
    poses = RobotPoses(t=jnp.asarray(robot.times), p=jnp.asarray(robot.p), q=jnp.asarray(robot.q))
    T_f_c_, T_i_c_ = _se3(T_f_c), _se3(T_i_c)
    P0 = initial_covariance(2e-3, 0.05, 0.01, 0.1, 0.01)
    estimated = latency is None
    if estimated:
        est = estimate_latency(
            imu, poses, P0, imu_noise, robot_noise, T_f_c=T_f_c_, T_i_c=T_i_c_, gravity_w=gravity_w
        )
        latency = float(est.latency)
    events = build_events(
        imu,
        poses,
        jnp.asarray(image_times),
        noise=robot_noise,
        latency=latency,
        T_f_c=T_f_c_,
        T_i_c=T_i_c_,
    )
    result = eskf(events, initial_state(events), P0, imu_noise, gravity_w)
    updated = np.asarray(result.updated)
    nis = float(np.mean(np.asarray(result.nis)[updated])) if updated.any() else float("nan")
    if smooth:
        result = rts_smoother(result, imu_noise, gravity_w)
    if not bool(result.ok):
        raise ValueError("the camera-pose filter diverged (non-finite state); check the data")
    R_c_w, t_c_w = (np.asarray(a) for a in camera_poses_at(result, image_times, T_i_c_))
    var = np.asarray(result.variances)[np.asarray(result.kind) == IMAGE]
    order = np.argsort(np.asarray(result.index)[np.asarray(result.kind) == IMAGE], kind="stable")
    var = var[order]
    R_w_c = np.swapaxes(R_c_w, -1, -2)
    p_w_c = -np.einsum("fij,fj->fi", R_w_c, t_c_w)
    q_w_c = matrix_to_quat(R_w_c)
    return FusedCameraPath(
        times=image_times,
        R_c_w=R_c_w,
        t_c_w=t_c_w,
        pose=PoseStream(image_times, p_w_c, q_w_c),
        position_sigma=np.sqrt(var[:, 0:3].mean(axis=1)),
        orientation_sigma=np.sqrt(var[:, 6:9].mean(axis=1)),
        latency=float(latency),
        latency_estimated=estimated,
        nis_mean=nis,
        num_imu=int(imu_t.shape[0]),
        num_robot=int(robot.times.shape[0]),
    )

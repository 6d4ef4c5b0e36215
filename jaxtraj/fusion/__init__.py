"""Camera pose from IMU and robot controller data: error-state Kalman filter, RTS
smoother, poses at image times, latency estimation, simulation.

Typical use::

    events = build_events(imu, robot, image_times, noise=RobotNoise.kuka_class(),
                          latency=0.004, T_f_c=T_f_c, T_i_c=T_i_c)
    result = eskf(events, initial_state(events), P0, ImuNoise.xsens_mti())
    result = rts_smoother(result, ImuNoise.xsens_mti())       # offline
    R_c_w, t_c_w = camera_poses_at(result, image_times, T_i_c)
    P = projection_matrices(result, image_times, K, T_i_c)    # (F, 3, 4)

The latency is found with :func:`estimate_latency` (maximum likelihood over vmapped
candidate offsets); the hand-eye transform ``T_f_c`` with
:func:`jaxtraj.vision.calibrate_hand_eye` (OpenCV, at the host-side edge);
synthetic recordings come from :mod:`jaxtraj.fusion.simulate`.
"""

from .eskf import FusionResult as FusionResult
from .eskf import eskf as eskf
from .eskf import eskf_batch as eskf_batch
from .eskf import initial_covariance as initial_covariance
from .eskf import initial_state as initial_state
from .eskf import nees as nees
from .events import EventStream as EventStream
from .events import ImuData as ImuData
from .events import RobotNoise as RobotNoise
from .events import RobotPoses as RobotPoses
from .events import build_events as build_events
from .imu import ImuNoise as ImuNoise
from .imu import NominalState as NominalState
from .interpolate import camera_poses_at as camera_poses_at
from .interpolate import interpolate_poses as interpolate_poses
from .interpolate import projection_matrices as projection_matrices
from .latency import LatencyEstimate as LatencyEstimate
from .latency import estimate_latency as estimate_latency
from .latency import latency_nll as latency_nll
from .smoother import rts_smoother as rts_smoother

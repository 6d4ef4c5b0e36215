"""From a recording folder to the measured workpiece: one module per pipeline stage.

``calibrate`` (camera + hand-eye) -> ``detect`` (markers in the images) -> ``fuse``
(camera poses from IMU + robot) -> ``reconstruct`` (6-DoF pose, per-point trajectories)
-> ``evaluate`` (against simulated truth). :mod:`.steps` runs each stage on folders, as
the ``jaxtraj`` command does.
"""

from .calibrate import calibrate_recording as calibrate_recording
from .detect import detect_images as detect_images
from .evaluate import evaluate_results as evaluate_results
from .fuse import FusedCameraPath as FusedCameraPath
from .fuse import fuse_camera_path as fuse_camera_path
from .reconstruct import Measurement as Measurement
from .reconstruct import reconstruct_recording as reconstruct_recording
from .steps import step_calibrate as step_calibrate
from .steps import step_evaluate as step_evaluate
from .steps import step_fuse as step_fuse
from .steps import step_reconstruct as step_reconstruct
from .steps import step_simulate as step_simulate

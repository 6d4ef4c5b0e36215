"""Simulated robot cells: workpiece motion, camera paths, detector noise, whole scenes."""

from .camera_paths import CameraPath as CameraPath
from .camera_paths import following_camera as following_camera
from .camera_paths import orbit_camera as orbit_camera
from .camera_paths import random_discontinuous_camera as random_discontinuous_camera
from .camera_paths import smooth_random_camera as smooth_random_camera
from .camera_paths import static_camera as static_camera
from .scene import CAMERA_KINDS as CAMERA_KINDS
from .scene import DEFAULT_MARKERS as DEFAULT_MARKERS
from .scene import IMAGE_SIZE as IMAGE_SIZE
from .scene import Observation as Observation
from .scene import RigidScene as RigidScene
from .scene import Scene as Scene
from .scene import default_intrinsics as default_intrinsics
from .scene import make_rigid_scene as make_rigid_scene
from .scene import make_scene as make_scene
from .scene import observe as observe
from .scene import paper_experiment as paper_experiment
from .trajectories import SmoothCurve as SmoothCurve
from .trajectories import bvh_curve as bvh_curve
from .trajectories import rigid_motion as rigid_motion
from .trajectories import sample_smooth_curve as sample_smooth_curve
from .trajectories import sample_times as sample_times
from .trajectories import smooth_random_curve as smooth_random_curve
from .trajectories import transform_points as transform_points

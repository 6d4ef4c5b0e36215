"""Vision at the host-side edge (OpenCV): camera and hand-eye calibration, marker detection."""

from .calibration import CalibrationResult as CalibrationResult
from .calibration import CalibrationTarget as CalibrationTarget
from .calibration import calibrate_camera as calibrate_camera
from .calibration import calibrate_from_corners as calibrate_from_corners
from .calibration import check_image_size as check_image_size
from .calibration import detect_target as detect_target
from .calibration import find_charuco as find_charuco
from .calibration import find_chessboard as find_chessboard
from .calibration import find_circle_grid as find_circle_grid
from .handeye import METHODS as METHODS
from .handeye import HandEyeResult as HandEyeResult
from .handeye import calibrate_hand_eye as calibrate_hand_eye
from .handeye import consistency as consistency
from .handeye import hand_eye_residuals as hand_eye_residuals
from .handeye import motion_axes_check as motion_axes_check
from .handeye import solve_hand_eye as solve_hand_eye
from .handeye import target_poses_from_views as target_poses_from_views
from .handeye import view_pose_covariances as view_pose_covariances
from .markers import MarkerDetections as MarkerDetections
from .markers import detect_markers as detect_markers

"""Vision at the host-side edge (OpenCV): hand-eye calibration; later calibration and markers."""

from .handeye import HandEyeResult as HandEyeResult
from .handeye import calibrate_hand_eye as calibrate_hand_eye
from .handeye import hand_eye_residuals as hand_eye_residuals
from .handeye import target_poses_from_views as target_poses_from_views

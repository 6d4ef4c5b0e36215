"""Calibration in pure JAX: the robot-world hand-eye bundle adjustment.

:func:`refine_hand_eye` refines intrinsics, distortion, the hand-eye transform and the
target pose together by minimising the (robust) reprojection error of every target corner
in every view (optimistix Levenberg-Marquardt), with parameter covariances. The OpenCV
closed-form start and the file handling live at the edge (:mod:`jaxtraj.vision`,
:mod:`jaxtraj.pipeline.calibrate`).
"""

from .bundle import PARAMETER_NAMES as PARAMETER_NAMES
from .bundle import HandEyeBundle as HandEyeBundle
from .bundle import bundle_residuals as bundle_residuals
from .bundle import refine_hand_eye as refine_hand_eye

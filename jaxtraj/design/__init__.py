"""Active camera-path design: smooth robot paths that keep the workpiece reconstructible.

* :mod:`.path` - the camera path model (few parameters, starts at the start pose, looks at
  the predicted workpiece point).
* :mod:`.objectives` - expected reconstruction error and eta, differentiable.
* :mod:`.smoother_error` - expected error of the smoothness-prior smoother (the per-point
  estimator): the prior's bias plus the noise variance, exact for the linearised smoother.
* :mod:`.pose_error` - expected error of the known-layout pose (per-image PnP of the
  object's reference points), first order, with the exact mean of its Gaussian error.
* :mod:`.constraints` - workspace, stand-off, field of view, velocity, acceleration, end
  pose, as normalised constraint values.
* :mod:`.optimise` - penalty continuation with optimistix BFGS over several initial guesses.

In the robot's joint space (the path a KUKA arm executes, orientation included):

* :mod:`.joint_path` - ``q(t) = q0 + B-spline``, camera pose ``T_w_base FK(q) T_f_c``,
  joint position/velocity/acceleration/jerk limits on a fine grid, field of view,
  stand-off, keep-out, floor, optional end position;
* :mod:`.joint_optimise` - augmented Lagrangian with a BFGS of its own (one evaluation
  site, KKT test after every step), the starts on a CPU's threads or vmapped, reporting
  the largest violation and the KKT stationarity.
"""

from .constraints import CONSTRAINTS as CONSTRAINTS
from .constraints import CellLimits as CellLimits
from .constraints import constraint_values as constraint_values
from .joint_optimise import JointPathDesign as JointPathDesign
from .joint_optimise import design_joint_path as design_joint_path
from .joint_optimise import evaluate_joint_path as evaluate_joint_path
from .joint_path import JOINT_CONSTRAINTS as JOINT_CONSTRAINTS
from .joint_path import JointPathModel as JointPathModel
from .joint_path import RobotCell as RobotCell
from .joint_path import joint_constraint_values as joint_constraint_values
from .objectives import expected_error as expected_error
from .objectives import expected_error_for_cameras as expected_error_for_cameras
from .objectives import expected_errors_for_cameras as expected_errors_for_cameras
from .objectives import monte_carlo_error as monte_carlo_error
from .objectives import path_reconstructibility as path_reconstructibility
from .objectives import plausible_trajectories as plausible_trajectories
from .objectives import sampled_limits as sampled_limits
from .optimise import PathDesign as PathDesign
from .optimise import design_camera_path as design_camera_path
from .optimise import evaluate_path as evaluate_path
from .path import CameraPathModel as CameraPathModel
from .pose_error import expected_pose_errors_for_cameras as expected_pose_errors_for_cameras
from .pose_error import gaussian_mean_norm as gaussian_mean_norm
from .pose_error import pose_point_covariances as pose_point_covariances
from .smoother_error import (
    expected_smoother_errors_for_cameras as expected_smoother_errors_for_cameras,
)
from .smoother_error import smoother_error_terms as smoother_error_terms

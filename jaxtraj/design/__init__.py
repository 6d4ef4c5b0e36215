"""Active camera-path design: smooth robot paths that keep the workpiece reconstructible.

* :mod:`.path` - the camera path model (few parameters, starts at the start pose, looks at
  the predicted workpiece point).
* :mod:`.objectives` - expected reconstruction error and eta, differentiable.
* :mod:`.constraints` - workspace, stand-off, field of view, velocity, acceleration, end
  pose, as normalised constraint values.
* :mod:`.optimise` - penalty continuation with optimistix BFGS over several initial guesses.
"""

from .constraints import CONSTRAINTS as CONSTRAINTS
from .constraints import CellLimits as CellLimits
from .constraints import constraint_values as constraint_values
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

"""jaxtraj: trajectory and 6-DoF pose of a moving workpiece from a robot-carried camera.

The public names are re-exported here; see the README and ``DESIGN`` notes for the method.

Importing jaxtraj before the first JAX computation lets XLA:CPU compile small loops (such
as the camera-pose filter's scan) into one kernel; see :mod:`jaxtraj._xla`.
"""

from . import _xla  # noqa: F401  (first: sets XLA_FLAGS before anything compiles)
from .analysis import OnRay as OnRay
from .analysis import conditioning_gain as conditioning_gain
from .analysis import on_ray_decomposition as on_ray_decomposition
from .analysis import reconstructibility as reconstructibility
from .basis import DCTBasis as DCTBasis
from .basis import dct_basis as dct_basis
from .camera import camera_centre as camera_centre
from .camera import look_at as look_at
from .camera import project as project
from .camera import projection_matrix as projection_matrix
from .camera import undistort_points as undistort_points
from .constraints import block_diagonal_Q as block_diagonal_Q
from .constraints import ray_constraints as ray_constraints
from .constraints import theta_matrix as theta_matrix
from .estimators.estimate import PointEstimate as PointEstimate
from .estimators.estimate import depth_uncertainty as depth_uncertainty
from .estimators.estimate import estimate_points as estimate_points
from .rigid import fit_rigid as fit_rigid
from .solve import Reconstruction as Reconstruction
from .solve import Status as Status
from .solve import normal_equations as normal_equations
from .solve import reconstruct as reconstruct
from .solve import reconstruct_points as reconstruct_points

__version__ = "0.1.0"

"""Estimators beyond the plain DCT least squares of the paper.

* :mod:`.estimate` - :func:`estimate_points`, the one call: model chosen per point,
  along-ray uncertainty, DEGENERATE where the depth is not determined.
* :mod:`.smoothness` - smoothness prior (trajectory filter / state-space smoother), no k.
* :mod:`.filtering` - Kalman filter / RTS smoother from a known start (slow cameras).
* :mod:`.select_k` - automatic k: cross-validation and conditioning-gain bound.
* :mod:`.refine` - maximum-likelihood (robust) refinement of DCT coefficients.
* :mod:`.covariance` - first-order covariance from pixel and camera-pose noise.
* :mod:`.streaming` - recursive sliding-window DCT estimation for on-line use.
* :mod:`.joint_pose` - joint 6-DoF fit of a rigid motion to all reference points' rays.
* :mod:`.regularised` - regularised DCT: roughness penalty with a cross-validated weight.
"""

from .covariance import ReconstructionCovariance as ReconstructionCovariance
from .covariance import dct_covariance as dct_covariance
from .covariance import points_covariance as points_covariance
from .estimate import PointEstimate as PointEstimate
from .estimate import depth_uncertainty as depth_uncertainty
from .estimate import estimate_points as estimate_points
from .filtering import filter_points as filter_points
from .filtering import filter_trajectory as filter_trajectory
from .joint_pose import RigidTrajectory as RigidTrajectory
from .joint_pose import fit_rigid_trajectory as fit_rigid_trajectory
from .joint_pose import kabsch_per_frame as kabsch_per_frame
from .refine import Refined as Refined
from .refine import refine_dct as refine_dct
from .refine import refine_points as refine_points
from .regularised import PenaltyChoice as PenaltyChoice
from .regularised import reconstruct_regularised as reconstruct_regularised
from .regularised import reconstruct_regularised_points as reconstruct_regularised_points
from .regularised import regularised_covariance as regularised_covariance
from .regularised import roughness_penalty as roughness_penalty
from .regularised import select_penalty_cv as select_penalty_cv
from .select_k import KSelection as KSelection
from .select_k import select_k_cv as select_k_cv
from .select_k import select_k_gain as select_k_gain
from .select_k import select_k_points as select_k_points
from .smoothness import Smoothed as Smoothed
from .smoothness import default_psd_grid as default_psd_grid
from .smoothness import predict as predict
from .smoothness import select_process_psd as select_process_psd
from .smoothness import smooth_points as smooth_points
from .smoothness import smooth_trajectory as smooth_trajectory
from .streaming import StreamEstimate as StreamEstimate
from .streaming import StreamState as StreamState
from .streaming import stream_estimate as stream_estimate
from .streaming import stream_init as stream_init
from .streaming import stream_rebase as stream_rebase
from .streaming import stream_run as stream_run
from .streaming import stream_update as stream_update

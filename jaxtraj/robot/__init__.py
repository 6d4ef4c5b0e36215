"""Robot arms in pure JAX: serial kinematic chains, forward and inverse kinematics.

* :mod:`.chain` - :class:`KinematicChain`, the plain chain description (from URDF at the
  edge: :func:`jaxtraj.io.urdf.load_robot`, :func:`jaxtraj.io.urdf.read_urdf`);
* :mod:`.limits` - the documented default acceleration and jerk limits (assumptions);
* :mod:`.kinematics` - forward kinematics, camera pose ``T_w_base FK(q) T_f_c``, Jacobian;
* :mod:`.ik` - inverse kinematics (Levenberg-Marquardt) with reachability and joint-limit
  reports.
"""

from .chain import KinematicChain as KinematicChain
from .chain import kinematic_chain as kinematic_chain
from .ik import IKResult as IKResult
from .ik import inverse_kinematics as inverse_kinematics
from .ik import pose_residual as pose_residual
from .ik import reach_distance as reach_distance
from .ik import require_reachable as require_reachable
from .ik import solve_ik as solve_ik
from .kinematics import axis_rotation as axis_rotation
from .kinematics import camera_pose as camera_pose
from .kinematics import forward_kinematics as forward_kinematics
from .kinematics import jacobian as jacobian
from .kinematics import joint_frames as joint_frames
from .kinematics import link_positions as link_positions
from .limits import default_acceleration as default_acceleration
from .limits import default_jerk as default_jerk

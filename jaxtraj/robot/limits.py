"""Default joint acceleration and jerk limits: ASSUMPTIONS, not datasheet values.

Robot makers publish joint ranges and rated speeds (KUKA KR 16-2: 156, 156, 156, 330,
330, 615 deg/s) but not joint accelerations or jerks; these depend on the payload, the
pose and the controller's motion profile. jaxtraj therefore assumes, for every joint:

* ``ACCELERATION_TIME = 0.5`` s: the joint reaches its rated speed from rest in 0.5 s at
  its acceleration limit, ``a_max = v_max / 0.5 s`` (KR 16-2 A1: 312 deg/s^2);
* ``JERK_TIME = 0.25`` s: it reaches its acceleration limit in 0.25 s at its jerk limit,
  ``j_max = a_max / 0.25 s`` (KR 16-2 A1: 1248 deg/s^3).

These are deliberately gentle for a 16 kg-class arm carrying a camera (a KUKA moves its
axes to full speed in a few tenths of a second at 100 % override) so that a designed path
keeps a reserve; measure your cell and pass the measured values instead
(:meth:`~jaxtraj.robot.KinematicChain.with_limits`, or ``limits`` in CELL.json).
"""

from __future__ import annotations

from jaxtyping import Array, ArrayLike, Float

__all__ = ["ACCELERATION_TIME", "JERK_TIME", "default_acceleration", "default_jerk"]

ACCELERATION_TIME = 0.5  # [s] assumed time to rated speed at the acceleration limit
JERK_TIME = 0.25  # [s] assumed time to the acceleration limit at the jerk limit


def default_acceleration(velocity: Float[ArrayLike, " n"]) -> Float[Array, " n"]:
    """Assumed acceleration limits ``velocity / ACCELERATION_TIME`` [rad/s^2]."""
    return velocity / ACCELERATION_TIME


def default_jerk(acceleration: Float[ArrayLike, " n"]) -> Float[Array, " n"]:
    """Assumed jerk limits ``acceleration / JERK_TIME`` [rad/s^3]."""
    return acceleration / JERK_TIME

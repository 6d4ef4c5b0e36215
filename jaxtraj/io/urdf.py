"""Robot descriptions from URDF files (host side): the kinematic chain the JAX core uses.

The URDF is parsed with ``yourdfpy`` (a maintained URDF parser: it resolves ``rpy``
origins, default axes and the link tree); the chain from the base link to the tip link is
reduced to a :class:`~jaxtraj.robot.KinematicChain`, fixed joints folded into their
neighbours. The robots shipped with jaxtraj (package data ``jaxtraj/robot/data``):

* ``kr16_2`` - KUKA KR 16-2, the camera robot of the paper (ROS-Industrial kr16_2
  geometry and limits);
* ``kr60_3`` - KUKA KR 60-3, the workpiece robot of the simulated cell.

Their tip is KUKA's ``$FLANGE`` (link ``flange``, x out of the flange face), the frame the
robot controller reports and the hand-eye ``T_f_c`` refers to.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np

from ..robot.chain import KinematicChain, kinematic_chain

__all__ = ["ROBOTS", "load_robot", "read_urdf"]

ROBOTS = {"kr16_2": "kr16_2.urdf", "kr60_3": "kr60_3.urdf"}


def _robot_key(name: str) -> str:
    return str(name).strip().lower().replace(" ", "").replace("-", "_")


def robot_file(name: str) -> Path:
    """Path of a shipped robot's URDF file (``"kr16_2"``, ``"KR 16-2"``, ``"kr60_3"``)."""
    key = _robot_key(name)
    if key not in ROBOTS:
        raise ValueError(f"robot: unknown robot {name!r}; known robots: {', '.join(ROBOTS)}")
    return Path(str(resources.files("jaxtraj.robot") / "data" / ROBOTS[key]))


def load_robot(
    name: str,
    *,
    tip_link: str = "flange",
    acceleration=None,
    jerk=None,
) -> KinematicChain:
    """The kinematic chain of a robot shipped with jaxtraj (see :data:`ROBOTS`).

    Args:
        name: ``"kr16_2"`` or ``"kr60_3"`` (case, spaces and '-' ignored: ``"KR 16-2"``).
        tip_link: the tip frame (``"flange"``: KUKA $FLANGE; ``"tool0"``: ROS-Industrial).
        acceleration, jerk: (6,) limits [rad/s^2, rad/s^3]; default: the assumptions of
            :mod:`jaxtraj.robot.limits`.
    """
    return read_urdf(robot_file(name), tip_link=tip_link, acceleration=acceleration, jerk=jerk)


def read_urdf(
    path: str | Path,
    *,
    base_link: str | None = None,
    tip_link: str | None = None,
    acceleration=None,
    jerk=None,
) -> KinematicChain:
    """Read the serial chain from ``base_link`` to ``tip_link`` of a URDF file.

    Args:
        path: the URDF file.
        base_link: first link of the chain (default: the tree's root link).
        tip_link: last link (default: the only leaf of the tree; required when the tree
            branches).
        acceleration, jerk: optional (n,) limits (URDF has none); default: the
            assumptions of :mod:`jaxtraj.robot.limits`.

    Raises:
        ValueError: the file is missing or not URDF, a link is unknown, the links are
            not connected, or a joint on the chain is of an unsupported type or lacks
            limits (messages name the file and the joint).
    """
    import yourdfpy  # the edge's only user of the URDF parser

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: URDF file not found")
    try:
        urdf = yourdfpy.URDF.load(
            str(path),
            load_meshes=False,
            load_collision_meshes=False,
            build_scene_graph=False,
            build_collision_scene_graph=False,
        )
    except Exception as err:  # lxml / yourdfpy errors: name the file
        raise ValueError(f"{path}: not a readable URDF file ({err})") from err
    joints = dict(urdf.joint_map)
    by_child = {j.child: j for j in joints.values()}
    links = set(urdf.link_map)
    roots = sorted(links - set(by_child))
    base = base_link or (roots[0] if len(roots) == 1 else None)
    if base is None:
        raise ValueError(f"{path}: {len(roots)} root links {roots}; give base_link")
    if tip_link is None:
        leaves = sorted(links - {j.parent for j in joints.values()})
        if len(leaves) != 1:
            raise ValueError(f"{path}: the tree has leaves {leaves}; give tip_link")
        tip_link = leaves[0]
    for label, link in (("base_link", base), ("tip_link", tip_link)):
        if link not in links:
            raise ValueError(f"{path}: {label} {link!r} is not a link (links: {sorted(links)})")
    chain = []
    link = tip_link
    while link != base:
        if link not in by_child:
            raise ValueError(f"{path}: link {tip_link!r} is not below base_link {base!r}")
        chain.append(by_child[link])
        link = by_child[link].parent
    chain.reverse()

    names, types, origins, axes, lower, upper, velocity = [], [], [], [], [], [], []
    pending = np.eye(4)  # fixed joints since the last moving joint
    for j in chain:
        origin = np.eye(4) if j.origin is None else np.asarray(j.origin, float)
        if j.type == "fixed":
            pending = pending @ origin
            continue
        if j.type not in ("revolute", "prismatic"):
            raise ValueError(
                f"{path}: joint {j.name!r} is {j.type!r}; only revolute, prismatic and fixed "
                "joints (with limits) are supported"
            )
        if getattr(j, "mimic", None) is not None:
            raise ValueError(f"{path}: joint {j.name!r} mimics another joint (not supported)")
        lim = j.limit
        if lim is None or lim.lower is None or lim.upper is None or not lim.velocity:
            raise ValueError(f"{path}: joint {j.name!r} needs lower, upper and velocity limits")
        names.append(j.name)
        types.append(j.type)
        origins.append(pending @ origin)
        axes.append(np.asarray([1.0, 0.0, 0.0] if j.axis is None else j.axis, float))
        lower.append(float(lim.lower))
        upper.append(float(lim.upper))
        velocity.append(float(lim.velocity))
        pending = np.eye(4)
    if not names:
        raise ValueError(f"{path}: no moving joint between {base!r} and {tip_link!r}")
    return kinematic_chain(
        urdf.robot.name,
        names,
        np.stack(origins),
        np.stack(axes),
        pending,
        lower,
        upper,
        velocity,
        acceleration=acceleration,
        jerk=jerk,
        joint_types=types,
    )

"""A simulated cell whose camera robot runs a given joint path (host side).

``jaxtraj simulate --camera-path joint_path.csv`` checks a designed path the way it will
be used: the camera robot moves through the joint path (:mod:`.joint_camera`), the
workpiece's assembly point moves along the cell's predicted trajectory (the one the path
was designed for), and the rest of the simulation (IMU, robot log with latency, rendered
images, calibration views) is that of :func:`jaxtraj.sim.cell.simulate_cell`. The
recording then goes through the whole pipeline, so the measured error of the per-point
trajectories can be compared with the error the design predicted.

The workpiece plate keeps one orientation, facing the mean camera position, because a
predicted trajectory gives positions only; a cell designed for the known-layout pose
(estimator ``"pose"``) uses the orientation and the followed object point it was designed
for.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..camera import look_at
from ..io.cell import CellSpec
from ..io.urdf import load_robot
from .cell import CellConfig, SimulatedCell, _x64, simulate_cell
from .joint_camera import cubic_spline, joint_path_camera

__all__ = ["designed_cell"]


def _check_path(spec: CellSpec, chain, times: np.ndarray, q: np.ndarray) -> None:
    if q.shape != (times.size, chain.n):
        raise ValueError(
            f"joint path: expected ({times.size}, {chain.n}) axis values, got {q.shape}"
        )
    lo, hi = np.asarray(chain.lower), np.asarray(chain.upper)
    bad = chain.outside_limits(q, 1e-9)
    if bad.size:
        i, j = bad[0]
        raise ValueError(
            f"joint path: A{j + 1} = {np.degrees(q[i, j]):.2f} deg at "
            f"t = {times[i]:.3f} s is outside its limits {np.degrees(lo[j]):.0f} .. "
            f"{np.degrees(hi[j]):.0f} deg ({len(np.unique(bad[:, 0]))} of {times.size} "
            "samples outside)"
        )
    t0, t1 = spec.times[0], spec.times[-1]
    if times[0] < t0 - 1e-6 or times[-1] > t1 + 1e-6:
        raise ValueError(
            f"joint path: times {times[0]:.3f} .. {times[-1]:.3f} s lie outside the "
            f"prediction's {t0:.3f} .. {t1:.3f} s"
        )


def designed_cell(
    spec: CellSpec,
    times,
    q,
    *,
    seed: int = 0,
    config: CellConfig | None = None,
) -> SimulatedCell:
    """Simulate the cell ``spec`` with the camera robot on the joint path ``(times, q)``.

    Args:
        spec: the cell (robot, base, hand-eye, camera matrix, predicted trajectory), as
            read from CELL.json or from ``design.json``'s ``"cell"``.
        times: (F,) image times [s] within the prediction's time span; the images are taken
            at these times (shifted to start at 0).
        q: (F, n) axis values [rad] of the camera robot at ``times``.
        seed: seed of the sensor noise and calibration views.
        config: other settings of the simulation (noise, IMU, markers); its image count,
            duration, camera matrix and hand-eye are replaced by the path's and the cell's.

    Raises:
        ValueError: a path outside the joint limits (naming the axis and the time), times
            outside the prediction, a camera matrix without square pixels.
    """
    chain = load_robot(spec.robot)
    times = np.asarray(times, float)
    q = np.asarray(q, float)
    if times.ndim != 1 or times.size < 8 or np.any(np.diff(times) <= 0):
        raise ValueError("joint path: expected at least 8 strictly increasing times")
    _check_path(spec, chain, times, q)
    K = np.asarray(spec.K, float)
    if abs(K[0, 0] - K[1, 1]) > 1e-6 * K[0, 0] or abs(K[0, 1]) > 1e-9:
        raise ValueError(f"K: the simulated camera has square pixels (fx = fy, no skew), got {K}")
    base = CellConfig() if config is None else config
    w, h = base.image_size
    t0 = times[0]
    config = dataclasses.replace(
        base,
        n_images=times.size,
        duration=float(times[-1] - t0),
        focal_px=float(K[0, 0]),
        principal_offset=(float(K[0, 2] - (w - 1) / 2), float(K[1, 2] - (h - 1) / 2)),
        T_f_c=np.asarray(spec.T_f_c, float),
    )
    t = times - t0
    with _x64():
        camera = joint_path_camera(chain, t, q, spec.T_f_c, spec.T_w_base)
        point = cubic_spline(spec.times - t0, spec.predicted)
        p_point = np.asarray(jax.vmap(point)(jnp.asarray(t)))
        centres = np.asarray(jax.vmap(lambda s: camera(s)[0])(jnp.asarray(t)))
        # the plate faces the mean camera position (object z towards the camera)
        R_o_w, _ = look_at(p_point.mean(0), centres.mean(0), up_w=(0.0, 0.0, 1.0))
    R = np.asarray(R_o_w).T
    if spec.method == "pose":  # the orientation and followed point the path was designed for
        R = spec.workpiece_orientation(centres[0])
        point = tuple(np.asarray(spec.point, float).tolist())
        config = dataclasses.replace(config, assembly_point=point)
    R_w_o = np.repeat(R[None], t.size, axis=0)
    p_w_o = p_point - R_w_o @ np.asarray(config.assembly_point)
    return simulate_cell(config, seed, times=t, camera=camera, object_pose=(R_w_o, p_w_o))

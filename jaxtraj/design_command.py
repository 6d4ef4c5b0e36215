"""``jaxtraj design``: a joint-space camera path for a robot cell, and its files (host side).

:func:`example_cell` is the built-in simulated cell (a KUKA KR 16-2 carrying the camera,
the workpiece carried by a KUKA KR 60-3 along a smooth 3D curve); :func:`design_cell`
designs the path for a :class:`~jaxtraj.io.cell.CellSpec`; :func:`write_design` writes

* ``joint_path.csv`` - ``t, A1..A6`` [s, deg] at the image times;
* ``joint_path_ipo.csv`` - the same resampled at the KUKA controller cycle (12 ms);
* ``camera_poses.tum`` - the camera poses ``T_w_c`` at the image times (TUM);
* ``design.json`` - objective, errors, per-constraint margins and active constraints,
  convergence per start, timings, the cell;
* ``path_3d.png``, ``joints.png`` - the path with the workpiece, each joint against its
  limits.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from . import dct_basis, look_at
from .design.joint_optimise import design_joint_path, visible_points
from .design.joint_path import (
    JOINT_CONSTRAINTS,
    JointPathModel,
    RobotCell,
    camera_poses,
    joint_constraint_values,
)
from .design.objectives import plausible_trajectories
from .io.cell import CellSpec
from .io.urdf import load_robot
from .robot import forward_kinematics, solve_ik

__all__ = [
    "IPO_CYCLE",
    "design_cell",
    "example_cell",
    "example_layout",
    "write_design",
]

IPO_CYCLE = 0.012  # [s] KUKA KRC interpolation cycle

# camera optical axis (z) out of the flange (flange x), image y down at the home pose
EXAMPLE_T_F_C = np.array(
    [[0.0, 0.0, 1.0, 0.08], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.05], [0, 0, 0, 1.0]]
)


def example_cell(frames: int = 60, duration: float = 10.0, starts: int = 8) -> CellSpec:
    """The built-in simulated cell: KR 16-2 (camera) at the origin; a KR 60-3 3.3 m in
    front of it, facing it, carries the workpiece (0.1 m out of its flange) along a smooth
    3D curve (A1 +-12 deg, A2 +-6 deg, A3 +-8 deg) about 1.9 m from the KR 16."""
    kr60 = load_robot("kr60_3")
    T_w_b60 = np.eye(4)
    T_w_b60[:3, :3] = np.diag([-1.0, -1.0, 1.0])
    T_w_b60[:3, 3] = [3.3, 0.0, 0.0]
    times = np.linspace(0.0, duration, frames)
    s = times / duration
    q60 = np.radians(
        np.stack(
            [
                12 * np.sin(2 * np.pi * s),
                -60 + 6 * np.sin(np.pi * s),
                100 - 8 * np.sin(2 * np.pi * s + 0.5),
                np.zeros_like(s),
                50 + 0 * s,
                np.zeros_like(s),
            ],
            1,
        )
    )
    T_f_part = np.eye(4)
    T_f_part[0, 3] = 0.1
    flange = np.asarray(jax.jit(jax.vmap(lambda q: forward_kinematics(kr60, q)))(q60))
    predicted = (T_w_b60 @ flange @ T_f_part)[:, :3, 3]
    K = np.array([[700.0, 0.0, 319.5], [0.0, 700.0, 239.5], [0.0, 0.0, 1.0]])
    return CellSpec(
        robot="kr16_2",
        T_w_base=np.eye(4),
        T_f_c=EXAMPLE_T_F_C.copy(),
        K=K,
        times=times,
        predicted=predicted,
        camera_start=predicted[0] + np.array([-0.9, 0.0, 0.35]),
        k=min(12, 2 * frames // 3),
        starts=starts,
    )


def example_layout() -> tuple[np.ndarray, np.ndarray]:
    """The simulated workpiece's reference points (its six marker centres, object frame)
    and its assembly point [m]: the known layout of the built-in cell (``"pose"``)."""
    from types import SimpleNamespace

    from .sim.cell import CellConfig
    from .sim.recording import workpiece

    _, model = workpiece(SimpleNamespace(config=CellConfig()))
    return np.asarray(model.points, float), np.asarray(model.assembly_point, float)


#: the ``kappa`` bound of a design for the per-point estimator: estimate_points' default
MAX_DEPTH_UNCERTAINTY = 0.08


def estimator_name(spec: CellSpec) -> str:
    """The ``estimator`` argument of :func:`design_joint_path` for a cell's estimator."""
    return f"smoother{spec.order}" if spec.method == "smoother" else spec.method


def _start_configuration(spec: CellSpec, chain) -> np.ndarray:
    """The start configuration: given, or by IK for the camera at ``camera_start`` looking
    at the first prediction (``ValueError`` naming the pose when it cannot be reached)."""
    if spec.q_start is not None:
        q = np.asarray(spec.q_start)
        lo, hi = np.asarray(chain.lower), np.asarray(chain.upper)
        bad = chain.outside_limits(q)
        if bad.size:
            j = bad[0, -1]
            raise ValueError(
                f"start: {chain.joint_names[j]} = {np.degrees(q[j]):.1f} deg is outside its "
                f"limits {np.degrees(lo[j]):.0f} .. {np.degrees(hi[j]):.0f} deg"
            )
        return q
    c0 = np.asarray(spec.camera_start, float)
    R_c_w, _ = look_at(jnp.asarray(c0), jnp.asarray(spec.predicted[0]), jnp.asarray([0, 0, 1.0]))
    T_w_c = np.eye(4)
    T_w_c[:3, :3] = np.asarray(R_c_w).T
    T_w_c[:3, 3] = c0
    T_b_f = np.linalg.inv(spec.T_w_base) @ T_w_c @ np.linalg.inv(spec.T_f_c)
    home = np.radians([0.0, -90.0, 90.0, 0.0, 45.0, 0.0])
    return np.asarray(solve_ik(chain, T_b_f, home, what="start pose (camera at start)"))


def _initial_guesses(model: JointPathModel, chain, starts: int, seed: int) -> np.ndarray:
    """Smooth joint weaves (A1-A6 sinusoids of 1-3 cycles, 2-10 deg) fitted into the path
    model. (The start pose held still is no guess: a static camera is the degenerate case,
    with an expected error of metres and a gradient to match.)"""
    rng = np.random.default_rng(seed)
    grid = np.asarray(model.grid)
    span = grid[-1] - grid[0]
    q0 = np.asarray(model.q0)
    out = []
    for _ in range(starts):
        amp = np.radians([6, 4, 4, 10, 10, 10]) * rng.uniform(0.3, 1.0, 6)
        f = rng.integers(1, 4, 6)
        ph = rng.uniform(0, 2 * np.pi, 6)
        arg = 2 * np.pi * f * (grid[:, None] - grid[0]) / span + ph
        out.append(np.asarray(model.fit(q0 + amp * (np.sin(arg) - np.sin(ph)))))
    return np.stack(out)


def _chain(spec: CellSpec):
    """The cell's robot, its velocity, acceleration and jerk limits replaced by the cell's
    where given (e.g. reduced speed)."""
    return load_robot(spec.robot).with_limits(
        velocity=spec.velocity, acceleration=spec.acceleration, jerk=spec.jerk
    )


def design_cell(spec: CellSpec, *, inner_steps: int = 500) -> dict:
    """Design the camera path for a cell; returns the design, the model and the check on
    a 10x finer grid, with timings (host side)."""
    chain = _chain(spec)
    q0 = _start_configuration(spec, chain)
    cell = RobotCell(
        chain,
        spec.T_w_base,
        spec.T_f_c,
        spec.K,
        standoff=spec.standoff,
        half_fov=spec.half_fov,
        fov_margin=spec.fov_margin,
        keep_out_radius=spec.keep_out_radius,
        floor_z=spec.floor_z,
        floor_clearance=spec.floor_clearance,
        end_offset=np.zeros(3) if spec.end_offset is None else spec.end_offset,
        end_tolerance=spec.end_tolerance,
        use_end=spec.end_offset is not None,
        # designed for estimate_points: its tracks must come out with depth determined
        max_depth_uncertainty=MAX_DEPTH_UNCERTAINTY if spec.method == "smoother" else None,
        depth_order=spec.order,
    )
    model = JointPathModel.create(spec.times, q0, n_control=spec.n_control)
    key = jax.random.PRNGKey(spec.seed)
    samples = plausible_trajectories(
        key, spec.predicted, spec.times, spec.plausible_samples, extent=spec.plausible_extent
    )
    basis = dct_basis(spec.times - spec.times[0], spec.k)
    inits = jnp.asarray(_initial_guesses(model, chain, spec.starts, spec.seed))
    layout = None
    if spec.method == "pose":
        c0 = np.asarray(camera_poses(cell, jnp.asarray(q0)[None]))[0, :3, 3]
        layout = (spec.layout, spec.point, spec.workpiece_orientation(c0))
    t0 = time.perf_counter()
    best, designs = design_joint_path(
        model,
        cell,
        spec.predicted,
        samples,
        basis,
        inits,
        objective=spec.objective,
        estimator=estimator_name(spec),
        layout=layout,
        pixel_sigma=spec.pixel_sigma,
        inner_steps=inner_steps,
    )
    best.theta.block_until_ready()
    seconds = time.perf_counter() - t0
    per_image = 10 * JointPathModel.default_grid_per_image(spec.times)  # 10x the design's
    fine = JointPathModel.create(spec.times, q0, n_control=spec.n_control, grid_per_image=per_image)
    visible = visible_points(samples, layout)
    values = joint_constraint_values(fine, best.theta, cell, spec.predicted, visible)
    return {
        "chain": chain,
        "cell": cell,
        "model": model,
        "best": best,
        "designs": designs,
        "samples": samples,
        "inits": inits,
        "basis": basis,
        "layout": layout,
        "seconds": seconds,
        "fine_violation": {k: float(jnp.max(values[k])) for k in JOINT_CONSTRAINTS},
    }


def _joint_table(t, q_deg, names) -> str:
    header = "t," + ",".join(names) + "\n"
    rows = "".join(
        f"{ti:.6f}," + ",".join(f"{v:.6f}" for v in row) + "\n"
        for ti, row in zip(t, q_deg, strict=True)
    )
    return header + rows


def write_design(out: str | Path, spec: CellSpec, result: dict, plots: bool = True) -> Path:
    """Write the design's files into ``out`` (see the module docstring); returns ``out``."""
    from .design.bspline import bspline_basis, clamped_knots
    from .io.csv_formats import write_tum
    from .io.records import PoseStream
    from .io.tables import atomic_folder, atomic_write_text

    model, best, chain = result["model"], result["best"], result["chain"]
    names = [f"A{i + 1}" for i in range(chain.n)]
    theta = np.asarray(best.theta)
    q_img = np.asarray(model.joints_at_images(theta))
    t_ipo = np.arange(spec.times[0], spec.times[-1] + 1e-9, IPO_CYCLE)
    knots = clamped_knots(spec.times[0], spec.times[-1], spec.n_control, 5)
    control = np.concatenate([np.zeros((3, chain.n)), theta]) + np.asarray(model.q0)
    q_ipo = bspline_basis(t_ipo, knots, 5) @ control
    T_w_c = np.asarray(camera_poses(result["cell"], jnp.asarray(q_img)))
    import jaxlie

    quat = np.asarray(
        jax.vmap(lambda R: jaxlie.SO3.from_matrix(R).wxyz)(jnp.asarray(T_w_c[:, :3, :3]))
    )
    designs = result["designs"]
    report = {
        "objective": spec.objective,
        "estimator": estimator_name(spec),
        "expected_mean_error_m": float(best.expected_mean_error),
        "expected_rms_error_m": float(best.expected_error),
        "expected_worst_frame_error_m": float(best.expected_worst_error),
        "constraints": best.report(),
        "active_constraints": [k for k, v in best.report().items() if v["active"]],
        "max_violation": float(best.max_violation),
        "stationarity": float(best.stationarity),
        "converged": bool(best.converged),
        "starts": {
            "converged": np.asarray(designs.converged).tolist(),
            "max_violation": np.asarray(designs.max_violation).tolist(),
            "stationarity": np.asarray(designs.stationarity).tolist(),
            "rounds": np.asarray(designs.rounds).tolist(),
            "evaluations": np.asarray(designs.evaluations).tolist(),
            "expected_mean_error_m": np.asarray(designs.expected_mean_error).tolist(),
        },
        "fine_grid_violation": result["fine_violation"],
        **(
            {"workpiece_R_w_o": np.asarray(result["layout"][2]).tolist()}
            if result.get("layout") is not None
            else {}
        ),
        "design_seconds": result["seconds"],
        "start_q_deg": np.degrees(np.asarray(model.q0)).tolist(),
        "joint_limits": {
            "lower_deg": np.degrees(np.asarray(chain.lower)).tolist(),
            "upper_deg": np.degrees(np.asarray(chain.upper)).tolist(),
            "velocity_deg_s (datasheet unless given)": np.degrees(
                np.asarray(chain.velocity)
            ).tolist(),
            "acceleration_deg_s2 (assumed unless given)": np.degrees(
                np.asarray(chain.acceleration)
            ).tolist(),
            "jerk_deg_s3 (assumed unless given)": np.degrees(np.asarray(chain.jerk)).tolist(),
        },
        "cell": spec.to_dict(),
    }
    with atomic_folder(out) as tmp:
        atomic_write_text(
            tmp / "joint_path.csv", _joint_table(spec.times, np.degrees(q_img), names)
        )
        atomic_write_text(tmp / "joint_path_ipo.csv", _joint_table(t_ipo, np.degrees(q_ipo), names))
        write_tum(tmp / "camera_poses.tum", PoseStream(times=spec.times, p=T_w_c[:, :3, 3], q=quat))
        atomic_write_text(tmp / "design.json", json.dumps(report, indent=2) + "\n")
        if plots:
            _plots(tmp, spec, result, T_w_c, t_ipo, q_ipo)
    return Path(out)


def _plots(folder: Path, spec, result, T_w_c, t_ipo, q_ipo) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    chain = result["chain"]
    fig = plt.figure(figsize=(7, 6))
    ax = fig.add_subplot(projection="3d")
    ax.plot(*spec.predicted.T, "k-", label="predicted workpiece")
    ax.plot(*T_w_c[:, :3, 3].T, "C0.-", label="camera (designed)")
    for i in range(0, len(T_w_c), max(1, len(T_w_c) // 12)):
        c, z = T_w_c[i, :3, 3], T_w_c[i, :3, 2]
        ax.plot(*np.stack([c, c + 0.15 * z]).T, "C1-", lw=0.8)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.legend()
    fig.savefig(folder / "path_3d.png", dpi=100)
    plt.close(fig)
    fig, axes = plt.subplots(chain.n, 1, figsize=(7, 1.6 * chain.n), sharex=True)
    lo, hi = np.degrees(np.asarray(chain.lower)), np.degrees(np.asarray(chain.upper))
    for j, ax in enumerate(axes):
        ax.plot(t_ipo, np.degrees(q_ipo[:, j]), "C0-")
        ax.axhline(lo[j], color="r", lw=0.8)
        ax.axhline(hi[j], color="r", lw=0.8)
        ax.set_ylabel(f"A{j + 1} [deg]")
    axes[-1].set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(folder / "joints.png", dpi=100)
    plt.close(fig)

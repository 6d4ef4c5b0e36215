"""``jaxtraj simulate --camera-path``: the camera robot on a joint path, the workpiece on the
cell's prediction (jaxtraj.sim.joint_camera, jaxtraj.sim.designed)."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtraj.cli import main
from jaxtraj.design_command import _start_configuration, example_cell
from jaxtraj.io.csv_formats import read_joint_path, read_poses
from jaxtraj.io.recording import read_recording
from jaxtraj.io.urdf import load_robot
from jaxtraj.robot import camera_pose
from jaxtraj.sim.designed import designed_cell
from jaxtraj.sim.joint_camera import cubic_spline
from jaxtraj.sim.recording import pose_matrices


def test_cubic_spline_interpolates_with_continuous_acceleration_and_linear_ends():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.1, 0.3, 9))
    y = rng.normal(size=(9, 2))
    f = cubic_spline(t, y)
    np.testing.assert_allclose(jax.vmap(f)(jnp.asarray(t)), y, atol=1e-12)
    acc = jax.jacfwd(jax.jacfwd(f))
    for tk in t[1:-1]:  # second derivative continuous across each inner knot
        np.testing.assert_allclose(acc(tk - 1e-9), acc(tk + 1e-9), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(acc(t[0]), 0.0, atol=1e-9)  # natural ends
    vel_end = jax.jacfwd(f)(t[-1])
    np.testing.assert_allclose(f(t[-1] + 0.5), y[-1] + 0.5 * vel_end, atol=1e-12)
    np.testing.assert_allclose(acc(t[-1] + 0.3), 0.0, atol=1e-12)
    # a straight line is reproduced exactly, also beyond the ends
    line = cubic_spline(t, 2.0 * t - 1.0)
    np.testing.assert_allclose(line(t[0] - 0.4), 2.0 * (t[0] - 0.4) - 1.0, atol=1e-12)
    np.testing.assert_allclose(line(0.5 * (t[2] + t[3])), t[2] + t[3] - 1.0, atol=1e-12)
    with pytest.raises(ValueError, match="strictly increasing"):
        cubic_spline(t[::-1], y)
    with pytest.raises(ValueError, match="N >= 2"):
        cubic_spline(t[:1], y[:1])


def _weave(frames: int, amplitude_deg=(3, 2, 2, 3, 3, 3)):
    spec = example_cell(frames=frames)
    chain = load_robot(spec.robot)
    q0 = _start_configuration(spec, chain)
    s = (spec.times - spec.times[0]) / np.ptp(spec.times)
    wave = np.sin(2 * np.pi * s[:, None] * np.array([1, 2, 1, 2, 1, 1]))
    return spec, chain, q0 + np.radians(amplitude_deg) * wave


def test_designed_cell_moves_the_camera_through_the_joint_path():
    spec, chain, q = _weave(8)
    cell = designed_cell(spec, spec.times, q, seed=3)
    T_w_c = pose_matrices(cell.camera_pose)
    T_ref = np.stack([np.asarray(camera_pose(chain, qq, spec.T_f_c, spec.T_w_base)) for qq in q])
    np.testing.assert_allclose(T_w_c, T_ref, atol=1e-12)
    np.testing.assert_allclose(cell.times, spec.times - spec.times[0], atol=1e-12)
    # the workpiece's assembly point is on the prediction, in front of every camera
    T_w_o = pose_matrices(cell.object_pose)
    point = T_w_o[:, :3, :3] @ np.asarray(cell.config.assembly_point) + T_w_o[:, :3, 3]
    np.testing.assert_allclose(point, spec.predicted, atol=1e-12)
    depth = (np.linalg.inv(T_w_c) @ T_w_o)[:, 2, 3]
    assert np.all((depth > spec.standoff[0] - 0.2) & (depth < spec.standoff[1]))
    # the robot log is the flange of the same path (plus the controller's noise)
    T_w_f = T_ref @ np.linalg.inv(spec.T_f_c)
    log = pose_matrices(cell.robot)
    i = np.argmin(np.abs(cell.robot.times[:, None] - (cell.times + 0.004)[None]), axis=0)
    assert np.max(np.linalg.norm(log[i, :3, 3] - T_w_f[:, :3, 3], axis=1)) < 2e-3
    # the camera matrix and hand-eye are the cell's
    np.testing.assert_allclose(cell.config.K, spec.K, atol=1e-9)
    np.testing.assert_allclose(cell.config.T_f_c, spec.T_f_c, atol=0)
    # a cell designed for the known-layout pose: the orientation and followed point of
    # the design (object z towards the start camera, or the cell's R_w_o)
    spec.method, spec.layout, spec.point = "pose", np.eye(4, 3), np.array([0.02, 0.01, 0.0])
    cell = designed_cell(spec, spec.times, q, seed=3)
    T_w_o = pose_matrices(cell.object_pose)
    R = spec.workpiece_orientation(T_ref[0, :3, 3])
    np.testing.assert_allclose(T_w_o[:, :3, :3], np.repeat(R[None], len(q), 0), atol=1e-12)
    np.testing.assert_allclose(
        R[:, 2],
        (T_ref[0, :3, 3] - spec.predicted[0]) / np.linalg.norm(T_ref[0, :3, 3] - spec.predicted[0]),
        atol=1e-12,
    )
    np.testing.assert_allclose(
        T_w_o[:, :3, :3] @ spec.point + T_w_o[:, :3, 3], spec.predicted, atol=1e-12
    )


def test_designed_cell_rejects_paths_a_robot_cannot_run():
    spec, _, q = _weave(8)
    bad = q.copy()
    bad[5, 1] = np.radians(40.0)  # A2 above +35 deg
    with pytest.raises(ValueError, match=r"A2 = 40\.00 deg at t = 7\.143 s is outside"):
        designed_cell(spec, spec.times, bad)
    with pytest.raises(ValueError, match="outside the prediction"):
        designed_cell(spec, spec.times + 1.0, q)
    with pytest.raises(ValueError, match=r"expected \(8, 6\) axis values"):
        designed_cell(spec, spec.times, q[:, :5])


def _write_path(folder, times, q):
    rows = "".join(
        f"{t:.6f}," + ",".join(f"{v:.6f}" for v in np.degrees(row)) + "\n"
        for t, row in zip(times, q, strict=True)
    )
    path = folder / "joint_path.csv"
    path.write_text("t,A1,A2,A3,A4,A5,A6\n" + rows)
    return path


def test_simulate_camera_path_command_and_its_bad_input(tmp_path, capsys):
    spec, chain, q = _weave(8)
    path = _write_path(tmp_path, spec.times, q)
    (tmp_path / "CELL.json").write_text(json.dumps(spec.to_dict()))
    t_read, q_read = read_joint_path(path)
    np.testing.assert_allclose(t_read, spec.times, atol=1e-6)
    np.testing.assert_allclose(np.degrees(q_read), np.degrees(q), atol=1e-6)
    # no design.json beside the path and no --cell: the file is named
    assert main(["--quiet", "simulate", str(tmp_path / "r"), "--camera-path", str(path)]) == 2
    assert "design.json: cell file not found" in capsys.readouterr().err
    cell = ["--camera-path", str(path), "--cell", str(tmp_path / "CELL.json")]
    assert main(["--quiet", "simulate", str(tmp_path / "r"), *cell, "--frames", "20"]) == 2
    assert "set by --camera-path" in capsys.readouterr().err
    broken = tmp_path / "broken.csv"
    broken.write_text(path.read_text().replace("\n", ",x\n", 3).replace("t,A1", "t,A1", 1))
    args = ["--quiet", "simulate", str(tmp_path / "r"), "--camera-path", str(broken)]
    assert main([*args, "--cell", str(tmp_path / "CELL.json")]) == 2
    assert "broken.csv:" in capsys.readouterr().err
    # the recording: images at the path's times, the truth on the path
    assert main(["--quiet", "simulate", str(tmp_path / "rec"), *cell]) == 0
    rec = read_recording(tmp_path / "rec")
    assert len(rec.image_index[2]) == 8
    np.testing.assert_allclose(rec.image_index[1], spec.times - spec.times[0], atol=1e-6)
    truth = read_poses(tmp_path / "rec" / "truth" / "camera_pose.csv")
    T_ref = [np.asarray(camera_pose(chain, qq, spec.T_f_c, spec.T_w_base)) for qq in q_read]
    np.testing.assert_allclose(truth.p, np.stack(T_ref)[:, :3, 3], atol=1e-9)

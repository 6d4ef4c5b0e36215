"""``jaxtraj design``: CELL.json checks and bad input (exit 2, one clear message).

The design itself is tested in test_design_joint.py; these cases fail before it runs.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from jaxtraj.cli import main
from jaxtraj.design_command import example_cell
from jaxtraj.io.cell import cell_from_dict, read_cell


def _cell(**changes) -> dict:
    data = example_cell(frames=12).to_dict()
    data.update(changes)
    return data


def _run(tmp_path, capsys, data=None, text=None, extra=()):
    path = tmp_path / "cell.json"
    path.write_text(text if text is not None else json.dumps(data, indent=2))
    code = main(["design", str(path), str(tmp_path / "out"), *extra])
    return code, capsys.readouterr().err.strip()


def test_example_cell_round_trips_through_json(tmp_path):
    spec = example_cell(frames=12)
    path = tmp_path / "cell.json"
    path.write_text(json.dumps(spec.to_dict()))
    again = read_cell(path)
    np.testing.assert_allclose(again.predicted, spec.predicted, atol=1e-12)
    np.testing.assert_allclose(again.camera_start, spec.camera_start, atol=1e-12)
    np.testing.assert_allclose(again.half_fov, spec.half_fov, atol=1e-12)
    assert again.robot == "kr16_2" and again.k == 8 and again.starts == 8
    # the workpiece robot's curve: about 0.4-0.6 m across, 1.6-2.1 m in front of the KR 16
    extent = np.ptp(spec.predicted, axis=0)
    assert 0.3 < np.max(extent) < 0.8
    assert 1.5 < spec.predicted[:, 0].min() and spec.predicted[:, 0].max() < 2.2


def test_cell_limits_replace_the_robots_and_round_trip(tmp_path):
    """A cell's velocity, acceleration and jerk limits (e.g. reduced speed) survive
    CELL.json and replace the shipped robot's in the design's chain."""
    from jaxtraj.design_command import _chain
    from jaxtraj.io.urdf import load_robot

    shipped = load_robot("kr16_2")
    data = _cell()
    data["limits"]["velocity_deg_s"] = [50.0] * 6
    data["limits"]["jerk_deg_s3"] = [900.0, 900.0, 900.0, 1800.0, 1800.0, 1800.0]
    path = tmp_path / "cell.json"
    path.write_text(json.dumps(data))
    spec = read_cell(path)
    again = cell_from_dict(spec.to_dict())
    for s in (spec, again):
        chain = _chain(s)
        np.testing.assert_allclose(np.degrees(chain.velocity), 50.0)
        np.testing.assert_allclose(np.degrees(chain.jerk)[[0, 5]], [900.0, 1800.0])
        np.testing.assert_allclose(chain.acceleration, shipped.acceleration)
    assert np.all(shipped.velocity > np.radians(150.0))


@pytest.mark.parametrize(
    "kind, pattern",
    [
        ("json", r"cell\.json, line 3: malformed JSON"),
        ("robot", r"cell\.json: robot: unknown robot 'kr5'; known robots: kr16_2, kr60_3"),
        ("empty", r"'prediction' is empty"),
        ("limits", r"start: joint_a2 = 50\.0 deg is outside its limits -155 \.\. 35 deg"),
        ("key", r"unknown key\(s\) \['robt'\]"),
        ("velocity", r"'limits\.velocity_deg_s': expected positive values"),
        ("shape", r"'T_f_c': expected shape \(4, 4\)"),
    ],
)
def test_bad_input_exits_2_with_one_clear_message(tmp_path, capsys, kind, pattern):
    text = None
    data = _cell()
    if kind == "json":
        text = '{\n  "robot": "kr16_2",\n  "K": [1, 2,,\n}'
    elif kind == "robot":
        data["robot"] = "kr5"
    elif kind == "empty":
        data["prediction"] = {"times": [], "points": []}
    elif kind == "limits":
        data["start"] = {"q_deg": [0, 50, 90, 0, 0, 0]}
    elif kind == "key":
        data["robt"] = "kr16_2"
    elif kind == "velocity":
        data["limits"]["velocity_deg_s"] = [100, 100, 0, 100, 100, 100]
    elif kind == "shape":
        data["T_f_c"] = np.eye(3).tolist()
    code, err = _run(tmp_path, capsys, data, text)
    assert code == 2
    assert err.startswith("jaxtraj design: error: ") and len(err.splitlines()) == 1
    assert re.search(pattern, err), err
    assert not (tmp_path / "out").exists()


def test_cell_or_example_but_not_both(tmp_path, capsys):
    assert main(["design", str(tmp_path / "out")]) == 2
    assert "give either CELL.json or --example" in capsys.readouterr().err
    with pytest.raises(ValueError, match=r"'design\.objective'"):
        cell_from_dict(_cell(design={"objective": "speed"}))
    with pytest.raises(ValueError, match=r"'estimator\.method': expected 'dct'"):
        cell_from_dict(_cell(estimator={"method": "kalman"}))
    with pytest.raises(ValueError, match=r"'estimator\.order' belongs to method 'smoother'"):
        cell_from_dict(_cell(estimator={"method": "dct", "order": 2}))
    with pytest.raises(ValueError, match=r"'estimator\.order': expected 1 or 2"):
        cell_from_dict(_cell(estimator={"method": "smoother", "order": 3}))
    spec = cell_from_dict(_cell(estimator={"method": "smoother", "order": 1}))
    assert (spec.method, spec.order) == ("smoother", 1)
    assert cell_from_dict(spec.to_dict()).to_dict() == spec.to_dict()


def test_design_example_writes_its_files(tmp_path):
    """``jaxtraj design --example`` (12 images, one start) writes a joint path within the
    limits, the same path at the 12 ms controller cycle, the camera poses the robot
    reaches on it, and design.json, whose cell reads back."""
    from jaxtraj.design_command import _chain
    from jaxtraj.robot.kinematics import camera_pose

    out = tmp_path / "d"
    args = ["design", "--example", str(out), "--frames", "12", "--starts", "1", "--no-plots"]
    code = main(args)
    report = json.loads((out / "design.json").read_text())
    assert code == 0 and report["max_violation"] <= 1e-3, report["max_violation"]
    assert len(report["starts"]["converged"]) == 1
    assert max(report["fine_grid_violation"].values()) <= 1e-3, report["fine_grid_violation"]
    assert report["expected_worst_frame_error_m"] >= report["expected_mean_error_m"] > 0
    spec = read_cell(out / "design.json")
    np.testing.assert_allclose(spec.predicted, example_cell(frames=12).predicted, atol=1e-9)
    path = np.loadtxt(out / "joint_path.csv", delimiter=",", skiprows=1)
    assert path.shape == (12, 7)
    np.testing.assert_allclose(path[:, 0], spec.times, atol=1e-6)
    limits = report["joint_limits"]
    assert np.all(path[:, 1:] >= limits["lower_deg"]) and np.all(path[:, 1:] <= limits["upper_deg"])
    ipo = np.loadtxt(out / "joint_path_ipo.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(np.diff(ipo[:, 0]), 0.012, atol=1e-6)
    assert ipo[0, 0] == spec.times[0] and ipo[-1, 0] > spec.times[-1] - 0.012
    np.testing.assert_allclose(ipo[0, 1:], path[0, 1:], atol=1e-5)  # both start at q0
    # the same path: the 12 ms samples interpolate the images' axes (up to the last cycle)
    inside = path[:, 0] <= ipo[-1, 0]
    assert inside.sum() >= 11
    for j in range(1, 7):
        fit = np.interp(path[inside, 0], ipo[:, 0], ipo[:, j])
        np.testing.assert_allclose(fit, path[inside, j], atol=0.02)
    tum = np.loadtxt(out / "camera_poses.tum")
    assert tum.shape == (12, 8)
    np.testing.assert_allclose(np.linalg.norm(tum[:, 4:], axis=1), 1.0, atol=1e-6)
    chain = _chain(spec)
    centres = [
        np.asarray(camera_pose(chain, np.radians(q), spec.T_f_c, spec.T_w_base))[:3, 3]
        for q in path[:, 1:]
    ]
    np.testing.assert_allclose(tum[:, 1:4], centres, atol=1e-5)

"""The ``jaxtraj`` command on folders: bad input, atomic outputs, round trips, ``--help``.

Every bad-input case must end with exit code 2 and one line on stderr that names the file
(and, for CSV files, the line) and the problem. One small simulated recording (12 images)
is built per module and copied into each test before it is changed.
"""

from __future__ import annotations

import json
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import jaxtraj.sim.cell
from jaxtraj.cli import EXIT_OK, EXIT_USAGE, main
from jaxtraj.io import read_tum
from jaxtraj.io.formats import read_poses
from jaxtraj.pipeline.steps import step_simulate

FRAMES, DURATION, SEED = 12, 2.0, 3
BLANK_FRAME = 5

SUBCOMMAND_OPTIONS = {
    "simulate": ("--frames", "--duration", "--seed", "--latency-known"),
    "calibrate": ("recording",),
    "fuse": ("--out", "--latency", "--no-smoother"),
    "reconstruct": ("--out", "--pose-method", "--track-method", "--k"),
    "evaluate": ("--out", "--no-plots", "--max-position-mm", "--max-orientation-deg"),
    "demo": ("--out", "--frames", "--seed", "--paper", "--method", "--noise"),
}


def _build(root: Path) -> None:
    """Simulate, calibrate and fuse a small recording in ``root / "rec"``; pickle its cell."""
    folder = root / "rec"
    cells = []
    real = jaxtraj.sim.cell.simulate_cell

    def keep(*args, **kwargs):
        cells.append(real(*args, **kwargs))
        return cells[-1]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(jaxtraj.sim.cell, "simulate_cell", keep)
        step_simulate(folder, frames=FRAMES, duration=DURATION, seed=SEED)
    assert len(cells) == 1
    assert main(["calibrate", str(folder)]) == EXIT_OK
    assert main(["fuse", str(folder)]) == EXIT_OK
    assert (folder / "results" / "fusion.json").is_file()
    (root / "cell.pkl").write_bytes(pickle.dumps(cells[0]))


@pytest.fixture(scope="module")
def built(build_once):
    """A simulated recording after ``calibrate`` and ``fuse``, and its simulated cell.

    Returns ``(folder, cell)``; tests copy the folder (never change it). The workers of
    pytest-xdist share one build, as simulating and compiling the fusion take most of this
    file's time.
    """
    root = build_once("cli_pipeline", _build)
    return root / "rec", pickle.loads((root / "cell.pkl").read_bytes())


@pytest.fixture
def rec(built, tmp_path, capsys) -> Path:
    """A fresh copy of the built recording (camera.json and fused camera poses present)."""
    folder = tmp_path / "rec"
    shutil.copytree(built[0], folder)
    capsys.readouterr()  # drop what building the fixture printed
    return folder


def _edit_line(path: Path, line: int, edit) -> None:
    """Replace 1-based ``line`` of a text file by ``edit(cells)`` (cells split at commas)."""
    lines = path.read_text().split("\n")
    lines[line - 1] = ",".join(edit(lines[line - 1].split(",")))
    path.write_text("\n".join(lines))


def _set_cell(path: Path, line: int, column: int, value: str) -> None:
    def edit(cells):
        cells[column] = value
        return cells

    _edit_line(path, line, edit)


def _cell(path: Path, line: int, column: int) -> str:
    return path.read_text().split("\n")[line - 1].split(",")[column]


def _usage_error(argv: list[str], capsys) -> str:
    """Run ``main(argv)``, check exit code 2 and a one-line message; return that line."""
    code = main(argv)
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    assert code == EXIT_USAGE, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"jaxtraj {argv[0]}: error: "), err
    return lines[0]


# ------------------------------------------------------------------ bad input: exit code 2


def test_missing_imu_csv(rec, capsys):
    (rec / "imu.csv").unlink()
    msg = _usage_error(["fuse", str(rec)], capsys)
    assert "imu.csv" in msg and "no such file" in msg


def test_robot_row_with_too_few_cells(rec, capsys):
    _edit_line(rec / "robot.csv", 5, lambda cells: cells[:-1])
    msg = _usage_error(["fuse", str(rec)], capsys)
    assert "robot.csv:5:" in msg and "expected 8 cells" in msg and "got 7" in msg


def test_non_number_cell(rec, capsys):
    _set_cell(rec / "imu.csv", 5, 2, "1.0x")
    msg = _usage_error(["fuse", str(rec)], capsys)
    assert "imu.csv:5:" in msg and "column wy" in msg and "expected a number" in msg
    assert "'1.0x'" in msg


def test_nan_in_imu_csv(rec, capsys):
    _set_cell(rec / "imu.csv", 7, 5, "nan")
    msg = _usage_error(["fuse", str(rec)], capsys)
    assert "imu.csv:7:" in msg and "column ay" in msg and "finite" in msg and "nan" in msg


def test_duplicate_timestamp_in_robot_csv(rec, capsys):
    path = rec / "robot.csv"
    _set_cell(path, 6, 0, _cell(path, 5, 0))
    msg = _usage_error(["fuse", str(rec)], capsys)
    assert "robot.csv:6:" in msg and "duplicate timestamp" in msg and "line 5" in msg


def test_timestamp_going_backwards_in_imu_csv(rec, capsys):
    path = rec / "imu.csv"
    _set_cell(path, 9, 0, repr(float(_cell(path, 8, 0)) - 0.001))
    msg = _usage_error(["fuse", str(rec)], capsys)
    assert "imu.csv:9:" in msg and "backwards" in msg


@pytest.mark.parametrize("command", ["fuse", "reconstruct"])
def test_malformed_json_in_object_json(rec, capsys, command):
    path = rec / "object.json"
    text = path.read_text()
    path.write_text(text.replace('"marker_size": 0.06,', '"marker_size": 0.06'))
    assert path.read_text() != text
    msg = _usage_error([command, str(rec)], capsys)
    assert "object.json:6:" in msg and "invalid JSON" in msg


def test_unknown_key_in_recording_json(rec, capsys):
    path = rec / "recording.json"
    data = json.loads(path.read_text())
    data["robot_latancy"] = 0.004
    path.write_text(json.dumps(data))
    msg = _usage_error(["fuse", str(rec)], capsys)
    assert "recording.json" in msg and "unknown key" in msg and "robot_latancy" in msg


def test_non_unit_quaternion_in_robot_csv(rec, capsys):
    path = rec / "robot.csv"
    _set_cell(path, 4, 4, repr(2 * float(_cell(path, 4, 4)) + 0.5))
    msg = _usage_error(["fuse", str(rec)], capsys)
    assert "robot.csv:4:" in msg and "unit quaternion" in msg


def test_camera_image_size_not_matching_the_images(rec, capsys):
    path = rec / "camera.json"
    data = json.loads(path.read_text())
    assert data["image_size"] == [640, 480]
    data["image_size"] = [800, 600]
    path.write_text(json.dumps(data))
    assert (rec / "results" / "fusion.json").is_file()  # `jaxtraj fuse` succeeded (fixture)
    msg = _usage_error(["reconstruct", str(rec)], capsys)
    assert "000000.png" in msg and "image size 640x480" in msg and "800x600" in msg
    assert not (rec / "results" / "report.json").exists()


def test_missing_camera_json(rec, capsys):
    (rec / "camera.json").unlink()
    msg = _usage_error(["fuse", str(rec)], capsys)
    assert "camera.json" in msg and "`jaxtraj calibrate" in msg


def test_reconstruct_before_fuse(rec, capsys):
    shutil.rmtree(rec / "results")
    msg = _usage_error(["reconstruct", str(rec)], capsys)
    assert "camera_poses.csv" in msg and "`jaxtraj fuse" in msg
    assert not (rec / "results" / "report.json").exists()


def test_evaluate_without_truth(rec, capsys):
    shutil.rmtree(rec / "truth")
    msg = _usage_error(["evaluate", str(rec), "--no-plots"], capsys)
    assert "truth" in msg and "simulated recording" in msg
    assert not (rec / "results" / "evaluation.json").exists()


# ------------------------------------------------------------------ recoverable input


def test_blank_image_is_reported_not_fatal(rec, capsys):
    import cv2

    path = rec / "images" / f"{BLANK_FRAME:06d}.png"
    shape = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE).shape
    assert cv2.imwrite(str(path), np.full(shape, 128, np.uint8))
    code = main(["reconstruct", str(rec)])
    out = capsys.readouterr()
    assert code == EXIT_OK, out.err
    report = json.loads((rec / "results" / "report.json").read_text())
    reasons = [s["reason"] for s in report["skipped_frames"] if s["frame"] == BLANK_FRAME]
    notes = [n["note"] for n in report["notes"] if n["frame"] == BLANK_FRAME]
    assert "no reference point detected" in notes + reasons, report
    # the blank frame has no pose; the others still do
    assert report["frames"] == FRAMES
    assert report["frames_with_pose"] == FRAMES - 1
    assert f"frame {BLANK_FRAME}" in out.out


# ------------------------------------------------------------------ atomic outputs


def test_interrupted_reconstruct_leaves_no_report(rec, capsys, monkeypatch):
    report = rec / "results" / "report.json"
    assert main(["reconstruct", str(rec)]) == EXIT_OK
    assert json.loads(report.read_text())["frames_with_pose"] == FRAMES
    capsys.readouterr()

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("jaxtraj.pipeline.steps.write_points", interrupt)
    assert main(["reconstruct", str(rec)]) == 130
    assert capsys.readouterr().err.strip() == "jaxtraj: interrupted"
    assert not report.exists()
    assert not [p.name for p in (rec / "results").iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize("existing", [False, True])
def test_interrupted_simulate_leaves_no_folder(built, tmp_path, capsys, monkeypatch, existing):
    target = tmp_path / "sim"
    if existing:  # an earlier recording in its place must survive untouched
        target.mkdir()
        (target / "keep.txt").write_text("earlier")
    cell = built[1]
    monkeypatch.setattr(jaxtraj.sim.cell, "simulate_cell", lambda config, seed=0: cell)
    import jaxtraj.sim.recording as sim_recording

    calls = []
    real = sim_recording.render

    def render_then_interrupt(*args, **kwargs):
        calls.append(1)
        if len(calls) > 4:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(sim_recording, "render", render_then_interrupt)
    argv = ["simulate", str(target), "--frames", str(FRAMES), "--duration", str(DURATION)]
    assert main([*argv, "--seed", str(SEED)]) == 130
    assert len(calls) == 5
    assert "interrupted" in capsys.readouterr().err
    if existing:
        assert sorted(p.name for p in target.iterdir()) == ["keep.txt"]
    else:
        assert not target.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


# ------------------------------------------------------------------ round trip


def test_fuse_tum_equals_csv(rec):
    # written by `jaxtraj fuse` in the fixture (a second fuse would compile the filter again)
    results = rec / "results"
    csv, tum = read_poses(results / "camera_poses.csv"), read_tum(results / "camera_poses.tum")
    fusion = json.loads((results / "fusion.json").read_text())
    assert fusion["images"] == FRAMES == len(csv.times) == len(tum.times)
    np.testing.assert_allclose(tum.times, csv.times, rtol=0, atol=1e-12)
    np.testing.assert_allclose(tum.p, csv.p, rtol=0, atol=1e-12)
    np.testing.assert_allclose(tum.q, csv.q, rtol=0, atol=1e-12)
    frames, times = np.loadtxt(rec / "images.csv", delimiter=",", skiprows=1, usecols=(0, 1)).T
    np.testing.assert_array_equal(frames, np.arange(FRAMES))
    np.testing.assert_allclose(csv.times, times, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(tum.q, axis=1), 1.0, atol=1e-9)


# ------------------------------------------------------------------ --help, console script


@pytest.mark.parametrize("command", sorted(SUBCOMMAND_OPTIONS))
def test_subcommand_help(command):
    proc = subprocess.run(
        [sys.executable, "-m", "jaxtraj", command, "--help"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(f"usage: jaxtraj {command}")
    for option in SUBCOMMAND_OPTIONS[command]:
        assert option in proc.stdout, option


def test_console_script_help():
    script = shutil.which("jaxtraj")
    if script is None and (Path(sys.executable).parent / "jaxtraj").exists():
        script = str(Path(sys.executable).parent / "jaxtraj")
    if script is None:
        pytest.skip("the `jaxtraj` console script is not installed (pip install -e .)")
    proc = subprocess.run([script, "--help"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("usage: jaxtraj")
    for command in SUBCOMMAND_OPTIONS:
        assert command in proc.stdout

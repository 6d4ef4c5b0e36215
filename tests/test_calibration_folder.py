"""`jaxtraj calibrate DIR` on calibration folders: corners CSV or images, robot pose forms,
partial ChArUco views, a circle grid, eye-to-hand, and bad input."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from jaxtraj.cli import EXIT_FAILED, EXIT_OK, EXIT_USAGE, main
from jaxtraj.io.corners import write_corners
from jaxtraj.io.formats import read_camera
from jaxtraj.io.robot_poses import from_matrices
from jaxtraj.io.tables import write_table
from jaxtraj.sim.calibration_views import render_views, simulate_views
from jaxtraj.sim.render import PlanarTexture, charuco_texture
from jaxtraj.vision.calibration import CalibrationTarget, calibrate_camera

# A ChArUco board of 10 x 7 squares has the 9 x 6 corners of the other calibration tests:
# the bundle adjustment compiles once for (12 views, 54 corners).
CHARUCO = {"kind": "charuco", "cols": 10, "rows": 7, "square": 0.025, "marker": 0.018}
TARGET = CalibrationTarget.from_dict(CHARUCO)
HEAD = {
    "pq": ["x", "y", "z", "qw", "qx", "qy", "qz"],
    "kuka": ["X", "Y", "Z", "A", "B", "C"],
    "rpy": ["x", "y", "z", "roll", "pitch", "yaw"],
    "rotvec": ["x", "y", "z", "rx", "ry", "rz"],
}


def _rot_deg(A, B):
    return float(np.degrees(np.linalg.norm(cv2.Rodrigues(A[:3, :3].T @ B[:3, :3])[0])))


def _write_robot(path, T, form, names=None, **units):
    values = from_matrices(T, form, **units)
    if names is None:
        write_table(path, HEAD[form], list(values.T))
    else:
        write_table(path, ["file", *HEAD[form]], [np.asarray(names), *values.T])


def _corner_folder(tmp_path, s, *, drop=0.3, seed=0, image_size=True):
    """target.json, corners.csv (random partial views, corners outside the image left out)."""
    rng = np.random.default_rng(seed)
    folder = tmp_path / "cal"
    folder.mkdir()
    corners = {}
    W, H = s.image_size
    for k, uv in enumerate(s.uv):
        seen = np.all((uv > 5) & (uv < [W - 5, H - 5]), 1) & (rng.uniform(size=len(uv)) > drop)
        corners[f"view_{k}.png"] = (np.flatnonzero(seen), uv[seen])
    write_corners(folder / "corners.csv", corners)
    target = {**CHARUCO, "image_size": list(s.image_size)} if image_size else CHARUCO
    (folder / "target.json").write_text(json.dumps(target))
    return folder, [f"view_{k}.png" for k in range(len(s.uv))]


def test_corners_csv_rpy_mm_deg_file_column_and_a_skipped_view(tmp_path, capsys):
    s = simulate_views(TARGET.object_points(), views=13, seed=7, pixel_sigma=0.1, inside=0.8)
    folder, names = _corner_folder(tmp_path, s)
    # view_12 shows 4 corners only: listed and skipped.
    text = (folder / "corners.csv").read_text().splitlines()
    keep = [line for line in text if not line.startswith("view_12.png")]
    v12 = [line for line in text if line.startswith("view_12.png")][:4]
    (folder / "corners.csv").write_text("\n".join(keep + v12) + "\n")
    order = np.random.default_rng(1).permutation(13)  # rows in another order than the views
    _write_robot(folder / "robot.csv", s.T_b_f[order], "rpy", [names[k] for k in order],
                 length_unit="mm", angle_unit="deg")  # fmt: skip
    code = main(["calibrate", str(folder), "--robot-format", "rpy", "--length-unit", "mm",
                 "--angle-unit", "deg", "--robot-sigma-mm", "0.2"])  # fmt: skip
    out = capsys.readouterr().out
    assert code == EXIT_OK, out
    assert "skipped view_12.png: 4 ChArUco corners found, need 6" in out
    assert "refined (" in out and "hand-eye: residual" in out
    cam = read_camera(folder / "camera.json")
    assert np.linalg.norm(cam.T_f_c[:3, 3] - s.T_x[:3, 3]) < 1.5e-3  # measured 0.64 mm
    assert _rot_deg(cam.T_f_c, s.T_x) < 0.3  # measured 0.18 deg (cx off by 1.7 px)
    assert abs(cam.K[0, 0] - s.K[0, 0]) < 3 and abs(cam.K[0, 2] - s.K[0, 2]) < 3
    report = json.loads((folder / "calibration.json").read_text())
    he = report["hand_eye"]
    assert set(he["methods"]) == {"tsai", "park", "horaud", "andreff", "daniilidis", "shah", "li"}
    assert he["ok"] and he["limits"] == "derived from the data" and len(report["views_used"]) == 12
    assert he["refined"]["target_spread_position_mm"] < min(
        m["target_spread_position_mm"] for m in he["methods"].values()
    )


def test_rendered_charuco_images_natural_sort_and_kuka(tmp_path, capsys):
    board = charuco_texture(10, 7, 0.025, 0.018, px_per_square=40)
    s = simulate_views(TARGET.object_points(), views=12, seed=3, inside=0.7, distance=(0.3, 0.45))
    folder = tmp_path / "cal"
    folder.mkdir()
    (folder / "target.json").write_text(json.dumps(CHARUCO))
    for k, image in enumerate(render_views(s, board.texture, seed=1, supersample=2)):
        cv2.imwrite(str(folder / f"{k + 1}.png"), image)  # 1.png ... 12.png: no zero padding
    _write_robot(folder / "robot.csv", s.T_b_f, "kuka")  # rows in the views' natural order
    code = main(["calibrate", str(folder)])
    out = capsys.readouterr().out
    assert code == EXIT_OK, out
    cam = read_camera(folder / "camera.json")
    # Measured: 0.12 mm, 0.013 deg, fx off by 0.16 px.
    assert np.linalg.norm(cam.T_f_c[:3, 3] - s.T_x[:3, 3]) < 2e-3
    assert _rot_deg(cam.T_f_c, s.T_x) < 0.3
    assert abs(cam.K[0, 0] - s.K[0, 0]) < 3
    report = json.loads((folder / "calibration.json").read_text())
    partial = [k for k, v in enumerate(s.uv) if not np.all((v > 0) & (v < [640, 480]))]
    assert len(partial) >= 2 and len(report["views_used"]) == 12


def _circle_texture(target, px_per_m=4000.0):
    pts = target.object_points()
    w = np.ptp(pts[:, 0]) + 4 * target.square
    h = np.ptp(pts[:, 1]) + 4 * target.square
    W, H = round(w * px_per_m), round(h * px_per_m)
    w, h = W / px_per_m, H / px_per_m
    img = np.full((H, W), 235, np.uint8)
    shift = 4
    for x, y, _ in pts:
        c = ((x + w / 2) * px_per_m - 0.5, (h / 2 - y) * px_per_m - 0.5)
        centre = tuple(round(v * 2**shift) for v in c)
        r = round(0.3 * target.square * px_per_m * 2**shift)
        cv2.circle(img, centre, r, 20, -1, cv2.LINE_AA, shift)
    return PlanarTexture(img, (w, h), np.diag([1.0, -1.0, -1.0]), np.array([-w / 2, h / 2, 0]))


def test_asymmetric_circle_grid_images():
    target = CalibrationTarget("asymmetric_circles", 4, 11, 0.015)
    s = simulate_views(target.object_points(), views=8, seed=2, distance=(0.35, 0.5))
    images = render_views(s, _circle_texture(target), seed=0, supersample=2)
    result = calibrate_camera(images, target)
    assert result.used == list(range(8)) and not result.skipped
    K = result.calibration.K
    assert abs(K[0, 0] - s.K[0, 0]) < 1 and abs(K[0, 2] - s.K[0, 2]) < 1  # measured 0.02 px
    for k, T in enumerate(s.T_c_t):  # the detected order is the target's point order
        assert np.linalg.norm(result.t_c_t[k] - T[:3, 3]) < 1e-3  # measured 0.06 mm
        assert _rot_deg(np.c_[np.r_[result.R_c_t[k], [[0, 0, 0]]], [0, 0, 0, 1]], T) < 0.5


def test_eye_to_hand_folder(tmp_path, capsys):
    s = simulate_views(TARGET.object_points(), views=12, seed=5, pixel_sigma=0.1,
                       eye_in_hand=False, inside=0.8)  # fmt: skip
    folder, _ = _corner_folder(tmp_path, s, drop=0.1)
    _write_robot(folder / "robot.csv", s.T_b_f, "pq")
    assert main(["calibrate", str(folder), "--eye-to-hand"]) == EXIT_OK
    he = json.loads((folder / "calibration.json").read_text())["hand_eye"]
    T_b_c = np.asarray(he["T_x"])
    assert not he["eye_in_hand"] and np.linalg.norm(T_b_c[:3, 3] - s.T_x[:3, 3]) < 2e-3
    assert read_camera(folder / "camera.json").T_f_c is None
    assert "eye-to-hand" in capsys.readouterr().out


def test_bad_input(tmp_path, capsys):
    s = simulate_views(TARGET.object_points(), views=12, seed=6, pixel_sigma=0.1)
    folder, names = _corner_folder(tmp_path, s, drop=0.0)

    def run(*extra):
        code = main(["calibrate", str(folder), "--no-refine", *extra])
        return code, capsys.readouterr()

    # a robot pose file whose row count does not match the views
    _write_robot(folder / "robot.csv", s.T_b_f[:11], "rotvec")
    code, io = run()
    assert code == EXIT_USAGE and "robot.csv: 11 robot pose rows for 12 views" in io.err
    # degenerate motions: every rotation about one axis (the flange's z)
    T = s.T_b_f.copy()
    for k in range(12):
        T[k, :3, :3] = s.T_b_f[0, :3, :3] @ cv2.Rodrigues(np.array([0, 0, 0.2 * k]))[0]
    _write_robot(folder / "robot.csv", T, "rotvec")
    code, io = run()
    assert code == EXIT_USAGE and "robot.csv: robot poses: all rotations" in io.err
    assert "about one axis (+0.000, +0.000, +1.000)" in io.err
    # two views paired with each other's poses (as a lexicographic sort of unpadded names
    # would): rejected by the limits derived from the data, with the reason
    swapped = s.T_b_f[[0, 2, 1, *range(3, 12)]]
    _write_robot(folder / "robot.csv", swapped, "rotvec")
    code, io = run()
    assert code == EXIT_FAILED and "rejected: the target position implied" in io.out, io.out
    assert "rejected: the limits assume robot pose noise of 0.1 mm and 0.02 deg" in io.out
    # a clear rejection: limits given tighter than the data allow
    _write_robot(folder / "robot.csv", s.T_b_f, "rotvec")
    code, io = run("--max-spread-mm", "0.01")
    assert code == EXIT_FAILED and "rejected: the target position implied by the views" in io.out
    assert "over the limit 0.01 mm" in io.out
    # too few views: corners of two views only
    write_corners(folder / "corners.csv", {n: (np.arange(54), s.uv[k]) for k, n in
                                           enumerate(names[:2])})  # fmt: skip
    (folder / "robot.csv").unlink()
    code, io = run()
    assert (
        code == EXIT_USAGE and "corners.csv: images: the target was found in 2 image(s)" in io.err
    )
    # a corners CSV without the image size; no target description
    (folder / "target.json").write_text(json.dumps(CHARUCO))
    code, io = run()
    assert code == EXIT_USAGE and 'target.json: a corners CSV needs "image_size"' in io.err
    (folder / "target.json").unlink()
    code, io = run()
    assert code == EXIT_USAGE and "target.json: no target description" in io.err


@pytest.mark.parametrize("form", ["pq", "rotvec"])
def test_robot_format_option_is_checked(tmp_path, capsys, form):
    s = simulate_views(TARGET.object_points(), views=12, seed=6, pixel_sigma=0.1)
    folder, _ = _corner_folder(tmp_path, s, drop=0.0)
    _write_robot(folder / "robot.csv", s.T_b_f, form)
    other = "kuka"
    code = main(["calibrate", str(folder), "--no-refine", "--robot-format", other])
    assert code == EXIT_USAGE
    assert "robot.csv:1: missing header column(s) X, Y, Z, A, B, C" in capsys.readouterr().err


def test_options_are_checked():
    from jaxtraj.pipeline.calibrate import CalibrationOptions

    with pytest.raises(ValueError, match="method: expected one of"):
        CalibrationOptions(method="magic")
    with pytest.raises(ValueError, match="robot_sigma"):
        CalibrationOptions(robot_sigma=(1e-4, -1.0))
    with pytest.raises(ValueError, match="min_corners"):
        CalibrationOptions(min_corners=3)
    with pytest.raises(ValueError, match="max_position_spread"):
        CalibrationOptions(max_position_spread=0.0)

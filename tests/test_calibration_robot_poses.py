"""Robot pose forms of calibration views, pairing views with poses, the corners CSV."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from jaxtraj.io.corners import read_corners, write_corners
from jaxtraj.io.formats import kuka_to_pose
from jaxtraj.io.records import quat_to_matrix
from jaxtraj.io.robot_poses import (
    FORMS,
    from_matrices,
    natural_key,
    pair_views,
    read_robot_poses,
    to_matrices,
)
from jaxtraj.io.tables import RecordingError, write_table

_HEADERS = {
    "pq": ["x", "y", "z", "qw", "qx", "qy", "qz"],
    "kuka": ["X", "Y", "Z", "A", "B", "C"],
    "rpy": ["x", "y", "z", "roll", "pitch", "yaw"],
    "rotvec": ["x", "y", "z", "rx", "ry", "rz"],
    "matrix": [f"m{r}{c}" for r in range(3) for c in range(4)],
}


def _poses(rng, n=20):
    T = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        T[k, :3, :3] = cv2.Rodrigues(rng.uniform(-3, 3, 3))[0]
    T[:, :3, 3] = rng.uniform(-1.5, 1.5, (n, 3))
    return T


@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize("units", [("m", "rad"), ("mm", "deg")])
def test_each_form_round_trips_through_a_file(tmp_path, rng, form, units):
    T = _poses(rng)
    length, angle = units
    values = from_matrices(T, form, length_unit=length, angle_unit=angle)
    np.testing.assert_allclose(
        to_matrices(values, form, length_unit=length, angle_unit=angle), T, atol=1e-12
    )
    path = tmp_path / "robot.csv"
    write_table(path, ["t", *_HEADERS[form]], [np.arange(len(T)) * 0.0, *values.T])
    back = read_robot_poses(path, "auto", length_unit=length, angle_unit=angle)
    np.testing.assert_allclose(back.T_b_f, T, atol=1e-12)
    assert back.files is None and back.lines.tolist() == list(range(2, len(T) + 2))


def test_forms_agree_with_each_other_and_with_references(rng):
    T = _poses(rng)
    for a in FORMS:
        for b in FORMS:
            via = to_matrices(from_matrices(to_matrices(from_matrices(T, a), a), b), b)
            np.testing.assert_allclose(via, T, atol=1e-12)
    # KUKA: the recording reader's conversion (mm, deg, Rz(A) Ry(B) Rx(C)).
    p, q = kuka_to_pose(from_matrices(T, "kuka"))
    np.testing.assert_allclose(quat_to_matrix(q), T[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(p, T[:, :3, 3], atol=1e-12)
    # rotvec: OpenCV's Rodrigues.
    w = from_matrices(T, "rotvec")[:, 3:]
    for k in range(len(T)):
        np.testing.assert_allclose(cv2.Rodrigues(w[k])[0], T[k, :3, :3], atol=1e-12)
    # rpy: fixed axes x, then y, then z. Roll 90 deg alone turns y into z.
    R = to_matrices(np.array([[0, 0, 0, np.pi / 2, 0, 0]]), "rpy")[0, :3, :3]
    np.testing.assert_allclose(R @ [0, 1, 0], [0, 0, 1], atol=1e-15)
    # roll then yaw (fixed axes): x -> (yaw 90) y; y -> (roll 90) z -> (yaw) z.
    R = to_matrices(np.array([[0, 0, 0, 90, 0, 90]]), "rpy", angle_unit="deg")[0, :3, :3]
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(R @ [0, 1, 0], [0, 0, 1], atol=1e-15)


def test_natural_sort_and_pairing(tmp_path, rng):
    names = ["12.png", "4.png", "view_2.png", "1.png", "view_10.png"]
    assert sorted(names, key=natural_key) == [
        "1.png", "4.png", "12.png", "view_2.png", "view_10.png",
    ]  # fmt: skip
    T = _poses(rng, 5)
    path = tmp_path / "robot.csv"
    write_table(path, _HEADERS["rotvec"], list(from_matrices(T, "rotvec").T))
    ordered, poses = pair_views(names, read_robot_poses(path))
    assert ordered[2] == "12.png"
    np.testing.assert_allclose(poses, T, atol=1e-12)
    # An explicit file column, rows in another order (stems allowed).
    perm = [3, 0, 4, 1, 2]
    files = np.array(["12", "1.png", "view_10.png", "4.png", "view_2.png"])
    write_table(path, ["file", *_HEADERS["pq"]], [files, *from_matrices(T[perm], "pq").T])
    ordered, poses = pair_views(names, read_robot_poses(path, "pq"))
    row = {"12.png": 0, "1.png": 1, "view_10.png": 2, "4.png": 3, "view_2.png": 4}
    for name, pose in zip(ordered, poses, strict=True):
        np.testing.assert_allclose(pose, T[perm[row[name]]], atol=1e-12)
    with pytest.raises(RecordingError, match=r"robot\.csv: no row with file 'extra\.png'"):
        pair_views([*names, "extra.png"], read_robot_poses(path))


def test_pairing_errors(tmp_path, rng):
    path = tmp_path / "robot.csv"
    write_table(path, _HEADERS["rotvec"], list(from_matrices(_poses(rng, 3), "rotvec").T))
    poses = read_robot_poses(path)
    with pytest.raises(RecordingError, match=r"robot\.csv: 3 robot pose rows for 4 views"):
        pair_views(["a1.png", "a2.png", "a3.png", "a4.png"], poses)
    with pytest.raises(RecordingError, match=r"'v01\.png' and 'v1\.png' have the same natural"):
        pair_views(["v1.png", "v01.png", "v2.png"], poses)


def test_reader_errors_name_file_and_line(tmp_path):
    path = tmp_path / "robot.csv"
    path.write_text("x,y,z,qw,qx,qy,qz\n0,0,0,1,0,0,0\n0,0,0,2,0,0,0\n")
    with pytest.raises(RecordingError, match=r"robot\.csv:3: quaternion norm 2"):
        read_robot_poses(path)
    path.write_text("x,y,z,a,b,c\n0,0,0,1,0,0\n")
    with pytest.raises(RecordingError, match=r"robot\.csv:1: robot pose header x,y,z,a,b,c"):
        read_robot_poses(path)
    path.write_text(",".join(_HEADERS["matrix"]) + "\n" + ",".join(["2"] * 12) + "\n")
    with pytest.raises(RecordingError, match=r"robot\.csv:2: not a rotation"):
        read_robot_poses(path)
    path.write_text("file,x,y,z,rx,ry,rz\na.png,0,0,0,0,0,0\na.png,0,0,0,0,0,0\n")
    with pytest.raises(RecordingError, match=r"robot\.csv:3: file 'a\.png' listed twice"):
        read_robot_poses(path)
    with pytest.raises(ValueError, match="form"):
        read_robot_poses(path, "euler")


def test_corners_csv_round_trip_and_errors(tmp_path, rng):
    corners = {
        "b.png": (np.array([3, 0, 7]), rng.uniform(0, 600, (3, 2))),
        "a.png": (np.array([1, 2]), rng.uniform(0, 600, (2, 2))),
    }
    path = tmp_path / "corners.csv"
    write_corners(path, corners)
    back = read_corners(path)
    assert list(back) == ["b.png", "a.png"]
    order = np.argsort(corners["b.png"][0])
    np.testing.assert_array_equal(back["b.png"][0], [0, 3, 7])
    np.testing.assert_array_equal(back["b.png"][1], corners["b.png"][1][order])
    path.write_text("view,id,u,v\na,1,2.0,3.0\na,1,4.0,5.0\n")
    with pytest.raises(RecordingError, match=r"corners\.csv:3: corner id 1 of view 'a' repeated"):
        read_corners(path)
    path.write_text("view,id,u,v\na,x,2.0,3.0\n")
    with pytest.raises(RecordingError, match=r"corners\.csv:2"):
        read_corners(path)

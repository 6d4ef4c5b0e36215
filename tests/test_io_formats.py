"""File formats of a recording: exact round trips, clear errors with file and line."""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxtraj.io.formats import (
    ImuNoise,
    ImuSamples,
    RecordingMeta,
    RobotNoise,
    kuka_to_pose,
    pose_to_kuka,
    read_camera,
    read_detections,
    read_image_index,
    read_imu,
    read_meta,
    read_object,
    read_points,
    read_poses,
    read_robot,
    read_tum,
    write_camera,
    write_detections,
    write_image_index,
    write_imu,
    write_json,
    write_meta,
    write_object,
    write_points,
    write_poses,
    write_robot,
    write_tum,
)
from jaxtraj.io.recording import Recording, Truth, read_recording, read_truth, write_recording
from jaxtraj.io.records import CameraCalibration, Detections, ObjectModel, PoseStream
from jaxtraj.io.tables import (
    RecordingError,
    atomic_folder,
    atomic_write_text,
    read_table,
    write_table,
)

RNG = np.random.default_rng(20261123)


def _random_quats(n: int, rng=RNG) -> np.ndarray:
    q = rng.standard_normal((n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _poses(n: int = 7, rng=RNG) -> PoseStream:
    t = np.cumsum(rng.uniform(0.01, 0.02, n)) + 1 / 3
    return PoseStream(times=t, p=rng.standard_normal((n, 3)), q=_random_quats(n, rng))


def _camera(with_T: bool = True) -> CameraCalibration:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    T[:3, 3] = [0.01, 0.02, 0.1 / 3]
    return CameraCalibration(
        K=[[600.1 / 3, 0.0, 320.25], [0.0, 601.7, 239.9], [0.0, 0.0, 1.0]],
        dist=[-0.1, 0.01 / 3, 1e-4, -2e-4, 0.0],
        image_size=(640, 480),
        rms_px=0.1234,
        T_f_c=T if with_T else None,
        T_i_c=np.linalg.inv(T) if with_T else None,
    )


def _model() -> ObjectModel:
    return ObjectModel(
        ids=np.array([7, 3, 11, 5]),
        points=RNG.uniform(-0.2, 0.2, (4, 3)),
        assembly_point=[0.01, 0.0, 1 / 30],
        marker_dictionary="DICT_4X4_50",
        marker_size=0.06,
    )


def _assert_error(excinfo, path: Path, line: int | None, *words: str) -> None:
    err = excinfo.value
    assert isinstance(err, RecordingError) and isinstance(err, ValueError)
    assert err.path == Path(path)
    assert err.line == line
    prefix = f"{path}:{line}: " if line is not None else f"{path}: "
    assert str(err).startswith(prefix), str(err)
    for word in words:
        assert word in str(err), (word, str(err))


# ----------------------------------------------------------------------- tables


def test_read_table_header_comments_whitespace_aliases(tmp_path):
    path = tmp_path / "a.csv"
    path.write_text(
        "# recorded by hand\n"
        "#timestamp [ns], value ,name,extra\n"
        "\n"
        "30, 1.5 ,b,x\n"
        "# a comment between rows\n"
        "10,-2e-3,a ,y\n"
        "20,  nan ,c,z\n"
    )
    tab = read_table(
        path,
        {"t": "int64ns", "v": "float", "name": "str"},
        aliases={"t": ["timestamp [ns]"], "v": ["value"]},
        sort_key="t",
        strictly_increasing="t",
        allow_nonfinite=["v"],
    )
    assert tab["t"].tolist() == [10, 20, 30]
    assert tab["v"][0] == -2e-3 and math.isnan(tab["v"][1]) and tab["v"][2] == 1.5
    assert tab["name"].tolist() == ["a", "c", "b"]
    assert tab.lines.tolist() == [6, 7, 4]


def test_write_table_round_trip_exact_and_fast(tmp_path):
    n = 20_000
    t = np.cumsum(RNG.uniform(1e-3, 2e-3, n)) + 1e9 / 7
    x = RNG.standard_normal(n) * 10.0 ** RNG.integers(-30, 30, n)
    k = RNG.integers(-(2**62), 2**62, n)
    path = tmp_path / "t.csv"
    write_table(path, ["t", "x", "k"], [t, x, k])
    start = time.perf_counter()
    tab = read_table(path, {"t": "float", "x": "float", "k": "int"}, strictly_increasing="t")
    elapsed = time.perf_counter() - start
    np.testing.assert_array_equal(tab["t"], t)
    np.testing.assert_array_equal(tab["x"], x)
    np.testing.assert_array_equal(tab["k"], k)
    assert elapsed < 1.0  # 100k rows x 7 columns take ~0.4 s on one slow core
    assert [p.name for p in tmp_path.iterdir()] == ["t.csv"]


@pytest.mark.parametrize(
    "text, line, words",
    [
        ("t,x\n", None, ["no data rows"]),
        ("", None, ["empty file"]),
        ("t,y\n1,2\n", 1, ["missing header column(s) x", "found t, y"]),
        ("t,x\n1,2\n2\n", 3, ["expected 2 cells", "got 1"]),
        ("t,x\n1,2\n2,3,4\n", 3, ["expected 2 cells", "got 3"]),
        ("t,x\n1,2\n\n2,abc\n", 4, ["column x", "'abc'"]),
        ("t,x\n1,2\n2,\n", 3, ["column x", "''"]),
        ("t,x\n1,2\n2,nan\n", 3, ["column x", "finite", "nan"]),
        ("t,x\n1,2\n2,-inf\n", 3, ["column x", "finite"]),
        ("t,x\n1,2\n2,3\n2,4\n", 4, ["column t", "duplicate timestamp 2.0", "line 3"]),
        ("t,x\n1,2\n3,3\n2.5,4\n", 4, ["column t", "timestamp goes backwards (2.5 after 3.0)"]),
    ],
)
def test_read_table_errors_name_file_and_line(tmp_path, text, line, words):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(RecordingError) as excinfo:
        read_table(path, {"t": "float", "x": "float"}, strictly_increasing="t")
    _assert_error(excinfo, path, line, *words)


def test_read_table_int_errors_and_missing_file(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text("frame,t\n1,0.5\n2.0,0.6\n")
    with pytest.raises(RecordingError) as excinfo:
        read_table(path, {"frame": "int", "t": "float"})
    _assert_error(excinfo, path, 3, "column frame", "integer", "'2.0'")
    with pytest.raises(RecordingError) as excinfo:
        read_table(tmp_path / "nope.csv", {"t": "float"})
    _assert_error(excinfo, tmp_path / "nope.csv", None, "no such file")
    assert str(excinfo.value) == f"{tmp_path / 'nope.csv'}: no such file"


# ---------------------------------------------------------------------- atomic


def test_atomic_write_text_leaves_no_part_file(tmp_path, monkeypatch):
    path = tmp_path / "out.txt"
    atomic_write_text(path, "first\n")
    atomic_write_text(path, "second\n")
    assert path.read_text() == "second\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]

    def fail(*args):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        atomic_write_text(path, "third\n")
    monkeypatch.undo()
    assert path.read_text() == "second\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_atomic_folder_replaces_on_success_keeps_old_on_error(tmp_path):
    final = tmp_path / "rec"
    with atomic_folder(final) as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith(".rec.part-")
        (tmp / "a.txt").write_text("one")
    assert (final / "a.txt").read_text() == "one"

    with pytest.raises(RuntimeError, match="interrupted"):
        with atomic_folder(final) as tmp:
            (tmp / "a.txt").write_text("two")
            (tmp / "b.txt").write_text("half")
            raise RuntimeError("interrupted")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]
    assert sorted(p.name for p in final.iterdir()) == ["a.txt"]
    assert (final / "a.txt").read_text() == "one"

    with atomic_folder(final) as tmp:
        (tmp / "c.txt").write_text("three")
    assert sorted(p.name for p in final.iterdir()) == ["c.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]


# ------------------------------------------------------------------------- IMU


def test_imu_round_trip_exact(tmp_path):
    n = 50
    imu = ImuSamples(
        t=np.cumsum(RNG.uniform(0.004, 0.006, n)) + 0.1,
        gyro=RNG.standard_normal((n, 3)),
        accel=RNG.standard_normal((n, 3)) * 9.81,
    )
    write_imu(tmp_path / "imu.csv", imu)
    back = read_imu(tmp_path / "imu.csv")
    np.testing.assert_array_equal(back.t, imu.t)
    np.testing.assert_array_equal(back.gyro, imu.gyro)
    np.testing.assert_array_equal(back.accel, imu.accel)
    assert back.t0_ns is None


def test_imu_euroc_header_keeps_nanosecond_precision(tmp_path):
    path = tmp_path / "imu.csv"
    path.write_text(
        "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
        "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n"
        "1403636579758555392,-0.099134701513277898,0.14730578886832138,0.02722713633111154,"
        "8.1476917083333333,-0.37592158333333331,-2.4026292499999999\n"
        "1403636579763555584,-0.099134701513277898,0.14032447186034408,0.029321531433504529,"
        "8.033280791666666,-0.40861041666666664,-2.4026292499999999\n"
        "1403636579768555520,-0.098436569812480182,0.12775810124598494,0.037699111843077518,"
        "7.8861810416666662,-0.42495483333333334,-2.4353180833333332\n"
    )
    imu = read_imu(path)
    assert imu.t0_ns == 1403636579758555392
    np.testing.assert_array_equal(imu.t, [0.0, 0.005000192, 0.010000128])
    assert imu.gyro[1, 2] == 0.029321531433504529 and imu.accel[2, 0] == 7.8861810416666662
    shifted = read_imu(path, t0_ns=1403636579758555392 - 10**9)
    np.testing.assert_array_equal(shifted.t, [1.0, 1.005000192, 1.010000128])


# --------------------------------------------------------------------- poses


def test_pose_csv_and_robot_round_trip(tmp_path):
    poses = _poses()
    write_poses(tmp_path / "p.csv", poses)
    write_robot(tmp_path / "r.csv", poses)
    for back in (read_poses(tmp_path / "p.csv"), read_robot(tmp_path / "r.csv")):
        np.testing.assert_array_equal(back.times, poses.times)
        np.testing.assert_array_equal(back.p, poses.p)
        np.testing.assert_allclose(back.q, poses.q, rtol=0, atol=4e-16)


def test_robot_kuka_round_trip(tmp_path):
    poses = _poses(20)
    write_robot(tmp_path / "robot.csv", poses, kuka=True)
    assert (tmp_path / "robot.csv").read_text().startswith("t,X,Y,Z,A,B,C\n")
    back = read_robot(tmp_path / "robot.csv")
    np.testing.assert_array_equal(back.times, poses.times)
    np.testing.assert_allclose(back.p, poses.p, rtol=0, atol=1e-15)
    sign = np.sign(np.sum(back.q * poses.q, axis=1, keepdims=True))
    np.testing.assert_allclose(back.q * sign, poses.q, rtol=0, atol=1e-14)


def test_kuka_matches_scipy_intrinsic_zyx():
    abc = np.array(
        [
            [30.0, 20.0, -10.0],
            [-170.0, 45.0, 100.0],
            [179.9, -89.0, 5.0],
            [10.0, 90.0, 0.0],  # gimbal lock
            [-35.0, -90.0, 0.0],  # gimbal lock
            [0.0, 0.0, 0.0],
        ]
    )
    abc = np.concatenate([abc, RNG.uniform([-180, -90, -180], [180, 90, 180], (20, 3))])
    xyz = RNG.uniform(-2000, 2000, (abc.shape[0], 3))
    p, q = kuka_to_pose(np.concatenate([xyz, abc], 1))
    np.testing.assert_allclose(p, xyz / 1000, rtol=1e-15)
    R_ref = Rotation.from_euler("ZYX", abc, degrees=True).as_matrix()
    R = Rotation.from_quat(np.roll(q, -1, axis=1)).as_matrix()
    np.testing.assert_allclose(R, R_ref, rtol=0, atol=1e-14)
    assert np.all(q[:, 0] >= 0)
    # back to KUKA: the same angles away from gimbal lock, the same rotation everywhere
    v = pose_to_kuka(p, q)
    np.testing.assert_allclose(v[:, :3], xyz, rtol=1e-15)
    regular = np.abs(abc[:, 1]) < 89.5
    np.testing.assert_allclose(v[regular, 3:], abc[regular], rtol=0, atol=1e-9)
    R_back = Rotation.from_euler("ZYX", v[:, 3:], degrees=True).as_matrix()
    np.testing.assert_allclose(R_back, R_ref, rtol=0, atol=1e-13)
    assert np.all(v[:, 4] <= 90) and np.all(v[:, 4] >= -90)
    assert np.all(np.abs(v[:, [3, 5]]) <= 180)


@pytest.mark.parametrize("b_deg, a_minus_c", [(90.0, 25.0), (-90.0, -70.0)])
def test_pose_to_kuka_at_gimbal_lock_puts_turn_into_a(b_deg, a_minus_c):
    # At B = +-90 only A -+ C matters; the rotation must survive and C must be 0.
    abc = np.array([[a_minus_c + 40.0, b_deg, 40.0]])
    R_ref = Rotation.from_euler("ZYX", abc, degrees=True)
    q = np.roll(R_ref.as_quat(), 1, axis=1)
    v = pose_to_kuka(np.zeros((1, 3)), q)
    assert abs(v[0, 4] - b_deg) < 1e-6 and abs(v[0, 5]) < 1e-6
    R_back = Rotation.from_euler("ZYX", v[:, 3:], degrees=True).as_matrix()
    np.testing.assert_allclose(R_back, R_ref.as_matrix(), rtol=0, atol=1e-12)


def test_robot_non_unit_quaternion_and_unknown_header(tmp_path):
    path = tmp_path / "robot.csv"
    path.write_text("t,x,y,z,qw,qx,qy,qz\n0,0,0,0,1,0,0,0\n0.1,0,0,0,1.0011,0,0,0\n")
    with pytest.raises(RecordingError) as excinfo:
        read_robot(path)
    _assert_error(excinfo, path, 3, "quaternion norm 1.0011", "unit quaternion")
    path.write_text("t,x,y,z,qw,qx,qy,qz\n0,0,0,0,1,0,0,0\n0.1,0,0,0,1.0009,0,0,0\n")
    assert np.allclose(read_robot(path).q[1], [1, 0, 0, 0], atol=0)
    path.write_text("t,x,y,z,rx,ry,rz\n0,0,0,0,0,0,0\n")
    with pytest.raises(RecordingError) as excinfo:
        read_robot(path)
    _assert_error(excinfo, path, 1, "t,X,Y,Z,A,B,C", "t,x,y,z,qw,qx,qy,qz")


def test_tum_quaternion_order(tmp_path):
    path = tmp_path / "traj.tum"
    q_xyzw = np.array([0.1, 0.2, 0.3, 0.9])
    q_xyzw = q_xyzw / np.linalg.norm(q_xyzw)
    path.write_text(
        "# timestamp tx ty tz qx qy qz qw\n"
        f"1.5 1 2 3 {' '.join(map(repr, q_xyzw.tolist()))}\n"
        "1.75   4 5 6 0 0 0 1\n"
    )
    poses = read_tum(path)
    np.testing.assert_array_equal(poses.times, [1.5, 1.75])
    np.testing.assert_array_equal(poses.p, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_allclose(poses.q[0], np.roll(q_xyzw, 1), rtol=0, atol=4e-16)
    np.testing.assert_array_equal(poses.q[1], [1, 0, 0, 0])
    ref = _poses()
    write_tum(tmp_path / "w.tum", ref)
    back = read_tum(tmp_path / "w.tum")
    np.testing.assert_array_equal(back.times, ref.times)
    np.testing.assert_array_equal(back.p, ref.p)
    np.testing.assert_allclose(back.q, ref.q, rtol=0, atol=4e-16)
    line2 = (tmp_path / "w.tum").read_text().splitlines()[1].split()
    assert float(line2[7]) == ref.q[0, 0] and float(line2[4]) == ref.q[0, 1]
    path.write_text("1.5 1 2 3 0 0 0 1\n1.5 1 2 3 0 0 0 1\n")
    with pytest.raises(RecordingError) as excinfo:
        read_tum(path)
    _assert_error(excinfo, path, 2, "duplicate timestamp")


# ------------------------------------------------------------------------ JSON


def test_camera_round_trip_exact(tmp_path):
    for cal in (_camera(True), _camera(False)):
        write_camera(tmp_path / "camera.json", cal)
        back = read_camera(tmp_path / "camera.json")
        np.testing.assert_array_equal(back.K, cal.K)
        np.testing.assert_array_equal(back.dist, cal.dist)
        assert back.image_size == cal.image_size and back.rms_px == cal.rms_px
        for key in ("T_f_c", "T_i_c"):
            a, b = getattr(back, key), getattr(cal, key)
            assert (a is None) == (b is None)
            if a is not None:
                np.testing.assert_array_equal(a, b)


def _camera_dict() -> dict:
    return {
        "format": "jaxtraj-camera",
        "version": 1,
        "image_size": [640, 480],
        "K": [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]],
        "dist": [0.0, 0.0, 0.0, 0.0, 0.0],
        "rms_px": None,
        "T_f_c": None,
        "T_i_c": None,
    }


@pytest.mark.parametrize(
    "change, words",
    [
        ({"K": [[-500.0, 0, 320], [0, 500, 240], [0, 0, 1]]}, ['key "K"', "positive fx"]),
        ({"K": [[500.0, 0, 700], [0, 500, 240], [0, 0, 1]]}, ['key "K"', "principal point"]),
        ({"K": [[500.0, 0, 320], [0, 500, 240], [0, 0.5, 1]]}, ['key "K"', "[0, 0, 1]"]),
        ({"K": [[500.0, 0, 320], [0, 500, 240]]}, ['key "K"', "3x3"]),
        ({"dist": [0.1, 0.2]}, ['key "dist"', "4 or 5"]),
        ({"rms_px": -1.0}, ['key "rms_px"', "non-negative"]),
        ({"T_f_c": (2 * np.eye(4)).tolist()}, ['key "T_f_c"', "orthonormal"]),
        ({"T_i_c": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]}, ["0 0 0 1"]),
        ({"image_size": [640]}, ['key "image_size"', "[width, height]"]),
        ({"format": "jaxtraj-object"}, ['key "format"', "jaxtraj-camera"]),
        ({"focal": 3}, ["unknown key(s) 'focal'", "known keys"]),
    ],
)
def test_camera_validation_names_the_key(tmp_path, change, words):
    path = tmp_path / "camera.json"
    path.write_text(json.dumps(_camera_dict() | change))
    with pytest.raises(RecordingError) as excinfo:
        read_camera(path)
    _assert_error(excinfo, path, None, *words)


def test_malformed_json_gives_line(tmp_path):
    path = tmp_path / "camera.json"
    path.write_text('{\n  "format": "jaxtraj-camera",\n  "version": 1,\n  "K": [1, 2,]\n}\n')
    with pytest.raises(RecordingError) as excinfo:
        read_camera(path)
    _assert_error(excinfo, path, 4, "invalid JSON")
    with pytest.raises(RecordingError) as excinfo:
        read_object(tmp_path / "object.json")
    _assert_error(excinfo, tmp_path / "object.json", None, "no such file")


def test_opencv_yaml_camera(tmp_path):
    path = tmp_path / "camera.yaml"
    path.write_text(
        "%YAML:1.0\n"
        "---\n"
        'calibration_time: "Mon 23 Nov 2026 10:00:00 CET"\n'
        "image_width: 1280\n"
        "image_height: 720\n"
        "flags: 0\n"
        "camera_matrix: !!opencv-matrix\n"
        "   rows: 3\n"
        "   cols: 3\n"
        "   dt: d\n"
        "   data: [ 9.1234567890123e+02, 0., 6.4050000000000000e+02, 0.,\n"
        "       9.1300000000000000e+02, 3.595e+02, 0., 0., 1. ]\n"
        "distortion_coefficients: !!opencv-matrix\n"
        "   rows: 1\n"
        "   cols: 5\n"
        "   dt: d\n"
        "   data: [ -1.2e-01, 3.4e-02, 1.0e-04, -2.0e-04, 0. ]  # k1 k2 p1 p2 k3\n"
        "avg_reprojection_error: 2.1e-01\n"
    )
    cal = read_camera(path)
    np.testing.assert_array_equal(
        cal.K, [[912.34567890123, 0, 640.5], [0, 913.0, 359.5], [0, 0, 1]]
    )
    np.testing.assert_array_equal(cal.dist, [-0.12, 0.034, 1e-4, -2e-4, 0.0])
    assert cal.image_size == (1280, 720) and cal.rms_px == 0.21 and cal.T_f_c is None

    text = path.read_text().replace("   cols: 5\n", "   cols: 4\n")
    path.write_text(text)
    with pytest.raises(RecordingError) as excinfo:
        read_camera(path)
    _assert_error(excinfo, path, 17, "distortion_coefficients", "1x4", "5 numbers")


def test_object_round_trip_and_errors(tmp_path):
    model = _model()
    write_object(tmp_path / "object.json", model)
    back = read_object(tmp_path / "object.json")
    np.testing.assert_array_equal(back.ids, model.ids)
    np.testing.assert_array_equal(back.points, model.points)
    np.testing.assert_array_equal(back.assembly_point, model.assembly_point)
    assert back.marker_size == 0.06 and back.marker_dictionary == "DICT_4X4_50"
    data = json.loads((tmp_path / "object.json").read_text())
    data["points"][2]["id"] = data["points"][0]["id"]
    (tmp_path / "object.json").write_text(json.dumps(data))
    with pytest.raises(RecordingError) as excinfo:
        read_object(tmp_path / "object.json")
    _assert_error(excinfo, tmp_path / "object.json", None, "points[2].id", "twice")


def test_meta_defaults_round_trip_and_unknown_key(tmp_path):
    path = tmp_path / "recording.json"
    path.write_text('{"format": "jaxtraj-recording", "version": 1}')
    meta = read_meta(path)
    assert meta == RecordingMeta()
    assert meta.imu_noise.accel_noise_density == pytest.approx(5.884e-4, rel=1e-3)
    assert meta.imu_noise.gyro_noise_density == pytest.approx(1.745e-4, rel=1e-3)
    assert (meta.robot_noise.position, meta.robot_noise.orientation) == (3e-5, 1e-4)
    assert meta.robot_latency is None and meta.gravity_w == (0.0, 0.0, -9.81)
    custom = RecordingMeta(
        description="cell 3, run 7",
        imu_noise=ImuNoise(1e-3, 2e-4, 3e-5, 4e-6),
        robot_noise=RobotNoise(1e-4, 2e-4),
        robot_latency=0.012,
        gravity_w=(0.0, 0.1, -9.8),
        calibration_target={"type": "charuco", "squares": [7, 5]},
    )
    write_meta(path, custom)
    assert read_meta(path) == custom
    data = json.loads(path.read_text())
    data["robot_latancy"] = 0.01
    path.write_text(json.dumps(data))
    with pytest.raises(RecordingError) as excinfo:
        read_meta(path)
    _assert_error(excinfo, path, None, "'robot_latancy'", "robot_latency", "imu_noise")
    data.pop("robot_latancy")
    data["imu_noise"]["gyro_noise"] = 1.0
    path.write_text(json.dumps(data))
    with pytest.raises(RecordingError) as excinfo:
        read_meta(path)
    _assert_error(excinfo, path, None, "'gyro_noise'", "gyro_noise_density")


def test_write_json_numpy_and_nan(tmp_path):
    path = tmp_path / "report.json"
    write_json(path, {"a": np.float32(1.5), "b": np.arange(3), "c": [np.nan, 2.0], "d": np.inf})
    assert json.loads(path.read_text()) == {"a": 1.5, "b": [0, 1, 2], "c": [None, 2.0], "d": None}


# ----------------------------------------------------------------- detections


def _detections(model: ObjectModel) -> Detections:
    F, M = 5, model.ids.size
    detected = RNG.uniform(size=(F, M)) < 0.7
    detected[2] = False  # a frame without any detection
    uv = RNG.uniform(0, 640, (F, M, 2)) * detected[..., None]
    return Detections(
        times=0.05 * np.arange(F) + 1 / 3,
        ids=model.ids,
        uv=uv,
        detected=detected,
        frames=np.arange(F) + 10,
    )


def test_detections_round_trip(tmp_path):
    model = _model()
    det = _detections(model)
    write_detections(tmp_path / "detections.csv", det)
    back = read_detections(tmp_path / "detections.csv", model, frame_times=(det.frames, det.times))
    for key in ("times", "ids", "uv", "detected", "frames"):
        np.testing.assert_array_equal(getattr(back, key), getattr(det, key))
    sparse = read_detections(tmp_path / "detections.csv", model.ids)
    np.testing.assert_array_equal(sparse.frames, [10, 11, 13, 14])
    np.testing.assert_array_equal(sparse.uv, det.uv[[0, 1, 3, 4]])


@pytest.mark.parametrize(
    "rows, line, words",
    [
        (["0,0.1,3,1,2", "0,0.1,7,3,4", "0,0.1,3,5,6"], 4, ["duplicate", "id 3", "line 2"]),
        (["0,0.1,3,1,2", "1,0.2,99,3,4"], 3, ["column id", "99"]),
        (["0,0.1,3,1,2", "0,0.15,7,3,4"], 3, ["same t", "line 2"]),
        (["1,0.1,3,1,2", "0,0.2,7,3,4"], 3, ["frames must be increasing"]),
        (["0,0.1,3,1,2", "1,0.1,7,3,4"], 3, ["duplicate timestamp"]),
        (["0,0.2,3,1,2", "1,0.1,7,3,4"], 3, ["timestamp goes backwards"]),
    ],
)
def test_detections_errors(tmp_path, rows, line, words):
    path = tmp_path / "detections.csv"
    path.write_text("frame,t,id,u,v\n" + "\n".join(rows) + "\n")
    with pytest.raises(RecordingError) as excinfo:
        read_detections(path, _model().ids)
    _assert_error(excinfo, path, line, *words)


def test_detections_ignore_unknown(tmp_path):
    path = tmp_path / "detections.csv"
    path.write_text("frame,t,id,u,v\n0,0.1,3,1,2\n0,0.1,42,9,9\n1,0.2,11,3,4\n")
    det = read_detections(path, _model().ids, ignore_unknown=True)
    np.testing.assert_array_equal(
        det.detected, [[False, True, False, False], [False] * 2 + [True, False]]
    )
    np.testing.assert_array_equal(det.uv[1, 2], [3, 4])


def test_image_index_round_trip_and_missing_file(tmp_path):
    (tmp_path / "images").mkdir()
    files = [tmp_path / "images" / f"{i:04d}.png" for i in range(3)]
    for f in files:
        f.write_bytes(b"png")
    times = np.array([0.1, 0.2, 1 / 3])
    write_image_index(tmp_path / "images.csv", [4, 5, 6], times, files)
    assert (tmp_path / "images.csv").read_text().splitlines()[1] == "4,0.1,images/0000.png"
    frames, t, back = read_image_index(tmp_path / "images.csv")
    np.testing.assert_array_equal(frames, [4, 5, 6])
    np.testing.assert_array_equal(t, times)
    assert back == files
    files[1].unlink()
    with pytest.raises(RecordingError) as excinfo:
        read_image_index(tmp_path / "images.csv")
    _assert_error(excinfo, tmp_path / "images.csv", 3, "0001.png", "does not exist")


def test_image_index_with_paths_relative_to_the_working_directory(tmp_path, monkeypatch):
    """A recording written to a relative folder (e.g. ``jaxtraj simulate rec``)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "rec" / "images").mkdir(parents=True)
    files = [Path("rec") / "images" / f"{i:04d}.png" for i in range(2)]
    for f in files:
        f.write_bytes(b"png")
    write_image_index(Path("rec") / "images.csv", [0, 1], np.array([0.0, 0.1]), files)
    assert (tmp_path / "rec" / "images.csv").read_text().splitlines()[1] == "0,0.0,images/0000.png"
    _, _, back = read_image_index(tmp_path / "rec" / "images.csv")
    assert [b.resolve() for b in back] == [(tmp_path / f).resolve() for f in files]


def test_points_round_trip(tmp_path):
    F, M = 4, 3
    pts = RNG.standard_normal((F, M, 3))
    ok = RNG.uniform(size=(F, M)) < 0.7
    pts[~ok] = np.nan
    times = np.arange(F) / 3
    write_points(tmp_path / "points.csv", times, [5, 2, 9], pts, ok, frames=[1, 3, 4, 8])
    back = read_points(tmp_path / "points.csv")
    np.testing.assert_array_equal(back.frames, [1, 3, 4, 8])
    np.testing.assert_array_equal(back.times, times)
    np.testing.assert_array_equal(back.ids, [5, 2, 9])
    np.testing.assert_array_equal(back.ok, ok)
    np.testing.assert_array_equal(back.points, pts)  # NaN == NaN in assert_array_equal


# ------------------------------------------------------------------ recording


def _recording(root: Path, tmp_path: Path) -> tuple[Recording, Truth]:
    model = _model()
    det = _detections(model)
    src = tmp_path / "rendered"
    src.mkdir(exist_ok=True)
    files = []
    for f in det.frames:
        files.append(src / f"{f:04d}.png")
        files[-1].write_bytes(bytes([f]))
    calib = [src / f"calib_{i}.png" for i in range(3)]
    for f in calib:
        f.write_bytes(b"c")
    n = 40
    imu = ImuSamples(
        t=np.arange(n) * 0.005 + 0.3,
        gyro=RNG.standard_normal((n, 3)),
        accel=RNG.standard_normal((n, 3)),
    )
    rec = Recording(
        root=root,
        meta=RecordingMeta(description="sim"),
        camera=_camera(),
        object=model,
        imu=imu,
        robot=_poses(6),
        image_index=(det.frames, det.times, files),
        detections=det,
        calibration_images=calib,
        calibration_robot=_poses(3),
    )
    truth = Truth(object_pose=_poses(5), camera_pose=_poses(5), camera=_camera(False))
    return rec, truth


def test_recording_round_trip(tmp_path):
    root = tmp_path / "recording"
    rec, truth = _recording(root, tmp_path)
    write_recording(root, rec, truth=truth)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["recording", "rendered"]
    back = read_recording(root, require_camera=True)
    assert back.root == root and back.meta == rec.meta
    np.testing.assert_array_equal(back.camera.K, rec.camera.K)
    np.testing.assert_array_equal(back.object.points, rec.object.points)
    np.testing.assert_array_equal(back.imu.accel, rec.imu.accel)
    np.testing.assert_array_equal(back.robot.p, rec.robot.p)
    np.testing.assert_array_equal(back.image_index[1], rec.image_index[1])
    assert [f.read_bytes() for f in back.image_index[2]] == [
        bytes([f]) for f in rec.detections.frames
    ]
    assert all(f.parent == root / "images" for f in back.image_index[2])
    np.testing.assert_array_equal(back.detections.uv, rec.detections.uv)
    np.testing.assert_array_equal(back.detections.detected, rec.detections.detected)
    assert [f.name for f in back.calibration_images] == [
        "calib_0.png",
        "calib_1.png",
        "calib_2.png",
    ]
    np.testing.assert_array_equal(back.calibration_robot.times, rec.calibration_robot.times)
    t = read_truth(root)
    np.testing.assert_array_equal(t.object_pose.p, truth.object_pose.p)
    np.testing.assert_array_equal(t.camera_pose.times, truth.camera_pose.times)
    np.testing.assert_array_equal(t.camera.K, truth.camera.K)


def test_recording_missing_files(tmp_path):
    root = tmp_path / "recording"
    rec, _ = _recording(root, tmp_path)
    write_recording(root, rec)
    assert read_truth(root) is None
    (root / "camera.json").unlink()
    assert read_recording(root).camera is None
    with pytest.raises(RecordingError) as excinfo:
        read_recording(root, require_camera=True)
    _assert_error(excinfo, root / "camera.json", None, "jaxtraj calibrate")
    (root / "calibration" / "calib_0.png").unlink()
    with pytest.raises(RecordingError) as excinfo:
        read_recording(root)
    _assert_error(excinfo, root / "calibration" / "robot.csv", None, "3 flange poses for 2")
    (root / "images.csv").unlink()
    (root / "detections.csv").unlink()
    with pytest.raises(RecordingError) as excinfo:
        read_recording(root)
    _assert_error(excinfo, root, None, "neither images.csv", "detections.csv")
    (root / "imu.csv").unlink()
    with pytest.raises(RecordingError) as excinfo:
        read_recording(root)
    _assert_error(excinfo, root / "imu.csv", None, "no such file", "object.json, imu.csv")


def test_write_recording_failure_keeps_old(tmp_path, monkeypatch):
    root = tmp_path / "recording"
    rec, _ = _recording(root, tmp_path)
    write_recording(root, rec)
    before = sorted(p.name for p in root.iterdir())
    bad = Detections(
        times=rec.detections.times,
        ids=rec.detections.ids,
        uv=np.full_like(rec.detections.uv, np.nan),
        detected=rec.detections.detected,
        frames=rec.detections.frames,
    )
    with pytest.raises(ValueError, match="finite pixel"):
        write_recording(root, Recording(**{**rec.__dict__, "detections": bad}))
    assert sorted(p.name for p in root.iterdir()) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["recording", "rendered"]
    assert read_recording(root).detections.detected.sum() == rec.detections.detected.sum()

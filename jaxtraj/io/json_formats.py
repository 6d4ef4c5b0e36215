"""Readers and writers of a recording's JSON files and of OpenCV's camera YAML.

Every ``read_X`` stops bad input with one :class:`~jaxtraj.io.tables.RecordingError`
naming the file, the line (YAML, JSON syntax) or key (JSON) and the problem. Every
``write_X`` writes atomically and with enough digits that ``read_X(write_X(x)) == x``
exactly (floats use Python's shortest round-trip repr).

Files (see :mod:`jaxtraj.io.recording` for the folder; the CSV files are in
:mod:`jaxtraj.io.csv_formats`):

* ``camera.json`` (or OpenCV's ``camera.yaml``, read only): intrinsics, distortion and
  the camera's mounting (:func:`read_camera`, :func:`write_camera`).
* ``object.json``: the workpiece's reference points (:func:`read_object`,
  :func:`write_object`).
* ``recording.json``: sensor metadata (:class:`RecordingMeta`, :class:`ImuNoise`,
  :class:`RobotNoise`, :func:`read_meta`, :func:`write_meta`).
* any other JSON result (reports, summaries): :func:`write_json`.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .records import CameraCalibration, ObjectModel
from .tables import RecordingError, _check_file, _show, atomic_write_text

__all__ = [
    "ImuNoise",
    "RecordingMeta",
    "RobotNoise",
    "read_camera",
    "read_meta",
    "read_object",
    "write_camera",
    "write_json",
    "write_meta",
    "write_object",
]

# ------------------------------------------------------------------------- JSON


def _to_json(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _to_json(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return _to_json(value.tolist())
    if isinstance(value, (list, tuple)):
        return [_to_json(v) for v in value]
    if isinstance(value, np.generic):
        return _to_json(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "__dataclass_fields__"):
        return _to_json({k: getattr(value, k) for k in value.__dataclass_fields__})
    return value


def write_json(path: str | Path, data: Any) -> None:
    """Write ``data`` as indented JSON atomically (NumPy scalars/arrays, Paths and
    dataclasses converted; NaN and inf written as null)."""
    text = json.dumps(_to_json(data), indent=2, allow_nan=False)
    atomic_write_text(path, text + "\n")


def _read_json(path: str | Path, fmt: str) -> tuple[Path, dict]:
    path = _check_file(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))
    except json.JSONDecodeError as err:
        raise RecordingError(
            path, err.lineno, f"invalid JSON: {err.msg} (column {err.colno})"
        ) from None
    except UnicodeDecodeError as err:
        raise RecordingError(path, None, f"not UTF-8 text ({err.reason})") from None
    if not isinstance(data, dict):
        raise RecordingError(path, None, f"expected a JSON object, got {type(data).__name__}")
    if data.get("format") != fmt:
        raise RecordingError(
            path, None, f'key "format": expected "{fmt}", got {json.dumps(data.get("format"))}'
        )
    if data.get("version") != 1:
        raise RecordingError(
            path, None, f'key "version": expected 1, got {json.dumps(data.get("version"))}'
        )
    return path, data


def _check_keys(path: Path, data: dict, known: Sequence[str], where: str = "") -> None:
    unknown = [k for k in data if k not in known]
    if unknown:
        raise RecordingError(
            path,
            None,
            f"unknown key(s) {', '.join(map(repr, unknown))}{where}; known keys: "
            f"{', '.join(known)}",
        )


def _number(path: Path, key: str, value: Any, *, positive=False, nonneg=False) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or (positive and value <= 0) or (nonneg and value < 0):
        want = "a positive" if positive else "a non-negative" if nonneg else "a finite"
        raise RecordingError(
            path, None, f'key "{key}": expected {want} number, got {json.dumps(value)}'
        )
    return float(value)


def _matrix(path: Path, key: str, value: Any, shape: tuple[int, ...]) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
        good = arr.shape == shape and np.all(np.isfinite(arr))
        good = good and not _has_bool(value)
    except (TypeError, ValueError):
        good = False
    if not good:
        want = "x".join(map(str, shape))
        raise RecordingError(
            path, None, f'key "{key}": expected {want} finite numbers, got {json.dumps(value)}'
        )
    return arr


def _has_bool(value: Any) -> bool:
    if isinstance(value, list):
        return any(_has_bool(v) for v in value)
    return isinstance(value, bool)


# ------------------------------------------------------------------------ camera

CAMERA_KEYS = ("format", "version", "image_size", "K", "dist", "rms_px", "T_f_c", "T_i_c")


def _check_rigid(path: Path, key: str, T: np.ndarray | None) -> None:
    """A rigid (4, 4) transform: orthonormal rotation with det +1, last row 0 0 0 1."""
    if T is None:
        return
    R = T[:3, :3]
    if np.max(np.abs(R.T @ R - np.eye(3))) > 1e-6 or np.linalg.det(R) <= 0:
        raise RecordingError(
            path, None, f'key "{key}": rotation part not orthonormal (within 1e-6) with det +1'
        )
    if not np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise RecordingError(
            path, None, f'key "{key}": last row must be 0 0 0 1, got {T[3].tolist()}'
        )


def _rigid_or_none(path: Path, key: str, value: Any) -> np.ndarray | None:
    """A JSON 4x4 rigid transform or null."""
    if value is None:
        return None
    T = _matrix(path, key, value, (4, 4))
    _check_rigid(path, key, T)
    return T


def _check_camera(path: Path, K, dist, size, rms, T_f_c, T_i_c) -> CameraCalibration:
    w, h = size
    if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or abs(K[2, 2] - 1) > 1e-12:
        raise RecordingError(
            path, None, f'key "K": expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}'
        )
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise RecordingError(
            path, None, f'key "K": expected positive fx, fy, got {_show(K[0, 0])}, {_show(K[1, 1])}'
        )
    if not (-0.5 <= K[0, 2] <= w - 0.5 and -0.5 <= K[1, 2] <= h - 0.5):
        raise RecordingError(
            path,
            None,
            f'key "K": principal point ({_show(K[0, 2])}, {_show(K[1, 2])}) '
            f"outside the {w}x{h} image",
        )
    for key, T in (("T_f_c", T_f_c), ("T_i_c", T_i_c)):
        _check_rigid(path, key, T)
    return CameraCalibration(
        K=K, dist=dist, image_size=(w, h), rms_px=rms, T_f_c=T_f_c, T_i_c=T_i_c
    )


def _image_size(path: Path, key: str, value: Any) -> tuple[int, int]:
    if (
        not isinstance(value, list)
        or len(value) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in value)
    ):
        raise RecordingError(
            path,
            None,
            f'key "{key}": expected [width, height] positive integers, got {json.dumps(value)}',
        )
    return value[0], value[1]


def _dist(path: Path, key: str, value: Any) -> np.ndarray:
    arr = np.ravel(np.asarray(value, np.float64)) if isinstance(value, list) else None
    if arr is None or arr.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(arr)):
        raise RecordingError(
            path,
            None,
            f'key "{key}": expected 4 or 5 finite coefficients (k1, k2, p1, p2[, k3]), '
            f"got {json.dumps(value) if isinstance(value, list) else value!r}",
        )
    if arr.size > 5:
        if np.any(arr[5:] != 0):
            raise RecordingError(
                path,
                None,
                f'key "{key}": only the 5-coefficient model (k1, k2, p1, p2, k3) is '
                f"supported, got non-zero higher coefficients {arr[5:].tolist()}",
            )
        arr = arr[:5]
    return arr


def read_camera(path: str | Path) -> CameraCalibration:
    """Read ``camera.json`` or, for a ``.yaml``/``.yml`` suffix, an OpenCV calibration file.

    Checks: K upper triangular with positive fx, fy and K[2, 2] = 1; principal point inside
    the image; finite numbers; ``T_f_c``/``T_i_c`` rigid (R orthonormal within 1e-6, last
    row 0 0 0 1).
    """
    if Path(path).suffix.lower() in (".yaml", ".yml"):
        return _read_opencv_yaml(Path(path))
    path, data = _read_json(path, "jaxtraj-camera")
    _check_keys(path, data, CAMERA_KEYS)
    for key in ("image_size", "K"):
        if key not in data:
            raise RecordingError(path, None, f'missing key "{key}"')
    size = _image_size(path, "image_size", data["image_size"])
    K = _matrix(path, "K", data["K"], (3, 3))
    dist = _dist(path, "dist", data.get("dist", [0.0] * 5))
    rms = data.get("rms_px")
    rms = None if rms is None else _number(path, "rms_px", rms, nonneg=True)
    T = {}
    for key in ("T_f_c", "T_i_c"):
        value = data.get(key)
        T[key] = None if value is None else _matrix(path, key, value, (4, 4))
    return _check_camera(path, K, dist, size, rms, T["T_f_c"], T["T_i_c"])


def write_camera(path: str | Path, cal: CameraCalibration) -> None:
    """Write ``camera.json`` (always JSON, whatever the suffix)."""
    write_json(
        path,
        {
            "format": "jaxtraj-camera",
            "version": 1,
            "image_size": list(cal.image_size),
            "K": cal.K,
            "dist": cal.dist,
            "rms_px": cal.rms_px,
            "T_f_c": cal.T_f_c,
            "T_i_c": cal.T_i_c,
        },
    )


_YAML_KEY = re.compile(r"^(\s*)([A-Za-z_][\w\-]*)\s*:\s*(.*)$")


def _parse_opencv_yaml(path: Path) -> dict[str, tuple[int, Any]]:
    """The top-level keys of an OpenCV FileStorage YAML file: key -> (line, value).

    Values are a string (scalar) or, for a nested block (``!!opencv-matrix``), a dict
    key -> (line, string). Flow lists ``[ ... ]`` may span lines.
    """
    lines = path.read_text(encoding="utf-8-sig").split("\n")
    out: dict[str, tuple[int, Any]] = {}
    block: dict | None = None
    i = 0
    while i < len(lines):
        lineno, raw = i + 1, lines[i].split("#", 1)[0].rstrip()
        i += 1
        if not raw.strip() or raw.startswith("%") or raw.strip() in ("---", "..."):
            continue
        m = _YAML_KEY.match(raw)
        if not m:
            raise RecordingError(
                path, lineno, f"cannot parse line as 'key: value': {raw.strip()!r}"
            )
        indent, key, value = m.groups()
        if value.startswith("["):  # flow list, possibly over several lines
            while value.count("[") > value.count("]"):
                if i >= len(lines):
                    raise RecordingError(path, lineno, f"key {key}: '[' is never closed")
                value += " " + lines[i].split("#", 1)[0].strip()
                i += 1
        if not indent:
            if key in out:
                raise RecordingError(path, lineno, f"key {key} appears twice")
            if value in ("", "!!opencv-matrix") or value.startswith("!!"):
                block = {}
                out[key] = (lineno, block)
            else:
                block = None
                out[key] = (lineno, value.strip().strip("\"'"))
        else:
            if block is None:
                raise RecordingError(path, lineno, f"unexpected indented key {key}")
            block[key] = (lineno, value.strip())
    return out


def _yaml_matrix(
    path: Path, key: str, entry: tuple[int, Any], shape: tuple[int, ...]
) -> np.ndarray:
    lineno, value = entry
    if not isinstance(value, dict) or "data" not in value:
        raise RecordingError(
            path, lineno, f"key {key}: expected an !!opencv-matrix with rows, cols, data"
        )
    data_line, data = value["data"]
    text = data.strip()
    if not (text.startswith("[") and text.endswith("]")):
        raise RecordingError(path, data_line, f"key {key}: data must be a [ ... ] list")
    try:
        numbers = [float(v) for v in text[1:-1].replace(",", " ").split()]
    except ValueError as err:
        raise RecordingError(path, data_line, f"key {key}: bad number in data ({err})") from None
    try:
        rows = int(value.get("rows", (0, len(numbers)))[1])
        cols = int(value.get("cols", (0, 1))[1])
    except ValueError:
        raise RecordingError(path, lineno, f"key {key}: rows and cols must be integers") from None
    if rows * cols != len(numbers):
        raise RecordingError(
            path,
            data_line,
            f"key {key}: rows x cols = {rows}x{cols} but data has {len(numbers)} numbers",
        )
    arr = np.asarray(numbers, np.float64)
    if not np.all(np.isfinite(arr)):
        raise RecordingError(path, data_line, f"key {key}: expected finite numbers")
    if shape and arr.size != math.prod(shape):
        want = "x".join(map(str, shape))
        raise RecordingError(
            path, lineno, f"key {key}: expected a {want} matrix, got {rows}x{cols}"
        )
    return arr.reshape(shape) if shape else arr


def _read_opencv_yaml(path: Path) -> CameraCalibration:
    path = _check_file(path)
    try:
        doc = _parse_opencv_yaml(path)
    except UnicodeDecodeError as err:
        raise RecordingError(path, None, f"not UTF-8 text ({err.reason})") from None
    for key in ("camera_matrix", "image_width", "image_height"):
        if key not in doc:
            raise RecordingError(
                path,
                None,
                f"missing key {key} (an OpenCV calibration file needs camera_matrix, "
                "distortion_coefficients, image_width, image_height)",
            )
    size = []
    for key in ("image_width", "image_height"):
        lineno, value = doc[key]
        if not isinstance(value, str) or not value.isdigit() or int(value) <= 0:
            raise RecordingError(
                path, lineno, f"key {key}: expected a positive integer, got {value!r}"
            )
        size.append(int(value))
    K = _yaml_matrix(path, "camera_matrix", doc["camera_matrix"], (3, 3))
    dist = np.zeros(5)
    if "distortion_coefficients" in doc:
        entry = doc["distortion_coefficients"]
        arr = _yaml_matrix(path, "distortion_coefficients", entry, ())
        try:
            dist = _dist(path, "distortion_coefficients", arr.tolist())
        except RecordingError as err:
            raise RecordingError(path, entry[0], err.problem) from None
    rms = None
    for key in ("avg_reprojection_error", "rms_px"):
        if key in doc:
            lineno, value = doc[key]
            try:
                rms = float(value)
            except (TypeError, ValueError):
                raise RecordingError(
                    path, lineno, f"key {key}: expected a number, got {value!r}"
                ) from None
    T = {k: _yaml_matrix(path, k, doc[k], (4, 4)) if k in doc else None for k in ("T_f_c", "T_i_c")}
    return _check_camera(path, K, dist, (size[0], size[1]), rms, T["T_f_c"], T["T_i_c"])


# ------------------------------------------------------------------------ object

OBJECT_KEYS = ("format", "version", "marker_dictionary", "marker_size", "assembly_point", "points")


def read_object(path: str | Path) -> ObjectModel:
    """Read ``object.json``: the workpiece's reference points in the object frame [m]."""
    path, data = _read_json(path, "jaxtraj-object")
    _check_keys(path, data, OBJECT_KEYS)
    points = data.get("points")
    if not isinstance(points, list) or len(points) < 3:
        raise RecordingError(
            path, None, 'key "points": expected a list of >= 3 {"id", "xyz"} objects'
        )
    ids, xyz = [], []
    for n, item in enumerate(points):
        key = f"points[{n}]"
        if not isinstance(item, dict):
            raise RecordingError(
                path, None, f'key "{key}": expected {{"id": int, "xyz": [x, y, z]}}'
            )
        _check_keys(path, item, ("id", "xyz"), f" in {key}")
        pid = item.get("id")
        if not isinstance(pid, int) or isinstance(pid, bool):
            raise RecordingError(
                path, None, f'key "{key}.id": expected an integer, got {json.dumps(pid)}'
            )
        if pid in ids:
            raise RecordingError(path, None, f'key "{key}.id": id {pid} appears twice')
        ids.append(pid)
        xyz.append(_matrix(path, f"{key}.xyz", item.get("xyz"), (3,)))
    size = data.get("marker_size")
    dictionary = data.get("marker_dictionary", "DICT_4X4_50")
    if not isinstance(dictionary, str) or not dictionary:
        raise RecordingError(
            path, None, f'key "marker_dictionary": expected a name, got {json.dumps(dictionary)}'
        )
    return ObjectModel(
        ids=np.asarray(ids, np.int64),
        points=np.asarray(xyz),
        assembly_point=_matrix(path, "assembly_point", data.get("assembly_point", [0.0] * 3), (3,)),
        marker_dictionary=dictionary,
        marker_size=None if size is None else _number(path, "marker_size", size, positive=True),
    )


def write_object(path: str | Path, model: ObjectModel) -> None:
    """Write ``object.json``."""
    write_json(
        path,
        {
            "format": "jaxtraj-object",
            "version": 1,
            "marker_dictionary": model.marker_dictionary,
            "marker_size": model.marker_size,
            "assembly_point": model.assembly_point,
            "points": [
                {"id": int(i), "xyz": p} for i, p in zip(model.ids, model.points, strict=True)
            ],
        },
    )


# ---------------------------------------------------------------------- metadata


@dataclass(frozen=True)
class ImuNoise:
    """IMU noise (continuous-time densities), defaults: an Xsens MTi-class MEMS IMU.

    Attributes:
        accel_noise_density: [m/s^2/sqrt(Hz)], default 60 ug/sqrt(Hz) = 5.884e-4.
        gyro_noise_density: [rad/s/sqrt(Hz)], default 0.01 deg/s/sqrt(Hz) = 1.745e-4.
        accel_random_walk: [m/s^3/sqrt(Hz)], default 4e-5.
        gyro_random_walk: [rad/s^2/sqrt(Hz)], default 1e-6.
    """

    accel_noise_density: float = 60e-6 * 9.80665
    gyro_noise_density: float = 0.01 * math.pi / 180.0
    accel_random_walk: float = 4e-5
    gyro_random_walk: float = 1e-6


@dataclass(frozen=True)
class RobotNoise:
    """Noise of the robot controller's flange poses: position [m] (default 3e-5) and
    orientation [rad] (default 1e-4), standard deviations."""

    position: float = 3e-5
    orientation: float = 1e-4


@dataclass(frozen=True)
class RecordingMeta:
    """Sensor metadata of a recording (``recording.json``).

    Attributes:
        description: free text (default "").
        imu_noise: :class:`ImuNoise` (default: Xsens MTi-class).
        robot_noise: :class:`RobotNoise` (default 3e-5 m, 1e-4 rad).
        robot_latency: robot pose stamp latency [s], or None (default) to estimate it.
        gravity_w: (3,) gravity in the world frame [m/s^2] (default (0, 0, -9.81)).
        calibration_target: description of the calibration target (a dict passed through
            unchecked), or None.
        T_i_c: (4, 4) the camera in the IMU frame (how the IMU is mounted beside the
            camera), or None for identity. A ``T_i_c`` in ``camera.json`` takes precedence.
    """

    description: str = ""
    imu_noise: ImuNoise = field(default_factory=ImuNoise)
    robot_noise: RobotNoise = field(default_factory=RobotNoise)
    robot_latency: float | None = None
    gravity_w: tuple[float, float, float] = (0.0, 0.0, -9.81)
    calibration_target: dict | None = None
    T_i_c: np.ndarray | None = None


META_KEYS = (
    "format",
    "version",
    "description",
    "imu_noise",
    "robot_noise",
    "robot_latency",
    "gravity_w",
    "calibration_target",
    "T_i_c",
)


def _sub(path: Path, data: dict, key: str, cls) -> Any:
    value = data.get(key)
    if value is None:
        return cls()
    names = tuple(cls.__dataclass_fields__)
    if not isinstance(value, dict):
        raise RecordingError(
            path, None, f'key "{key}": expected an object with keys {", ".join(names)}'
        )
    _check_keys(path, value, names, f' in "{key}"')
    return cls(**{k: _number(path, f"{key}.{k}", v, nonneg=True) for k, v in value.items()})


def read_meta(path: str | Path) -> RecordingMeta:
    """Read ``recording.json``; unknown keys are an error (they list the known ones)."""
    path, data = _read_json(path, "jaxtraj-recording")
    _check_keys(path, data, META_KEYS)
    desc = data.get("description", "")
    if not isinstance(desc, str):
        raise RecordingError(
            path, None, f'key "description": expected a string, got {json.dumps(desc)}'
        )
    latency = data.get("robot_latency")
    latency = None if latency is None else _number(path, "robot_latency", latency)
    gravity = tuple(
        _matrix(path, "gravity_w", data.get("gravity_w", [0.0, 0.0, -9.81]), (3,)).tolist()
    )
    target = data.get("calibration_target")
    if target is not None and not isinstance(target, dict):
        raise RecordingError(path, None, 'key "calibration_target": expected an object or null')
    return RecordingMeta(
        description=desc,
        imu_noise=_sub(path, data, "imu_noise", ImuNoise),
        robot_noise=_sub(path, data, "robot_noise", RobotNoise),
        robot_latency=latency,
        gravity_w=gravity,
        calibration_target=target,
        T_i_c=_rigid_or_none(path, "T_i_c", data.get("T_i_c")),
    )


def write_meta(path: str | Path, meta: RecordingMeta) -> None:
    """Write ``recording.json``."""
    write_json(
        path,
        {
            "format": "jaxtraj-recording",
            "version": 1,
            "description": meta.description,
            "imu_noise": meta.imu_noise,
            "robot_noise": meta.robot_noise,
            "robot_latency": meta.robot_latency,
            "gravity_w": list(meta.gravity_w),
            "calibration_target": meta.calibration_target,
            "T_i_c": None if meta.T_i_c is None else np.asarray(meta.T_i_c).tolist(),
        },
    )

"""CELL.json: the robot cell a camera path is designed for (host side).

A JSON object (SI units except where a key says ``_deg``)::

    {
      "robot": "kr16_2",                       # a shipped robot (jaxtraj.io.urdf.ROBOTS)
      "T_w_base": [[...4x4...]],               # robot base in the world (default identity)
      "T_f_c": [[...4x4...]],                  # hand-eye: camera in the flange
      "K": [[...3x3...]],                      # camera matrix [px]
      "start": {"q_deg": [a1, ..., a6]}        # start configuration, or
               {"camera_position": [x, y, z]}  #   camera there, looking at the first prediction
      "prediction": {"times": [...], "points": [[x, y, z], ...]},   # predicted workpiece
      "limits": {"velocity_deg_s": [6], "acceleration_deg_s2": [6], "jerk_deg_s3": [6],
                 "standoff": [0.6, 1.4],
                 "half_fov_deg": 19, "fov_margin_deg": 3, "keep_out_radius": 0.4,
                 "floor_z": 0.0, "floor_clearance": 0.1},            # all optional
      "end": {"offset": [0, 0, 0.6], "tolerance": 0.05},             # optional
      "estimator": {"method": "dct", "k": 12, "pixel_sigma": 0.3},   # optional; or
                   {"method": "smoother", "order": 2, "pixel_sigma": 0.3}  # estimate_points' prior
                   {"method": "pose", "layout": [[x, y, z], ...], "point": [x, y, z],
                    "R_w_o": [[...3x3...]], "pixel_sigma": 0.3}  # per-image PnP of the
                   # object's >= 4 reference points (object frame [m]); "point": the object
                   # point the prediction follows (default origin); "R_w_o": the object's
                   # orientation (default: its z axis towards the camera's start position)
      "design": {"starts": 8, "n_control": 12, "objective": "mean_error",
                 "plausible_extent": 0.03, "plausible_samples": 2, "seed": 0}
    }

:func:`read_cell` checks every field and raises ``ValueError`` naming the file (and, for
malformed JSON, the line) and the key.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

__all__ = ["CellSpec", "cell_from_dict", "read_cell"]


@dataclasses.dataclass
class CellSpec:
    """A checked CELL.json (NumPy arrays, SI units, radians)."""

    robot: str
    T_w_base: np.ndarray
    T_f_c: np.ndarray
    K: np.ndarray
    times: np.ndarray
    predicted: np.ndarray
    q_start: np.ndarray | None = None
    camera_start: np.ndarray | None = None
    velocity: np.ndarray | None = None
    acceleration: np.ndarray | None = None
    jerk: np.ndarray | None = None
    standoff: tuple[float, float] = (0.6, 1.4)
    half_fov: float = float(np.radians(19.0))
    fov_margin: float = float(np.radians(3.0))
    keep_out_radius: float = 0.4
    floor_z: float = 0.0
    floor_clearance: float = 0.1
    end_offset: np.ndarray | None = None
    end_tolerance: float = 0.05
    method: str = "dct"
    k: int = 12
    order: int = 2
    pixel_sigma: float = 0.3
    layout: np.ndarray | None = None
    point: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    R_w_o: np.ndarray | None = None
    starts: int = 8
    n_control: int = 12
    objective: str = "mean_error"
    plausible_extent: float = 0.03
    plausible_samples: int = 2
    seed: int = 0

    def to_dict(self) -> dict:
        """The JSON form (lists; angles in degrees where the key says so)."""
        out = {
            "robot": self.robot,
            "T_w_base": self.T_w_base.tolist(),
            "T_f_c": self.T_f_c.tolist(),
            "K": self.K.tolist(),
            "prediction": {"times": self.times.tolist(), "points": self.predicted.tolist()},
            "start": (
                {"q_deg": np.degrees(self.q_start).tolist()}
                if self.q_start is not None
                else {"camera_position": self.camera_start.tolist()}
            ),
            "limits": {
                "standoff": list(self.standoff),
                "half_fov_deg": float(np.degrees(self.half_fov)),
                "fov_margin_deg": float(np.degrees(self.fov_margin)),
                "keep_out_radius": self.keep_out_radius,
                "floor_z": self.floor_z,
                "floor_clearance": self.floor_clearance,
            },
            "estimator": self._estimator_dict(),
            "design": {
                "starts": self.starts,
                "n_control": self.n_control,
                "objective": self.objective,
                "plausible_extent": self.plausible_extent,
                "plausible_samples": self.plausible_samples,
                "seed": self.seed,
            },
        }
        if self.velocity is not None:
            out["limits"]["velocity_deg_s"] = np.degrees(self.velocity).tolist()
        if self.acceleration is not None:
            out["limits"]["acceleration_deg_s2"] = np.degrees(self.acceleration).tolist()
        if self.jerk is not None:
            out["limits"]["jerk_deg_s3"] = np.degrees(self.jerk).tolist()
        if self.end_offset is not None:
            out["end"] = {"offset": self.end_offset.tolist(), "tolerance": self.end_tolerance}
        return out

    def workpiece_orientation(self, camera_centre) -> np.ndarray:
        """``R_w_o`` of a known-layout cell: the cell's ``R_w_o``, or the object z axis
        from the first prediction towards ``camera_centre`` (image-y-down convention of
        :func:`jaxtraj.look_at`, world z up)."""
        if self.R_w_o is not None:
            return np.asarray(self.R_w_o, float)
        from ..camera import look_at

        R_o_w, _ = look_at(np.asarray(self.predicted[0], float), np.asarray(camera_centre, float))
        return np.asarray(R_o_w, float).T

    def _estimator_dict(self) -> dict:
        out = {"method": self.method, "pixel_sigma": self.pixel_sigma}
        if self.method == "dct":
            out["k"] = self.k
        elif self.method == "smoother":
            out["order"] = self.order
        else:
            out["layout"] = self.layout.tolist()
            out["point"] = np.asarray(self.point).tolist()
            if self.R_w_o is not None:
                out["R_w_o"] = self.R_w_o.tolist()
        return out


def _array(where: str, value, shape: tuple) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: expected numbers of shape {shape}, got {value!r:.80}") from None
    ok = arr.ndim == len(shape) and all(
        e is None or e == s for e, s in zip(shape, arr.shape, strict=True)
    )
    if not ok:
        raise ValueError(f"{where}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{where}: expected finite numbers")
    return arr


def _number(where: str, value, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
        raise ValueError(f"{where}: expected a number, got {value!r}")
    if positive and not value > 0:
        raise ValueError(f"{where}: expected a positive number, got {value!r}")
    return float(value)


def _object(where: str, value, known: set[str]) -> dict:
    if not isinstance(value, dict):
        raise ValueError(f"{where}: expected a JSON object, got {type(value).__name__}")
    unknown = sorted(set(value) - known)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; known: {sorted(known)}")
    return value


def _rigid(where: str, value) -> np.ndarray:
    T = _array(where, value, (4, 4))
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise ValueError(
            f"{where}: expected a rigid transform (orthonormal rotation, last row 0 0 0 1)"
        )
    if np.linalg.det(R) < 0:
        raise ValueError(f"{where}: the rotation is a reflection (det -1)")
    return T


def cell_from_dict(data: dict, where: str = "CELL.json") -> CellSpec:
    """A :class:`CellSpec` from the parsed JSON object (errors name ``where`` and the key)."""
    from .urdf import robot_file

    top = {
        "robot",
        "T_w_base",
        "T_f_c",
        "K",
        "start",
        "prediction",
        "limits",
        "end",
        "estimator",
        "design",
    }
    data = _object(where, data, top)
    for key in ("robot", "T_f_c", "K", "start", "prediction"):
        if key not in data:
            raise ValueError(f"{where}: missing key {key!r}")
    if not isinstance(data["robot"], str):
        raise ValueError(f"{where}: 'robot': expected a name, got {data['robot']!r}")
    try:
        robot_file(data["robot"])
    except ValueError as err:
        raise ValueError(f"{where}: {err}") from None
    pred = _object(f"{where}: 'prediction'", data["prediction"], {"times", "points"})
    if "times" not in pred or "points" not in pred:
        raise ValueError(f"{where}: 'prediction': needs 'times' and 'points'")
    times = _array(f"{where}: 'prediction.times'", pred["times"], (None,))
    if times.size == 0:
        raise ValueError(f"{where}: 'prediction' is empty (no times)")
    points = _array(f"{where}: 'prediction.points'", pred["points"], (times.size, 3))
    if times.size < 8 or np.any(np.diff(times) <= 0):
        raise ValueError(f"{where}: 'prediction.times': expected >= 8 strictly increasing times")
    spec = CellSpec(
        robot=data["robot"],
        T_w_base=_rigid(f"{where}: 'T_w_base'", data.get("T_w_base", np.eye(4).tolist())),
        T_f_c=_rigid(f"{where}: 'T_f_c'", data["T_f_c"]),
        K=_array(f"{where}: 'K'", data["K"], (3, 3)),
        times=times,
        predicted=points,
    )
    start = _object(f"{where}: 'start'", data["start"], {"q_deg", "camera_position"})
    if len(start) != 1:
        raise ValueError(f"{where}: 'start': give exactly one of 'q_deg', 'camera_position'")
    if "q_deg" in start:
        spec.q_start = np.radians(_array(f"{where}: 'start.q_deg'", start["q_deg"], (6,)))
    else:
        spec.camera_start = _array(
            f"{where}: 'start.camera_position'", start["camera_position"], (3,)
        )
    limits = _object(
        f"{where}: 'limits'",
        data.get("limits", {}),
        {
            "velocity_deg_s",
            "acceleration_deg_s2",
            "jerk_deg_s3",
            "standoff",
            "half_fov_deg",
            "fov_margin_deg",
            "keep_out_radius",
            "floor_z",
            "floor_clearance",
        },
    )
    for key, attr in (
        ("velocity_deg_s", "velocity"),
        ("acceleration_deg_s2", "acceleration"),
        ("jerk_deg_s3", "jerk"),
    ):
        if key in limits:
            values = _array(f"{where}: 'limits.{key}'", limits[key], (6,))
            if np.any(values <= 0):
                raise ValueError(f"{where}: 'limits.{key}': expected positive values")
            setattr(spec, attr, np.radians(values))
    if "standoff" in limits:
        lo, hi = _array(f"{where}: 'limits.standoff'", limits["standoff"], (2,))
        if not 0 < lo < hi:
            raise ValueError(f"{where}: 'limits.standoff': expected 0 < min < max")
        spec.standoff = (float(lo), float(hi))
    for key, attr, conv in (
        ("half_fov_deg", "half_fov", np.radians),
        ("fov_margin_deg", "fov_margin", np.radians),
        ("keep_out_radius", "keep_out_radius", float),
        ("floor_clearance", "floor_clearance", float),
    ):
        if key in limits:
            setattr(spec, attr, float(conv(_number(f"{where}: 'limits.{key}'", limits[key], True))))
    if "floor_z" in limits:
        spec.floor_z = _number(f"{where}: 'limits.floor_z'", limits["floor_z"])
    if spec.fov_margin >= spec.half_fov:
        raise ValueError(f"{where}: 'limits.fov_margin_deg' must be below 'half_fov_deg'")
    if "end" in data:
        end = _object(f"{where}: 'end'", data["end"], {"offset", "tolerance"})
        spec.end_offset = _array(f"{where}: 'end.offset'", end.get("offset"), (3,))
        if "tolerance" in end:
            spec.end_tolerance = _number(f"{where}: 'end.tolerance'", end["tolerance"], True)
    est = _object(
        f"{where}: 'estimator'",
        data.get("estimator", {}),
        {"method", "k", "order", "pixel_sigma", "layout", "point", "R_w_o"},
    )
    spec.method = est.get("method", "dct")
    if spec.method not in ("dct", "smoother", "pose"):
        raise ValueError(
            f"{where}: 'estimator.method': expected 'dct' (the paper's DCT), 'smoother' "
            f"(the smoothness prior of estimate_points) or 'pose' (per-image PnP of a known "
            f"layout), got {spec.method!r}"
        )
    owner = {"k": "dct", "order": "smoother", "layout": "pose", "point": "pose", "R_w_o": "pose"}
    for key, method in owner.items():
        if key in est and spec.method != method:
            raise ValueError(f"{where}: 'estimator.{key}' belongs to method {method!r}")
    if spec.method == "pose":
        if "layout" not in est:
            raise ValueError(f"{where}: 'estimator': method 'pose' needs 'layout'")
        spec.layout = _array(f"{where}: 'estimator.layout'", est["layout"], (None, 3))
        centred = spec.layout - spec.layout.mean(0)
        if len(spec.layout) < 4 or np.linalg.matrix_rank(centred, tol=1e-6) < 2:
            raise ValueError(
                f"{where}: 'estimator.layout': expected >= 4 reference points, not all on one line"
            )
        spec.point = _array(f"{where}: 'estimator.point'", est.get("point", [0, 0, 0]), (3,))
        if "R_w_o" in est:
            R = _array(f"{where}: 'estimator.R_w_o'", est["R_w_o"], (3, 3))
            if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
                raise ValueError(f"{where}: 'estimator.R_w_o': expected a rotation matrix")
            spec.R_w_o = R
    if "order" in est:
        if est["order"] not in (1, 2) or isinstance(est["order"], bool):
            raise ValueError(f"{where}: 'estimator.order': expected 1 or 2, got {est['order']!r}")
        spec.order = est["order"]
    if "k" in est:
        k = est["k"]
        if isinstance(k, bool) or not isinstance(k, int) or not 2 <= k or 2 * times.size < 3 * k:
            raise ValueError(f"{where}: 'estimator.k': expected an int with 2 <= k <= 2F/3")
        spec.k = k
    if "pixel_sigma" in est:
        spec.pixel_sigma = _number(f"{where}: 'estimator.pixel_sigma'", est["pixel_sigma"], True)
    design = _object(
        f"{where}: 'design'",
        data.get("design", {}),
        {"starts", "n_control", "objective", "plausible_extent", "plausible_samples", "seed"},
    )
    for key in ("starts", "n_control", "plausible_samples", "seed"):
        if key in design:
            v = design[key]
            if isinstance(v, bool) or not isinstance(v, int) or v < (0 if key == "seed" else 1):
                raise ValueError(f"{where}: 'design.{key}': expected a positive int, got {v!r}")
            setattr(spec, key, v)
    if spec.n_control < 7:
        raise ValueError(f"{where}: 'design.n_control': expected >= 7, got {spec.n_control}")
    if "objective" in design:
        if design["objective"] not in ("mean_error", "error", "eta"):
            raise ValueError(
                f"{where}: 'design.objective': expected 'mean_error', 'error' or "
                f"'eta', got {design['objective']!r}"
            )
        spec.objective = design["objective"]
    if "plausible_extent" in design:
        spec.plausible_extent = _number(
            f"{where}: 'design.plausible_extent'", design["plausible_extent"], True
        )
    return spec


def read_cell(path: str | Path) -> CellSpec:
    """Read and check a CELL.json file (``ValueError`` naming file, line and key); a
    ``design.json`` written by ``jaxtraj design`` gives the cell it was designed for."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: cell file not found")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}, line {err.lineno}: malformed JSON ({err.msg})") from None
    if isinstance(data, dict) and "cell" in data and "design_seconds" in data:  # design.json
        return cell_from_dict(data["cell"], f"{path}: 'cell'")
    return cell_from_dict(data, str(path))

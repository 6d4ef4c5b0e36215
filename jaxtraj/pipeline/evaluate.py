"""Pipeline step ``evaluate``: measured results against the ground truth of a simulation.

Errors of the assembly point (position) and of the workpiece orientation at every image
with a pose, of the paper's per-point trajectories, of the fused camera poses, and of the
calibration (intrinsics and hand-eye) when the truth has them.
"""

from __future__ import annotations

import numpy as np

from ..io.records import CameraCalibration, PoseStream, quat_to_matrix

__all__ = ["evaluate_results", "quat_to_matrix", "rotation_error_deg"]  # quat_to_matrix: re-export


def rotation_error_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Angle of ``R_a^T R_b`` [deg], batched over leading axes."""
    cos = (np.trace(np.swapaxes(R_a, -1, -2) @ R_b, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _stats(values: np.ndarray, unit: str) -> dict:
    values = np.asarray(values, float)
    values = values[np.isfinite(values)]
    if values.size == 0:
        return {f"mean_{unit}": None, f"max_{unit}": None, f"rms_{unit}": None, "count": 0}
    return {
        f"mean_{unit}": float(values.mean()),
        f"max_{unit}": float(values.max()),
        f"rms_{unit}": float(np.sqrt(np.mean(values**2))),
        "count": int(values.size),
    }


def _aligned(truth: PoseStream, times: np.ndarray, what: str) -> np.ndarray:
    """Indices of ``times`` in the truth stream (the truth is sampled at the image times)."""
    idx = np.searchsorted(truth.times, times)
    idx = np.clip(idx, 0, len(truth.times) - 1)
    if not np.allclose(truth.times[idx], times, rtol=0, atol=1e-6):
        raise ValueError(f"truth/{what}: not sampled at the image times; cannot compare")
    return idx


def evaluate_results(
    *,
    times: np.ndarray,
    pose: PoseStream,
    pose_ok: np.ndarray,
    assembly_point: np.ndarray,
    model_points: np.ndarray,
    track_points: np.ndarray | None,
    camera_pose: PoseStream | None,
    camera: CameraCalibration | None,
    truth_object: PoseStream,
    truth_camera_pose: PoseStream | None,
    truth_camera: CameraCalibration | None,
) -> tuple[dict, dict]:
    """Compare a measurement with the truth.

    Returns:
        ``(summary, series)``: a JSON-ready dict of error statistics, and per-frame arrays
        (``assembly_true``/``assembly_measured`` (F, 3) [m], ``position_error_mm`` and
        ``orientation_error_deg`` (F,), NaN where no pose) for plots.
    """
    idx = _aligned(truth_object, times, "object_pose.csv")
    R_true = quat_to_matrix(truth_object.q[idx])
    p_true = truth_object.p[idx]
    R_meas = quat_to_matrix(pose.q)
    a_true = R_true @ assembly_point + p_true
    a_meas = R_meas @ assembly_point + pose.p
    pos_err = np.linalg.norm(a_meas - a_true, axis=1) * 1e3
    ang_err = rotation_error_deg(R_meas, R_true)
    pos_err[~pose_ok], ang_err[~pose_ok] = np.nan, np.nan
    summary = {
        "frames": len(times),
        "frames_with_pose": int(pose_ok.sum()),
        "assembly_point_position": _stats(pos_err, "mm"),
        "orientation": _stats(ang_err, "deg"),
    }
    points_true = np.einsum("fij,mj->fmi", R_true, model_points) + p_true[:, None]
    if track_points is not None and np.isfinite(track_points).any():
        track_err = np.linalg.norm(track_points - points_true, axis=-1) * 1e3
        summary["per_point_trajectories"] = _stats(track_err, "mm")  # flagged ones included
    if camera_pose is not None and truth_camera_pose is not None:
        j = _aligned(truth_camera_pose, camera_pose.times, "camera_pose.csv")
        dp = np.linalg.norm(camera_pose.p - truth_camera_pose.p[j], axis=1) * 1e3
        da = rotation_error_deg(
            quat_to_matrix(camera_pose.q), quat_to_matrix(truth_camera_pose.q[j])
        )
        summary["camera_pose"] = {"position": _stats(dp, "mm"), "orientation": _stats(da, "deg")}
    if camera is not None and truth_camera is not None:
        cal = {
            "focal_error_px": float(
                np.max(np.abs(np.diag(camera.K)[:2] - np.diag(truth_camera.K)[:2]))
            ),
            "principal_point_error_px": float(
                np.max(np.abs(camera.K[:2, 2] - truth_camera.K[:2, 2]))
            ),
        }
        if camera.T_f_c is not None and truth_camera.T_f_c is not None:
            cal["hand_eye_position_error_mm"] = float(
                np.linalg.norm(camera.T_f_c[:3, 3] - truth_camera.T_f_c[:3, 3]) * 1e3
            )
            cal["hand_eye_rotation_error_deg"] = float(
                rotation_error_deg(camera.T_f_c[:3, :3], truth_camera.T_f_c[:3, :3])
            )
        summary["calibration"] = cal
    series = {
        "assembly_true": a_true,
        "assembly_measured": a_meas,
        "position_error_mm": pos_err,
        "orientation_error_deg": ang_err,
    }
    return summary, series

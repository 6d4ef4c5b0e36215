"""Hand-eye calibration: the camera pose on the flange ``T_f_c`` from robot poses and
views of a calibration target, with a check of the result.

Host-side (NumPy + OpenCV 4.x ``calibrateHandEye``; OpenCV is imported lazily and only
here). With flange poses ``T_w_f_i`` and target poses in the camera ``T_c_t_i`` the
target is fixed in the world, ``T_w_t = T_w_f_i X T_c_t_i`` with ``X = T_f_c``, so every
pair of views gives ``A X = X B`` with ``A = T_w_f_j^-1 T_w_f_i`` and ``B = T_c_t_j
T_c_t_i^-1``. The check reports the residuals of these equations and the spread of the
implied target poses ``T_w_t``; a wrong or degenerate calibration shows up in both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..io.records import quat_to_matrix

__all__ = ["HandEyeResult", "calibrate_hand_eye", "hand_eye_residuals", "target_poses_from_views"]

_METHODS = ("tsai", "park", "horaud", "andreff", "daniilidis")


def _rot_angle(R):
    return np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0))


def _as_matrices(name, R_or_q, t):
    R_or_q, t = np.asarray(R_or_q, float), np.asarray(t, float)
    if R_or_q.ndim == 2 and R_or_q.shape[1] == 4:
        R = quat_to_matrix(R_or_q)
    elif R_or_q.ndim == 3 and R_or_q.shape[1:] == (3, 3):
        R = R_or_q
    else:
        raise ValueError(f"{name}: expected (N, 4) quaternions or (N, 3, 3), got {R_or_q.shape}")
    if t.shape != (R.shape[0], 3):
        raise ValueError(f"{name}: expected translations of shape ({R.shape[0]}, 3), got {t.shape}")
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise ValueError(f"{name}: non-finite entries")
    T = np.tile(np.eye(4), (R.shape[0], 1, 1))
    T[:, :3, :3], T[:, :3, 3] = R, t
    return T


@dataclass(frozen=True)
class HandEyeResult:
    """Hand-eye calibration and its check.

    Attributes:
        R_f_c, t_f_c: the camera in the flange frame (3, 3), (3,) [m].
        rotation_residual: RMS angle of ``(A X)^-1 X B`` over all view pairs [rad].
        translation_residual: RMS translation of the same [m].
        target_spread_position: RMS distance of the implied target positions from their
            mean [m]; target_spread_rotation: RMS angle from their mean [rad].
        axis_spread: smallest singular value of the unit rotation axes of the flange
            motions (0: all rotations about parallel axes, a degenerate data set).
        ok: residuals under the thresholds given to :func:`calibrate_hand_eye`.
    """

    R_f_c: np.ndarray
    t_f_c: np.ndarray
    rotation_residual: float
    translation_residual: float
    target_spread_position: float
    target_spread_rotation: float
    axis_spread: float
    ok: bool

    @property
    def T_f_c(self):
        """The result as a ``jaxlie.SE3`` (for :func:`~jaxtraj.fusion.build_events`)."""
        import jaxlie

        return jaxlie.SE3.from_matrix(np.vstack([np.c_[self.R_f_c, self.t_f_c], [0, 0, 0, 1]]))


def hand_eye_residuals(R_w_f, t_w_f, R_c_t, t_c_t, R_f_c, t_f_c) -> dict:
    """Residuals of a hand-eye transform on a data set (see :class:`HandEyeResult`).

    Args:
        R_w_f, t_w_f: (N, 4) quaternions (w, x, y, z) or (N, 3, 3), and (N, 3): flange poses.
        R_c_t, t_c_t: the same for the target in the camera.
        R_f_c, t_f_c: (3, 3), (3,) the transform to check.
    """
    T_wf = _as_matrices("R_w_f/t_w_f", R_w_f, t_w_f)
    T_ct = _as_matrices("R_c_t/t_c_t", R_c_t, t_c_t)
    if len(T_wf) != len(T_ct):
        raise ValueError(
            f"R_c_t: expected {len(T_wf)} target poses (one per robot pose), got {len(T_ct)}"
        )
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = R_f_c, t_f_c
    n = len(T_wf)
    i, j = np.triu_indices(n, 1)
    A = np.linalg.inv(T_wf[j]) @ T_wf[i]
    B = T_ct[j] @ np.linalg.inv(T_ct[i])
    E = np.linalg.inv(A @ X) @ (X @ B)
    T_wt = T_wf @ X @ T_ct
    mean_R = np.linalg.svd(T_wt[:, :3, :3].sum(0))
    R_mean = mean_R[0] @ mean_R[2]
    axes = []
    for k in range(n - 1):
        R = T_wf[k + 1, :3, :3].T @ T_wf[k, :3, :3]
        v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
        if np.linalg.norm(v) > 1e-9:
            axes.append(v / np.linalg.norm(v))
    axis_spread = (
        float(np.linalg.svd(np.array(axes), compute_uv=False)[-1]) if len(axes) >= 3 else 0.0
    )
    return {
        "rotation_residual": float(np.sqrt(np.mean(_rot_angle(E[:, :3, :3]) ** 2))),
        "translation_residual": float(np.sqrt(np.mean(np.sum(E[:, :3, 3] ** 2, -1)))),
        "target_spread_position": float(
            np.sqrt(np.mean(np.sum((T_wt[:, :3, 3] - T_wt[:, :3, 3].mean(0)) ** 2, -1)))
        ),
        "target_spread_rotation": float(
            np.sqrt(np.mean(_rot_angle(R_mean.T @ T_wt[:, :3, :3]) ** 2))
        ),
        "axis_spread": axis_spread,
    }


def calibrate_hand_eye(
    R_w_f,
    t_w_f,
    R_c_t,
    t_c_t,
    *,
    method: str = "tsai",
    max_position_spread: float = 2e-3,
    max_rotation_spread: float = np.radians(0.2),
) -> HandEyeResult:
    """``T_f_c`` from N >= 3 robot poses and target views with OpenCV's ``calibrateHandEye``.

    Args:
        R_w_f, t_w_f: flange poses from the controller: (N, 4) quaternions (w, x, y, z) or
            (N, 3, 3) rotations, and (N, 3) positions [m].
        R_c_t, t_c_t: target poses in the camera (e.g. :func:`target_poses_from_views`).
        method: ``"tsai"``, ``"park"``, ``"horaud"``, ``"andreff"`` or ``"daniilidis"``.
        max_position_spread, max_rotation_spread: thresholds [m], [rad] on the spread of
            the implied target pose for ``ok``.

    Returns:
        a :class:`HandEyeResult` with the transform and its check.
    """
    import cv2

    if method not in _METHODS:
        raise ValueError(f"method: expected one of {_METHODS}, got {method!r}")
    T_wf = _as_matrices("R_w_f/t_w_f", R_w_f, t_w_f)
    T_ct = _as_matrices("R_c_t/t_c_t", R_c_t, t_c_t)
    if len(T_wf) != len(T_ct):
        raise ValueError(
            f"R_c_t: expected {len(T_wf)} target poses (one per robot pose), got {len(T_ct)}"
        )
    if len(T_wf) < 3:
        raise ValueError(f"R_w_f: need at least 3 robot poses, got {len(T_wf)}")
    flag = getattr(cv2, f"CALIB_HAND_EYE_{method.upper()}")
    R, t = cv2.calibrateHandEye(
        list(T_wf[:, :3, :3]),
        list(T_wf[:, :3, 3]),
        list(T_ct[:, :3, :3]),
        list(T_ct[:, :3, 3]),
        method=flag,
    )
    R, t = np.asarray(R, float), np.asarray(t, float).reshape(3)
    res = hand_eye_residuals(T_wf[:, :3, :3], T_wf[:, :3, 3], T_ct[:, :3, :3], T_ct[:, :3, 3], R, t)
    ok = (
        res["target_spread_position"] <= max_position_spread
        and res["target_spread_rotation"] <= max_rotation_spread
        and res["axis_spread"] > 0.05
    )
    return HandEyeResult(R_f_c=R, t_f_c=t, ok=bool(ok), **res)


def target_poses_from_views(object_points, image_points, K, dist=None):
    """Target poses ``(R_c_t (N, 3, 3), t_c_t (N, 3))`` from detected target points by
    ``cv2.solvePnP`` (iterative).

    Args:
        object_points: (M, 3) target points in the target frame [m].
        image_points: (N, M, 2) their pixels in N views.
        K: (3, 3) camera matrix; dist: OpenCV distortion coefficients or None.
    """
    import cv2

    obj = np.asarray(object_points, np.float64)
    img = np.asarray(image_points, np.float64)
    if obj.ndim != 2 or obj.shape[1] != 3 or obj.shape[0] < 4:
        raise ValueError(f"object_points: expected shape (M >= 4, 3), got {obj.shape}")
    if img.ndim != 3 or img.shape[1:] != (obj.shape[0], 2):
        raise ValueError(f"image_points: expected shape (N, {obj.shape[0]}, 2), got {img.shape}")
    Rs, ts = [], []
    for k, uv in enumerate(img):
        ok, rvec, tvec = cv2.solvePnP(
            obj, uv, np.asarray(K, float), dist, flags=cv2.SOLVEPNP_ITERATIVE
        )
        if not ok:
            raise ValueError(f"image_points: solvePnP failed for view {k}")
        Rs.append(cv2.Rodrigues(rvec)[0])
        ts.append(tvec.reshape(3))
    return np.stack(Rs), np.stack(ts)

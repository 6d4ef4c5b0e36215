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

__all__ = [
    "METHODS",
    "HandEyeResult",
    "calibrate_hand_eye",
    "consistency",
    "hand_eye_residuals",
    "mean_pose",
    "motion_axes_check",
    "solve_hand_eye",
    "target_poses_from_views",
    "view_pose_covariances",
]

#: OpenCV's hand-eye methods: the five of ``calibrateHandEye`` (AX = XB) and the two of
#: ``calibrateRobotWorldHandEye`` (AX = ZB, which also give the target pose).
METHODS = ("tsai", "park", "horaud", "andreff", "daniilidis", "shah", "li")
_METHODS = METHODS


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
        method: one of :data:`METHODS`.
        max_position_spread, max_rotation_spread: thresholds [m], [rad] on the spread of
            the implied target pose for ``ok``.

    Returns:
        a :class:`HandEyeResult` with the transform and its check.
    """
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
    X, _ = solve_hand_eye(np.linalg.inv(T_wf), T_ct, method)
    R, t = X[:3, :3], X[:3, 3]
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


def _rigid(R, t):
    T = np.tile(np.eye(4), (*np.shape(R)[:-2], 1, 1))
    T[..., :3, :3], T[..., :3, 3] = R, t
    return T


def mean_pose(T) -> np.ndarray:
    """(4, 4) mean of (n, 4, 4) poses: chordal mean rotation, mean translation."""
    U, _, Vt = np.linalg.svd(np.sum(T[:, :3, :3], 0))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return _rigid(R, T[:, :3, 3].mean(0))


def solve_hand_eye(M, T_c_t, method: str) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form ``(X, B)`` of ``T_c_t_i = X^-1 M_i B`` by one OpenCV method.

    The model of :mod:`jaxtraj.calibration.bundle`: eye-in-hand ``M_i = T_b_f_i^-1`` gives
    ``X = T_f_c`` and ``B = T_b_t``; eye-to-hand ``M_i = T_b_f_i`` gives ``X = T_b_c`` and
    ``B = T_f_t``. The ``calibrateHandEye`` methods get ``M_i^-1`` as the gripper poses and
    return ``X``; ``B`` is then the mean of ``M_i^-1 X T_c_t_i``. ``shah`` and ``li``
    (``calibrateRobotWorldHandEye``) return both.

    Args:
        M: (V, 4, 4) robot poses as above; T_c_t: (V, 4, 4) target poses in the camera.
        method: one of :data:`METHODS`.

    Returns:
        (X, B), both (4, 4).
    """
    import cv2

    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    M, T_c_t = np.asarray(M, float), np.asarray(T_c_t, float)
    if method in ("shah", "li"):
        flag = getattr(cv2, f"CALIB_ROBOT_WORLD_HAND_EYE_{method.upper()}")
        R_bw, t_bw, R_gc, t_gc = cv2.calibrateRobotWorldHandEye(
            list(T_c_t[:, :3, :3]),
            list(T_c_t[:, :3, 3]),
            list(M[:, :3, :3]),
            list(M[:, :3, 3]),
            method=flag,
        )
        A = _rigid(np.asarray(R_gc, float), np.ravel(t_gc))
        B_inv = _rigid(np.asarray(R_bw, float), np.ravel(t_bw))
        return np.linalg.inv(A), np.linalg.inv(B_inv)
    G = np.linalg.inv(M)
    R, t = cv2.calibrateHandEye(
        list(G[:, :3, :3]),
        list(G[:, :3, 3]),
        list(T_c_t[:, :3, :3]),
        list(T_c_t[:, :3, 3]),
        method=getattr(cv2, f"CALIB_HAND_EYE_{method.upper()}"),
    )
    X = _rigid(np.asarray(R, float), np.ravel(t))
    return X, mean_pose(G @ X @ T_c_t)


def _rotvec(R):
    import cv2

    return np.stack([cv2.Rodrigues(np.ascontiguousarray(r))[0].ravel() for r in R])


def motion_axes_check(M) -> None:
    """Raise ValueError when the robot motions cannot determine a hand-eye transform.

    AX = XB needs rotations about at least two non-parallel axes: with all relative
    rotations about one axis the translation along it (and the rotation about it, for
    some methods) is undetermined. Checks the relative rotations of all view pairs.

    Args:
        M: (V, 4, 4) robot poses (either set-up; the check is on relative motions).
    """
    M = np.asarray(M, float)
    i, j = np.triu_indices(len(M), 1)
    rel = np.einsum("nji,njk->nik", M[i, :3, :3], M[j, :3, :3])
    w = _rotvec(rel)
    angle = np.linalg.norm(w, axis=1)
    big = angle > np.radians(1.0)
    if big.sum() < 2:
        raise ValueError(
            f"robot poses: the flange rotates by less than 1 deg between the views (largest "
            f"relative rotation {np.degrees(angle.max(initial=0.0)):.2f} deg); hand-eye "
            "calibration needs rotations about at least two different axes"
        )
    axes = w[big] / angle[big, None]
    scatter = axes.T @ axes / len(axes)
    lam, vec = np.linalg.eigh(scatter)
    if lam[1] < 2e-4:  # second-largest: axes within ~1 deg of one direction
        a = vec[:, 2] * np.sign(vec[np.argmax(np.abs(vec[:, 2])), 2])
        raise ValueError(
            "robot poses: all rotations between the views are about one axis "
            f"({a[0]:+.3f}, {a[1]:+.3f}, {a[2]:+.3f}) in the flange frame (spread of the "
            f"axes {np.degrees(np.sqrt(lam[1])):.2f} deg); the translation along it cannot "
            "be calibrated: add views rotated about a second axis (tilt the flange)"
        )


def view_pose_covariances(object_points, image_points, T_c_t, K, dist, pixel_sigma):
    """(V, 6, 6) covariances of per-view target poses from their corners (PnP).

    The order is (rotation perturbation on the left in the camera frame [rad],
    translation [m]); ``pixel_sigma^2 (J^T J)^-1`` with J from ``cv2.projectPoints``.

    Args:
        object_points: list of (n_i, 3) corners per view [m].
        image_points: list of (n_i, 2) pixels (unused; the Jacobian needs only the model).
        T_c_t: (V, 4, 4) the target poses; K, dist: the camera; pixel_sigma: [px].
    """
    import cv2

    out = []
    for obj, T in zip(object_points, T_c_t, strict=True):
        rvec = cv2.Rodrigues(np.ascontiguousarray(T[:3, :3]))[0]
        _, jac = cv2.projectPoints(np.asarray(obj, float), rvec, T[:3, 3], K, dist)
        J = jac[:, :6]
        cov = pixel_sigma**2 * np.linalg.pinv(J.T @ J)
        # rvec perturbation -> left rotation perturbation: d(theta) = J_l(rvec) d(rvec)
        phi = rvec.ravel()
        th = np.linalg.norm(phi)
        S = np.array([[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]])
        if th < 1e-8:
            Jl = np.eye(3) + 0.5 * S
        else:
            Jl = np.eye(3) + (1 - np.cos(th)) / th**2 * S + (th - np.sin(th)) / th**3 * S @ S
        G = np.eye(6)
        G[:3, :3] = Jl
        out.append(G @ cov @ G.T)
    return np.stack(out)


def _chi2_quantile(dof: float, z: float = 3.090) -> float:
    """Wilson-Hilferty approximation of the chi-square quantile (z = 3.09: 0.999)."""
    a = 2.0 / (9.0 * dof)
    return dof * (1 - a + z * np.sqrt(a)) ** 3


def consistency(M, T_c_t, X, view_cov=None, robot_sigma=(0.0, 0.0)) -> dict:
    """Truth-free consistency of a hand-eye result on its data, and acceptance limits.

    ``B_i = M_i^-1 X T_c_t_i`` is the target pose (eye-in-hand: in the robot base) implied
    by each view; a right calibration makes them agree up to noise. Reported: their RMS
    spread (position [m], rotation [rad]) about the mean, the AX = XB residuals over all
    view pairs, and, when ``view_cov`` is given, the limits the spread should stay under.

    Limits (chi-square style): each view's implied pose has the covariance of its PnP pose
    (``view_cov``, rotated into the base) plus the robot's noise (position sigma, and
    rotation sigma, also times the flange-to-target lever); the expected RMS spread is
    ``sqrt(mean trace C_i (V - 1) / V)`` and the limit is that times
    ``sqrt(q_0.999(3 (V - 1)) / (3 (V - 1)))`` (Wilson-Hilferty quantile).

    Args:
        M: (V, 4, 4) robot poses of the model (see :func:`solve_hand_eye`).
        T_c_t: (V, 4, 4) target poses in the camera; X: (4, 4) the hand-eye transform.
        view_cov: (V, 6, 6) from :func:`view_pose_covariances`, or None.
        robot_sigma: (position [m], rotation [rad]) noise of the controller's poses.
    """
    M, T_c_t, X = (np.asarray(a, float) for a in (M, T_c_t, X))
    G = np.linalg.inv(M)
    B = G @ X @ T_c_t
    Bm = mean_pose(B)
    V = len(B)
    dp = B[:, :3, 3] - Bm[:3, 3]
    dr = _rotvec(np.einsum("ji,njk->nik", Bm[:3, :3], B[:, :3, :3]))
    i, j = np.triu_indices(V, 1)
    A = np.linalg.inv(G[j]) @ G[i]
    Bp = T_c_t[j] @ np.linalg.inv(T_c_t[i])
    E = np.linalg.inv(A @ X) @ (X @ Bp)
    out = {
        "position_spread": float(np.sqrt(np.mean(np.sum(dp**2, 1)))),
        "rotation_spread": float(np.sqrt(np.mean(np.sum(dr**2, 1)))),
        "rotation_residual": float(np.sqrt(np.mean(_rot_angle(E[:, :3, :3]) ** 2))),
        "translation_residual": float(np.sqrt(np.mean(np.sum(E[:, :3, 3] ** 2, -1)))),
    }
    if view_cov is not None:
        s_p, s_r = (float(v) for v in robot_sigma)
        R_bc = (G @ X)[:, :3, :3]
        cov_r = np.einsum("nij,njk,nlk->nil", R_bc, view_cov[:, :3, :3], R_bc)
        cov_p = np.einsum("nij,njk,nlk->nil", R_bc, view_cov[:, 3:, 3:], R_bc)
        # the target position depends on the rotation of T_c_t only through its origin:
        # none; the robot's rotation noise moves it by the lever (target - flange).
        lever = np.linalg.norm(B[:, :3, 3] - G[:, :3, 3], axis=1)
        tr_p = np.trace(cov_p, axis1=1, axis2=2) + 3 * s_p**2 + 2 * (s_r * lever) ** 2
        tr_r = np.trace(cov_r, axis1=1, axis2=2) + 3 * s_r**2
        dof = 3 * (V - 1)
        k = np.sqrt(_chi2_quantile(dof) / dof)
        out["position_limit"] = float(k * np.sqrt(np.mean(tr_p) * (V - 1) / V))
        out["rotation_limit"] = float(k * np.sqrt(np.mean(tr_r) * (V - 1) / V))
    return out

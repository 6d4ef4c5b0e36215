"""Hand-eye calibration (OpenCV calibrateHandEye) and its check."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxtraj.camera import look_at
from jaxtraj.vision.handeye import calibrate_hand_eye, hand_eye_residuals, target_poses_from_views

K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
BOARD = np.array([[0.03 * i, 0.03 * j, 0.0] for j in range(5) for i in range(7)])
X_R = Rotation.from_euler("xyz", [5, -3, 90], degrees=True).as_matrix()
X_T = np.array([0.05, -0.02, 0.11])


def _views(rng, n=12, axis_only=None):
    """Flange poses and target-in-camera poses for a board near the world origin."""
    R_wf, t_wf, R_ct, t_ct = [], [], [], []
    centre = BOARD.mean(0)
    for _ in range(n):
        if axis_only is None:
            pos = centre + np.r_[rng.uniform(-0.25, 0.25, 2), rng.uniform(0.4, 0.6)]
            R_cw, _t_cw = (
                np.asarray(a) for a in look_at(pos, centre + rng.normal(0, 0.03, 3), (0, 1, 0))
            )
            R_wc = R_cw.T
        else:  # rotations about one axis only: degenerate for hand-eye
            R_wc = Rotation.from_rotvec(axis_only * rng.uniform(-0.5, 0.5)).as_matrix() @ np.diag(
                [1, -1, -1]
            )
            pos = centre + np.r_[rng.uniform(-0.05, 0.05, 2), 0.5]
        T_wc = np.eye(4)
        T_wc[:3, :3], T_wc[:3, 3] = R_wc, pos
        X = np.eye(4)
        X[:3, :3], X[:3, 3] = X_R, X_T
        T_wf = T_wc @ np.linalg.inv(X)
        T_ct = np.linalg.inv(T_wc)  # target frame = world
        R_wf.append(T_wf[:3, :3])
        t_wf.append(T_wf[:3, 3])
        R_ct.append(T_ct[:3, :3])
        t_ct.append(T_ct[:3, 3])
    return np.array(R_wf), np.array(t_wf), np.array(R_ct), np.array(t_ct)


def _rot_err(A, B):
    return np.degrees(np.linalg.norm(Rotation.from_matrix(A.T @ B).as_rotvec()))


@pytest.mark.parametrize("method", ["tsai", "park", "daniilidis"])
def test_exact_data_recovers_transform(rng, method):
    res = calibrate_hand_eye(*_views(rng), method=method)
    assert _rot_err(res.R_f_c, X_R) < 1e-4
    np.testing.assert_allclose(res.t_f_c, X_T, atol=1e-6)
    assert res.ok and res.translation_residual < 1e-6 and res.target_spread_position < 1e-6


def test_from_pixels_with_noise(rng):
    R_wf, t_wf, R_ct, t_ct = _views(rng, n=15)
    pix = []
    for R, t in zip(R_ct, t_ct, strict=True):
        uv, _ = cv2.projectPoints(BOARD, cv2.Rodrigues(R)[0], t, K, None)
        pix.append(uv.reshape(-1, 2) + rng.normal(0, 0.2, (len(BOARD), 2)))
    R_est, t_est = target_poses_from_views(BOARD, np.array(pix), K)
    # quaternion input for the robot poses (w, x, y, z), as the controller gives them
    q_wf = Rotation.from_matrix(R_wf).as_quat()[:, [3, 0, 1, 2]]
    res = calibrate_hand_eye(q_wf, t_wf, R_est, t_est)
    assert _rot_err(res.R_f_c, X_R) < 0.3
    assert np.linalg.norm(res.t_f_c - X_T) < 3e-3
    assert res.ok
    T = res.T_f_c  # as jaxlie.SE3
    np.testing.assert_allclose(np.asarray(T.translation()), res.t_f_c, atol=1e-12)


def test_check_flags_a_wrong_transform(rng):
    data = _views(rng)
    good = hand_eye_residuals(*data, X_R, X_T)
    bad = hand_eye_residuals(*data, X_R, X_T + np.array([0.02, 0, 0]))
    assert good["target_spread_position"] < 1e-9
    assert bad["target_spread_position"] > 4e-3 and bad["translation_residual"] > 4e-3


def test_degenerate_motion_is_not_ok(rng):
    res = calibrate_hand_eye(*_views(rng, axis_only=np.array([0.0, 0.0, 1.0])))
    assert res.axis_spread < 1e-6
    assert not res.ok


def test_bad_inputs(rng):
    R_wf, t_wf, R_ct, t_ct = _views(rng, n=4)
    with pytest.raises(ValueError, match="R_w_f: need at least 3"):
        calibrate_hand_eye(R_wf[:2], t_wf[:2], R_ct[:2], t_ct[:2])
    with pytest.raises(ValueError, match="R_c_t: expected 4 target poses"):
        calibrate_hand_eye(R_wf, t_wf, R_ct[:3], t_ct[:3])
    with pytest.raises(ValueError, match="method"):
        calibrate_hand_eye(R_wf, t_wf, R_ct, t_ct, method="magic")
    with pytest.raises(ValueError, match=r"R_w_f/t_w_f: expected translations of shape \(4, 3\)"):
        calibrate_hand_eye(R_wf, t_wf[:, :2], R_ct, t_ct)
    with pytest.raises(ValueError, match="image_points"):
        target_poses_from_views(BOARD, np.zeros((2, 3, 2)), K)


def test_view_pose_covariance_matches_pnp_scatter(rng):
    """The per-view pose covariance behind the acceptance limits, against Monte Carlo PnP."""
    from jaxtraj.vision.handeye import view_pose_covariances

    _, _, R_ct, t_ct = _views(rng, n=1)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_ct[0], t_ct[0]
    uv0, _ = cv2.projectPoints(BOARD, cv2.Rodrigues(R_ct[0])[0], t_ct[0], K, None)
    uv0 = uv0.reshape(-1, 2)
    cov = view_pose_covariances([BOARD], [uv0], T[None], K, np.zeros(5), 0.3)[0]
    draws = []
    for _ in range(300):
        _, rv, tv = cv2.solvePnP(BOARD, uv0 + rng.normal(0, 0.3, uv0.shape), K, None)
        dR = cv2.Rodrigues(rv)[0] @ R_ct[0].T  # left perturbation in the camera frame
        draws.append(np.r_[cv2.Rodrigues(dR)[0].ravel(), tv.ravel() - t_ct[0]])
    emp = np.cov(np.array(draws).T)
    # 300 draws: variances within about +-20 %; measured ratios 0.9-1.1.
    np.testing.assert_allclose(np.diag(emp) / np.diag(cov), 1.0, atol=0.25)

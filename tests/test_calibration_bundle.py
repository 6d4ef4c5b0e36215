"""The JAX hand-eye bundle adjustment against OpenCV's closed forms on simulated cells."""

from __future__ import annotations

from pathlib import Path

import cv2
import jax
import numpy as np
import pytest

from jaxtraj.calibration import PARAMETER_NAMES, bundle_residuals, refine_hand_eye
from jaxtraj.io.robot_poses import RobotPoses
from jaxtraj.pipeline.calibrate import CalibrationOptions, calibrate_views
from jaxtraj.sim.calibration_views import simulate_views
from jaxtraj.vision.calibration import CalibrationTarget
from jaxtraj.vision.handeye import METHODS, solve_hand_eye

TARGET = CalibrationTarget("chessboard", 9, 6, 0.025)
BOARD = TARGET.object_points()
VIEWS = 12


def _rot_deg(A, B):
    return float(np.degrees(np.linalg.norm(cv2.Rodrigues(A[:3, :3].T @ B[:3, :3])[0])))


def _opencv(s):
    """calibrateCamera, then every hand-eye method: (K, dist, rms, T_c_t, {method: X})."""
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    obj = [BOARD.astype(np.float32)] * len(s.uv)
    img = [u.astype(np.float32).reshape(-1, 1, 2) for u in s.uv]
    rms, K, d, rv, tv = cv2.calibrateCamera(obj, img, s.image_size, None, None, criteria=crit)
    T_c_t = np.tile(np.eye(4), (len(rv), 1, 1))
    for k, (r, t) in enumerate(zip(rv, tv, strict=True)):
        T_c_t[k, :3, :3], T_c_t[k, :3, 3] = cv2.Rodrigues(r)[0], np.ravel(t)
    M = np.linalg.inv(s.T_b_f) if s.eye_in_hand else s.T_b_f
    sols = {m: solve_hand_eye(M, T_c_t, m) for m in METHODS}
    return K, np.ravel(d)[:5], rms, T_c_t, M, sols


def _refine(s, K, d, rms, X, B, sigma_mm, sigma_deg):
    return refine_hand_eye(
        BOARD, s.uv, np.ones(s.uv.shape[:2]), s.T_b_f, K, d, X, B,
        eye_in_hand=s.eye_in_hand, pixel_sigma=rms / np.sqrt(2),
        robot_position_sigma=sigma_mm * 1e-3, robot_rotation_sigma=np.radians(sigma_deg),
        loss_scale=3 * rms,
    )  # fmt: skip


def test_exact_data_from_a_perturbed_start_recovers_the_truth():
    s = simulate_views(BOARD, views=VIEWS, seed=1, pixel_sigma=0.0, robot_position_sigma=0.0,
                       robot_rotation_sigma=0.0)  # fmt: skip
    e = np.asarray(bundle_residuals(BOARD, s.uv, s.T_b_f, s.K, s.dist, s.T_x, s.T_b))
    assert np.abs(e).max() < 1e-9
    K0 = s.K + np.diag([4.0, -3.0, 0.0])
    X0 = s.T_x.copy()
    X0[:3, :3] = X0[:3, :3] @ cv2.Rodrigues(np.array([0.01, -0.01, 0.02]))[0]
    X0[:3, 3] += [2e-3, -1e-3, 3e-3]
    B0 = s.T_b.copy()
    B0[:3, 3] += [-3e-3, 2e-3, 1e-3]
    r = refine_hand_eye(BOARD, s.uv, np.ones(s.uv.shape[:2]), s.T_b_f, K0, s.dist * 0.5, X0, B0,
                        pixel_sigma=0.1)  # fmt: skip
    assert bool(r.converged) and float(r.rms_px) < 1e-7 and float(r.rms_px_initial) > 5
    np.testing.assert_allclose(np.asarray(r.K), s.K, atol=1e-6)
    np.testing.assert_allclose(np.asarray(r.dist), s.dist, atol=1e-8)
    np.testing.assert_allclose(np.asarray(r.T_x), s.T_x, atol=1e-9)
    np.testing.assert_allclose(np.asarray(r.T_b), s.T_b, atol=1e-9)
    assert np.abs(np.asarray(r.robot_corrections)).max() < 1e-10
    assert r.covariance.shape == (21, 21) and len(PARAMETER_NAMES) == 21


def _report(s, level):
    """The calibrate command's computation on a simulated set (corners given)."""
    corners = {f"view_{k}.png": (np.arange(len(BOARD)), uv) for k, uv in enumerate(s.uv)}
    robot = RobotPoses(s.T_b_f, None, np.arange(len(s.uv)) + 2, Path("robot.csv"))
    sigma = (level * 1e-3, np.radians(level / 10))
    # Gauss-Newton from OpenCV's start: the LM minimum to 1e-7 mm in a quarter of the steps.
    options = CalibrationOptions(
        robot_sigma=sigma, eye_to_hand=not s.eye_in_hand, solver="gauss-newton"
    )
    return calibrate_views(corners, TARGET, s.image_size, robot=robot, options=options)


def test_refinement_beats_every_opencv_method_over_seeds():
    """Eye-in-hand, 12 views, 0.1 px corners, robot noise 0.1-0.3 mm / 0.01-0.03 deg."""
    names = (*METHODS, "refined")
    t_err = {m: [] for m in names}
    r_err = {m: [] for m in names}
    k_err_cv, k_err_ref, nees = [], [], []
    for seed in range(10):
        level = (0.1, 0.2, 0.3)[seed % 3]
        s = simulate_views(BOARD, views=VIEWS, seed=seed, pixel_sigma=0.1,
                           robot_position_sigma=level * 1e-3,
                           robot_rotation_sigma=np.radians(level / 10))  # fmt: skip
        report = _report(s, level)
        he = report.hand_eye
        sols = {m: np.asarray(he["methods"][m]["T_x"]) for m in METHODS}
        sols["refined"] = np.asarray(he["T_x"])
        for m, X in sols.items():
            t_err[m].append(np.linalg.norm(X[:3, 3] - s.T_x[:3, 3]))
            r_err[m].append(_rot_deg(X, s.T_x))
        # Truth-free consistency reported by the command: the refined result makes the
        # target poses implied by the views agree better than any OpenCV method.
        spread = he["refined"]["target_spread_position_mm"]
        assert spread < min(he["methods"][m]["target_spread_position_mm"] for m in METHODS)
        # The orientation spread is mostly the per-view PnP and robot rotation noise, which
        # no hand-eye removes, and the closed forms fit their rotation to these very poses:
        # the refined one is level with the best (measured 0.73-1.10 times the best), while
        # its rotation is the closest to the truth on average (below).
        rot = he["refined"]["target_spread_rotation_deg"]
        assert rot < 1.2 * min(he["methods"][m]["target_spread_rotation_deg"] for m in METHODS)
        assert he["ok"], he["reasons"]
        pick = [(0, 0), (1, 1), (0, 2), (1, 2)]
        K_cv = np.asarray(report.intrinsics["opencv"]["K"])
        k_err_cv.append(sum(abs(K_cv[i] - s.K[i]) for i in pick))
        k_err_ref.append(sum(abs(report.camera.K[i] - s.K[i]) for i in pick))
        dt = (sols["refined"][:3, 3] - s.T_x[:3, 3]) * 1e3
        nees.append(
            np.mean((dt / np.asarray(he["refined"]["std"]["hand_eye_translation_mm"])) ** 2)
        )
    mean_t = {m: np.mean(v) * 1e3 for m, v in t_err.items()}
    mean_r = {m: np.mean(v) for m, v in r_err.items()}
    best = min(METHODS, key=lambda m: mean_t[m])
    # Measured (10 seeds): refined 0.91 mm, 0.118 deg; best OpenCV li 1.84 mm (shah 2.06,
    # andreff 2.20, tsai/park/horaud/daniilidis 3.2-3.4 mm), 0.151 deg (all methods
    # 0.151-0.157). The rotation gains less: a shift of the principal point is a rotation
    # of the camera, so the hand-eye rotation is no better than the intrinsics pin it down.
    # Intrinsics (|dfx| + |dfy| + |dcx| + |dcy|): 3.0 px refined, 6.7 px calibrateCamera.
    # NEES of the hand-eye translation per axis: 1.4 (the covariance is about right).
    assert mean_t["refined"] < mean_t[best] / 2.0, mean_t
    assert mean_r["refined"] < min(mean_r[m] for m in METHODS), mean_r
    # Intrinsics (fx, fy, cx, cy) at least as close as cv2.calibrateCamera's.
    assert np.mean(k_err_ref) <= np.mean(k_err_cv), (np.mean(k_err_ref), np.mean(k_err_cv))
    assert 0.3 < np.mean(nees) < 2.5, nees


def test_eye_to_hand():
    s = simulate_views(BOARD, views=VIEWS, seed=4, pixel_sigma=0.1, eye_in_hand=False)
    K, d, rms, _, _, sols = _opencv(s)
    errs = {m: np.linalg.norm(X[:3, 3] - s.T_x[:3, 3]) for m, (X, _) in sols.items()}
    r = _refine(s, K, d, rms, *sols["park"], 0.2, 0.02)
    err = np.linalg.norm(np.asarray(r.T_x)[:3, 3] - s.T_x[:3, 3])
    # Measured: refined 0.4 mm; OpenCV 0.8 (li) to 3.6 mm.
    assert err < 1e-3 and err < min(errs.values()), (err, errs)
    assert _rot_deg(np.asarray(r.T_x), s.T_x) < 0.3  # measured 0.20 (OpenCV 0.21-0.23)
    np.testing.assert_allclose(np.asarray(r.T_b)[:3, 3], s.T_b[:3, 3], atol=2e-3)


def test_jit_and_float32_and_errors():
    s = simulate_views(BOARD, views=VIEWS, seed=2, pixel_sigma=0.1)
    args = (BOARD, s.uv, s.T_b_f, s.K, s.dist, s.T_x, s.T_b)
    eager = np.asarray(bundle_residuals(*args))
    jitted = np.asarray(jax.jit(bundle_residuals)(*args))
    np.testing.assert_allclose(jitted, eager, atol=1e-12)
    e32 = bundle_residuals(*(np.asarray(a, np.float32) for a in args))
    assert e32.dtype == np.float32
    np.testing.assert_allclose(np.asarray(e32), eager, atol=2e-3)  # projections of ~400 px
    w = np.ones(s.uv.shape[:2])
    # float32 with x64 enabled: the Levenberg-Marquardt fit runs in float64 (its damping is
    # float64; float32 failed there) and returns float32
    f32 = (np.asarray(a, np.float32) for a in (s.uv, w, s.T_b_f, s.K, s.dist, s.T_x, s.T_b))
    r32 = refine_hand_eye(BOARD, *f32)
    assert r32.K.dtype == r32.T_x.dtype == r32.covariance.dtype == np.float32
    r64 = refine_hand_eye(BOARD, s.uv, w, s.T_b_f, s.K, s.dist, s.T_x, s.T_b)
    assert np.abs(np.asarray(r32.T_x) - np.asarray(r64.T_x)).max() < 1e-5
    assert np.abs(np.asarray(r32.K) - np.asarray(r64.K)).max() < 1e-2  # [px]
    with pytest.raises(ValueError, match=r"T_b_f: expected robot poses .* \(12, 4, 4\)"):
        refine_hand_eye(BOARD, s.uv, w, s.T_b_f[:3], s.K, s.dist, s.T_x, s.T_b)
    with pytest.raises(ValueError, match="solver"):
        refine_hand_eye(BOARD, s.uv, w, s.T_b_f, s.K, s.dist, s.T_x, s.T_b, solver="bfgs")
    with pytest.raises(ValueError, match="loss"):
        refine_hand_eye(BOARD, s.uv, w, s.T_b_f, s.K, s.dist, s.T_x, s.T_b, loss="tukey")
    with pytest.raises(ValueError, match="pixel_sigma"):
        refine_hand_eye(BOARD, s.uv, w, s.T_b_f, s.K, s.dist, s.T_x, s.T_b, pixel_sigma=0)
    with pytest.raises(ValueError, match="weights: fewer than 11"):
        refine_hand_eye(BOARD, s.uv, w * 0, s.T_b_f, s.K, s.dist, s.T_x, s.T_b)

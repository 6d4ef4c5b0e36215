"""The hand-eye part of ``jaxtraj calibrate``: every OpenCV method scored by its
consistency, the bundle adjustment from the best one, and the acceptance check
(steps 3-5 of :mod:`jaxtraj.pipeline.calibrate`)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

__all__ = ["hand_eye_step"]


def _rigid(R, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _consistency_dict(c: dict) -> dict:
    out = {
        "target_spread_position_mm": c["position_spread"] * 1e3,
        "target_spread_rotation_deg": float(np.degrees(c["rotation_spread"])),
        "rotation_residual_deg": float(np.degrees(c["rotation_residual"])),
        "translation_residual_mm": c["translation_residual"] * 1e3,
    }
    if "position_limit" in c:
        out["position_limit_mm"] = c["position_limit"] * 1e3
        out["rotation_limit_deg"] = float(np.degrees(c["rotation_limit"]))
    return out


def _score(c: dict) -> float:
    return (c["position_spread"] / c["position_limit"]) ** 2 + (
        c["rotation_spread"] / c["rotation_limit"]
    ) ** 2


def _pnp(obj, uv, K, dist, T0):
    import cv2

    rvec = cv2.Rodrigues(np.ascontiguousarray(T0[:3, :3]))[0]
    _, rvec, tvec = cv2.solvePnP(
        obj, uv, K, dist, rvec.copy(), T0[:3, 3].reshape(3, 1).copy(), True, cv2.SOLVEPNP_ITERATIVE
    )
    return _rigid(cv2.Rodrigues(rvec)[0], tvec.ravel())


def hand_eye_step(result, target, T_b_f, options, robot_source: str) -> tuple:
    """Hand-eye from a :class:`~jaxtraj.vision.calibration.CalibrationResult` and the
    flange poses of its used views; returns ``(K, dist, rms, X, report dict)``."""
    import cv2

    from ..calibration import refine_hand_eye

    if options.robot_sigma is None:
        from .calibrate import DEFAULT_ROBOT_SIGMA

        options = replace(options, robot_sigma=DEFAULT_ROBOT_SIGMA)
    from ..vision.handeye import (
        METHODS,
        consistency,
        motion_axes_check,
        solve_hand_eye,
        view_pose_covariances,
    )

    try:
        motion_axes_check(T_b_f)
    except ValueError as err:
        raise ValueError(f"{robot_source}: {err}") from None
    cal = result.calibration
    obj_all = target.object_points()
    objs = [obj_all[ids] for ids in result.ids]
    T_c_t = np.stack([_rigid(R, t) for R, t in zip(result.R_c_t, result.t_c_t, strict=True)])
    eih = not options.eye_to_hand
    M = np.linalg.inv(T_b_f) if eih else T_b_f
    n_obs = sum(len(i) for i in result.ids)
    dof = 2 * n_obs - 9 - 6 * len(objs)
    pixel_sigma = max(cal.rms_px * np.sqrt(n_obs / max(dof, 1)), 1e-3)  # per coordinate
    cov = view_pose_covariances(objs, result.uv, T_c_t, cal.K, cal.dist, pixel_sigma)
    methods, solutions = {}, {}
    for m in METHODS:
        try:
            X, B = solve_hand_eye(M, T_c_t, m)
        except cv2.error as err:  # OpenCV refused (degenerate data): report, go on
            methods[m] = {"error": str(err).strip().splitlines()[-1]}
            continue
        if not (np.all(np.isfinite(X)) and np.all(np.isfinite(B))):
            methods[m] = {"error": "non-finite result"}
            continue
        c = consistency(M, T_c_t, X, cov, options.robot_sigma)
        methods[m] = {**_consistency_dict(c), "score": _score(c), "T_x": X.tolist()}
        solutions[m] = (X, B, c)
    if not solutions:
        raise ValueError(f"{robot_source}: every OpenCV hand-eye method failed: {methods}")
    if options.method == "auto":
        method = min(solutions, key=lambda m: methods[m]["score"])
    elif options.method in solutions:
        method = options.method
    else:
        raise ValueError(
            f"method: {options.method!r} failed on these data ({methods[options.method]})"
        )
    X, B, c = solutions[method]
    K, dist, rms = cal.K, cal.dist, cal.rms_px
    refined = None
    if options.refine:
        N = len(obj_all)
        uv = np.zeros((len(objs), N, 2))
        w = np.zeros((len(objs), N))
        for v, (ids, p) in enumerate(zip(result.ids, result.uv, strict=True)):
            uv[v, ids], w[v, ids] = p, 1.0
        r = refine_hand_eye(
            obj_all, uv, w, T_b_f, K, dist, X, B,
            eye_in_hand=eih,
            pixel_sigma=pixel_sigma,
            robot_position_sigma=options.robot_sigma[0],
            robot_rotation_sigma=options.robot_sigma[1],
            loss="huber",
            loss_scale=3.0 * max(rms, 0.05),
            solver=options.solver,
        )  # fmt: skip
        K, dist = np.asarray(r.K), np.asarray(r.dist)
        X, B = np.asarray(r.T_x), np.asarray(r.T_b)
        T_c_t = np.stack(
            [_pnp(o, p, K, dist, T) for o, p, T in zip(objs, result.uv, T_c_t, strict=True)]
        )
        cov = view_pose_covariances(objs, result.uv, T_c_t, K, dist, pixel_sigma)
        c = consistency(M, T_c_t, X, cov, options.robot_sigma)
        std = np.asarray(r.std)
        refined = {
            **_consistency_dict(c),
            "rms_px": float(r.rms_px),
            "rms_px_start": float(r.rms_px_initial),
            "variance_factor": float(r.variance_factor),
            "steps": int(r.steps),
            "converged": bool(r.converged),
            "std": {
                "fx_px": float(std[0]),
                "fy_px": float(std[1]),
                "cx_px": float(std[2]),
                "cy_px": float(std[3]),
                "hand_eye_rotation_deg": np.degrees(std[9:12]).tolist(),
                "hand_eye_translation_mm": (std[12:15] * 1e3).tolist(),
                "target_rotation_deg": np.degrees(std[15:18]).tolist(),
                "target_translation_mm": (std[18:21] * 1e3).tolist(),
            },
        }
        rms = float(r.rms_px)
    limits = (
        options.max_position_spread if options.max_position_spread else c["position_limit"],
        options.max_rotation_spread if options.max_rotation_spread else c["rotation_limit"],
    )
    reasons = []
    if c["position_spread"] > limits[0]:
        reasons.append(
            f"the target position implied by the views spreads by {c['position_spread'] * 1e3:.2f}"
            f" mm RMS, over the limit {limits[0] * 1e3:.2f} mm"
        )
    if c["rotation_spread"] > limits[1]:
        reasons.append(
            f"the target orientation implied by the views spreads by "
            f"{np.degrees(c['rotation_spread']):.3f} deg RMS, over the limit "
            f"{np.degrees(limits[1]):.3f} deg"
        )
    derived = options.max_position_spread is None and options.max_rotation_spread is None
    if reasons and derived:
        reasons.append(
            f"the limits assume robot pose noise of {options.robot_sigma[0] * 1e3:.3g} mm and "
            f"{np.degrees(options.robot_sigma[1]):.3g} deg and {pixel_sigma:.3g} px corner noise "
            "(from the intrinsic calibration); if the controller is noisier, say so with "
            "--robot-sigma-mm/--robot-sigma-deg, or set --max-spread-mm/--max-spread-deg"
        )
    hand_eye = {
        **_consistency_dict(c),
        "position_limit_mm": limits[0] * 1e3,
        "rotation_limit_deg": float(np.degrees(limits[1])),
        "limits": "derived from the data" if derived else "given",
        "ok": not reasons,
        "reasons": reasons,
        "method": method,
        "result": "refined" if refined is not None else method,
        "eye_in_hand": eih,
        "pixel_sigma_px": pixel_sigma,
        "methods": methods,
        "refined": refined,
        "T_x": X.tolist(),
        "T_b": B.tolist(),
    }
    return K, dist, rms, X, hand_eye

"""Pipeline step ``reconstruct``: detections + camera poses -> trajectories and 6-DoF pose.

Two measurements come out of the same detections:

* the **6-DoF pose** ``T_w_o`` of the workpiece at every image with >= 4 detected
  reference points: the object pose in the camera (PnP on the undistorted pixels, then
  Levenberg-Marquardt on the reprojection error, OpenCV) composed with the fused camera
  pose ``T_w_c``. Optionally (``pose_method="joint"``) one smooth rigid motion in a DCT
  basis is then fitted to all pixels at once (:func:`jaxtraj.estimators.fit_rigid_trajectory`),
  starting from the per-image poses. The reference points and the assembly point follow
  from the pose.
* the **point trajectories** of the paper: every reference point reconstructed on its
  own from its rays (no object model), with the smoothness prior or the plain DCT, and
  the solver's status. They need a camera path that makes each point reconstructible and
  are reported next to the model-based points.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from ..basis import DCTBasis
from ..camera import undistort_points
from ..io.records import (
    CameraCalibration,
    Detections,
    ObjectModel,
    PoseStream,
    matrix_to_quat,
    quat_to_matrix,
)

__all__ = ["POSE_METHODS", "TRACK_METHODS", "Measurement", "reconstruct_recording"]

POSE_METHODS = ("pnp", "joint")
TRACK_METHODS = ("estimate", "smoother", "dct", "none")
#: A frame whose model-based reprojection RMS exceeds this [px] is not trusted.
MAX_FRAME_RMS_PX = 3.0
#: A per-point trajectory whose largest posterior standard deviation exceeds this [m] is
#: flagged as not OK (the camera path does not determine it well).
MAX_TRACK_STD_M = 0.01


@dataclass(frozen=True)
class Measurement:
    """What ``reconstruct`` measured (NumPy).

    Attributes:
        times, frames: (F,) image times [s] and frame numbers.
        ids: (M,) reference-point ids (the object model's order).
        pose: ``T_w_o`` at every frame (rows of frames without a pose repeat a neighbour;
            use ``pose_ok``).
        pose_ok: (F,) a pose was measured and passed its checks.
        pose_rms_px: (F,) reprojection RMS of the pose [px] (NaN without a pose).
        points: (F, M, 3) reference points from the pose [m].
        assembly: (F, 3) the assembly point from the pose [m].
        track_points: (F, M, 3) per-point trajectories of the paper's method [m] (NaN
            when ``track_method="none"``).
        track_ok: (M,) solver status OK per point (and, for the smoother, posterior standard
            deviation below :data:`MAX_TRACK_STD_M`); track_rms_px: (M,) reprojection RMS.
        track_std: (M,) largest posterior position standard deviation over the frames [m]
            (first-order, from the assumed pixel noise), or NaN.
        skipped: (frame, reason) for frames without a pose.
        pose_method, track_method: the estimators used.
    """

    times: np.ndarray
    frames: np.ndarray
    ids: np.ndarray
    pose: PoseStream
    pose_ok: np.ndarray
    pose_rms_px: np.ndarray
    points: np.ndarray
    assembly: np.ndarray
    track_points: np.ndarray
    track_ok: np.ndarray
    track_rms_px: np.ndarray
    track_std: np.ndarray
    skipped: list = field(default_factory=list)
    pose_method: str = "pnp"
    track_method: str = "estimate"


def _pnp(model: np.ndarray, uv: np.ndarray, K: np.ndarray):
    """Object pose in the camera from >= 4 undistorted pixels: SQPnP then LM refinement."""
    import cv2

    obj, img = model.astype(np.float64), uv.astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, None, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, None)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
    return cv2.Rodrigues(rvec)[0], tvec.reshape(3), rms


def _fill(values: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Rows where ``ok`` is False copied from the nearest valid row (for smooth outputs)."""
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return values
    nearest = idx[np.clip(np.searchsorted(idx, np.arange(len(ok))), 0, idx.size - 1)]
    return values[nearest]


def reconstruct_recording(
    detections: Detections,
    camera: CameraCalibration,
    cameras: PoseStream,
    model: ObjectModel,
    *,
    pose_method: str = "pnp",
    track_method: str = "estimate",
    k: int = 20,
    pixel_sigma: float = 0.1,
) -> Measurement:
    """Measure the workpiece from its detections and the fused camera poses.

    Args:
        detections: (F, M) detections in the object model's id order.
        camera: intrinsics and distortion of the camera.
        cameras: camera poses ``T_w_c`` at the same image times (from ``fuse``).
        model: reference points in the object frame and the assembly point.
        pose_method: ``"pnp"`` (per image) or ``"joint"`` (one smooth motion, DCT ``k``).
        track_method: per-point trajectories with ``"estimate"`` (the default:
            :func:`jaxtraj.estimate_points`, model chosen per point, DEGENERATE where the
            depth is not determined), ``"smoother"`` (order 2), ``"dct"`` (``k``
            vectors) or ``"none"``.
        k: DCT vectors for ``"joint"`` and ``"dct"``.
        pixel_sigma: detection noise [px] assumed by the smoother.

    Raises:
        ValueError: mismatched inputs, unknown methods, or no frame with a pose.
    """
    if pose_method not in POSE_METHODS:
        raise ValueError(f"pose_method: expected one of {POSE_METHODS}, got {pose_method!r}")
    if track_method not in TRACK_METHODS:
        raise ValueError(f"track_method: expected one of {TRACK_METHODS}, got {track_method!r}")
    if not np.array_equal(detections.ids, model.ids):
        raise ValueError("detections: columns must follow the object model's ids")
    if detections.times.shape != cameras.times.shape or not np.allclose(
        detections.times, cameras.times, rtol=0, atol=1e-6
    ):
        raise ValueError("cameras: camera poses must be given at the detections' image times")
    F, M = detections.detected.shape
    K = camera.K
    uv = np.asarray(undistort_points(jnp.asarray(detections.uv), jnp.asarray(K), camera.dist))
    det = detections.detected & np.all(np.isfinite(uv), axis=-1)
    uv = np.where(det[..., None], uv, 0.0)

    R_w_o = np.tile(np.eye(3), (F, 1, 1))
    t_w_o = np.zeros((F, 3))
    rms = np.full(F, np.nan)
    ok = np.zeros(F, bool)
    skipped = []
    R_w_c = quat_to_matrix(cameras.q)
    R_c_w = np.swapaxes(R_w_c, -1, -2)
    t_c_w = -np.einsum("fij,fj->fi", R_c_w, cameras.p)
    for f in range(F):
        n = int(det[f].sum())
        if n < 4:
            skipped.append((int(detections.frames[f]), f"{n} reference point(s) detected, need 4"))
            continue
        sol = _pnp(model.points[det[f]], uv[f][det[f]], K)
        if sol is None:
            skipped.append((int(detections.frames[f]), "PnP failed"))
            continue
        R_c_o, t_c_o, rms[f] = sol
        if rms[f] > MAX_FRAME_RMS_PX:
            skipped.append(
                (int(detections.frames[f]), f"pose reprojection RMS {rms[f]:.2f} px is too large")
            )
            continue
        R_w_o[f] = R_w_c[f] @ R_c_o
        t_w_o[f] = R_w_c[f] @ (t_c_o - t_c_w[f])
        ok[f] = True
    if not ok.any():
        raise ValueError(
            "no image has 4 or more detected reference points: nothing to measure "
            f"(frames: {F}, detections per frame: max {int(det.sum(axis=1).max())})"
        )
    R_w_o, t_w_o = _fill(R_w_o, ok), _fill(t_w_o, ok)
    P = np.einsum("ij,fjk->fik", K, np.concatenate([R_c_w, t_c_w[..., None]], -1))
    weights = det.astype(float)

    if pose_method == "joint":
        from ..estimators import fit_rigid_trajectory

        w_joint = weights * ok[:, None]
        basis = DCTBasis.from_times(detections.times, k)(detections.times)
        fit = fit_rigid_trajectory(
            P, np.swapaxes(uv, 0, 1), model.points, basis, w_joint.T, init=(R_w_o, t_w_o)
        )
        R_w_o, t_w_o = np.asarray(fit.R), np.asarray(fit.t)

    points = np.einsum("fij,mj->fmi", R_w_o, model.points) + t_w_o[:, None]
    assembly = R_w_o @ model.assembly_point + t_w_o
    track_points = np.full((F, M, 3), np.nan)
    track_ok = np.zeros(M, bool)
    track_rms = np.full(M, np.nan)
    track_std = np.full(M, np.nan)
    if track_method != "none":
        track_points, track_ok, track_rms, track_std = _tracks(
            track_method, P, uv, detections.times, weights, k, pixel_sigma
        )
    pose = PoseStream(detections.times, t_w_o, matrix_to_quat(R_w_o))
    return Measurement(
        times=detections.times,
        frames=detections.frames,
        ids=model.ids,
        pose=pose,
        pose_ok=ok,
        pose_rms_px=rms,
        points=points,
        assembly=assembly,
        track_points=track_points,
        track_ok=track_ok,
        track_rms_px=track_rms,
        track_std=track_std,
        skipped=skipped,
        pose_method=pose_method,
        track_method=track_method,
    )


def _tracks(method, P, uv, times, weights, k, pixel_sigma):
    """Per-point trajectories (F, M, 3), OK flags (M,), RMS (M,) and largest posterior
    standard deviation (M,) [m], the paper's way (each point on its own)."""
    from ..solve import Status

    uv_t, w_t = np.swapaxes(uv, 0, 1), weights.T
    if method == "dct":
        from ..estimators.covariance import dct_covariance
        from ..solve import reconstruct_points

        basis = DCTBasis.from_times(times, k)(times)
        res = reconstruct_points(P, uv_t, basis, w_t)
        cov = jax.vmap(
            lambda u, c, w: dct_covariance(P, u, basis, c, w, pixel_sigma=pixel_sigma).points
        )(jnp.asarray(uv_t), res.coeffs, jnp.asarray(w_t))
        pts, rms = res.points, res.rms_px
        ok = np.asarray(res.status == Status.OK)
    elif method == "smoother":
        from ..estimators import smooth_points

        res = smooth_points(P, uv_t, times, w_t, pixel_sigma=pixel_sigma, covariance=True)
        pts, cov, rms = res.points, res.cov, res.rms_px
        ok = np.asarray(res.status == Status.OK)
    else:  # estimate: model chosen per point, along-ray uncertainty, DEGENERATE flag
        from ..estimators.estimate import estimate_points

        res = estimate_points(P, uv_t, times, w_t, pixel_sigma=pixel_sigma)
        pts, cov, rms = res.points, res.cov, res.rms_px
        ok = np.asarray(res.status == Status.OK)
    std = np.sqrt(np.max(np.trace(np.asarray(cov), axis1=-2, axis2=-1), axis=-1))
    ok = ok & np.all(np.isfinite(np.asarray(pts)), axis=(-2, -1)) & (std <= MAX_TRACK_STD_M)
    return np.swapaxes(np.asarray(pts), 0, 1), ok, np.asarray(rms), std

"""Pipeline step ``calibrate``: intrinsics (and hand-eye) from the calibration images.

The images in ``calibration/`` show the target described by ``calibration_target`` in
``recording.json``; OpenCV finds it and calibrates K and (k1, k2, p1, p2, k3)
(:func:`jaxtraj.vision.calibrate_camera`). When ``calibration/robot.csv`` gives the
flange pose at every calibration image, the hand-eye transform ``T_f_c`` follows from the
target poses (:func:`jaxtraj.vision.calibrate_hand_eye`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..io.recording import Recording
from ..io.records import CameraCalibration

__all__ = ["CalibrationReport", "calibrate_recording"]


@dataclass(frozen=True)
class CalibrationReport:
    """Outcome of :func:`calibrate_recording`.

    Attributes:
        camera: the calibration to write as ``camera.json``.
        views_used, views_skipped: image names used / (name, reason) left out.
        rms_px: reprojection RMS of the intrinsic calibration [px].
        hand_eye: None, or a dict with the hand-eye residuals and its ``ok`` flag.
    """

    camera: CameraCalibration
    views_used: list
    views_skipped: list
    rms_px: float
    hand_eye: dict | None


def _read_image(path):
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise ValueError(f"{path}: cannot read the image (not an image file, or damaged)")
    return image


def calibrate_recording(rec: Recording) -> CalibrationReport:
    """Calibrate the camera of a recording from its ``calibration/`` images.

    Raises:
        ValueError: no calibration images or target description, too few usable views,
            or a calibration robot file whose length does not match the images.
    """
    from ..vision.calibration import CalibrationTarget, calibrate_camera

    if not rec.calibration_images:
        raise ValueError(f"{rec.root / 'calibration'}: no calibration images (*.png, *.jpg)")
    if rec.meta.calibration_target is None:
        raise ValueError(
            f'{rec.root / "recording.json"}: no "calibration_target" describing the target '
            'in the calibration images (e.g. {"kind": "chessboard", "cols": 9, "rows": 6, '
            '"square": 0.03})'
        )
    target = CalibrationTarget.from_dict(rec.meta.calibration_target)
    images = [_read_image(p) for p in rec.calibration_images]
    names = [p.name for p in rec.calibration_images]
    result = calibrate_camera(images, target, image_names=names)
    T_i_c = rec.camera.T_i_c if rec.camera is not None else None
    camera = replace(result.calibration, T_i_c=T_i_c)
    hand_eye = None
    if rec.calibration_robot is not None:
        from ..vision.handeye import calibrate_hand_eye

        flange = rec.calibration_robot
        if len(flange.times) != len(images):
            raise ValueError(
                f"{rec.root / 'calibration' / 'robot.csv'}: {len(flange.times)} flange poses "
                f"for {len(images)} calibration images (need one per image, same order)"
            )
        used = np.asarray(result.used)
        he = calibrate_hand_eye(flange.q[used], flange.p[used], result.R_c_t, result.t_c_t)
        T_f_c = np.eye(4)
        T_f_c[:3, :3], T_f_c[:3, 3] = he.R_f_c, he.t_f_c
        camera = replace(camera, T_f_c=T_f_c)
        hand_eye = {
            "rotation_residual_deg": float(np.degrees(he.rotation_residual)),
            "translation_residual_mm": float(he.translation_residual * 1e3),
            "target_spread_position_mm": float(he.target_spread_position * 1e3),
            "target_spread_rotation_deg": float(np.degrees(he.target_spread_rotation)),
            "ok": bool(he.ok),
        }
    return CalibrationReport(
        camera=camera,
        views_used=[names[k] for k in result.used],
        views_skipped=[(str(n), why) for n, why in result.skipped],
        rms_px=float(result.calibration.rms_px),
        hand_eye=hand_eye,
    )

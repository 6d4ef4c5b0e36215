"""Pipeline step ``calibrate``: intrinsics and hand-eye from a calibration folder.

One code path serves a calibration folder on its own (:func:`calibrate_folder`) and the
``calibration/`` folder of a recording (:func:`calibrate_recording`):

1. the target's points in every view: found in the images (:func:`~jaxtraj.vision.
   calibration.detect_target`) or read from a corners CSV ``view,id,u,v``;
2. ``cv2.calibrateCamera`` (views with too few points are listed and skipped);
3. with robot poses (paired by a ``file`` column or natural sort): the motions are
   checked (rotations about two axes at least), every OpenCV hand-eye method is run and
   scored by the consistency it achieves on the data (the spread of the implied target
   pose against limits derived from the per-view pose uncertainty and the robot's noise);
   the best one (or ``method``) starts
4. the JAX bundle adjustment (:func:`jaxtraj.calibration.refine_hand_eye`) of
   intrinsics, distortion, hand-eye and target pose over all corners of all views;
5. acceptance: the final result's target spread under its limits (or the user's), with
   the reasons when it is rejected.

A calibration folder holds ``target.json`` (the :class:`~jaxtraj.vision.calibration.
CalibrationTarget`; with a corners CSV also ``"image_size": [width, height]``), the images
(``*.png``, ``*.jpg``, ...) or ``corners.csv``, and optionally ``robot.csv`` (any form of
:mod:`jaxtraj.io.robot_poses`). Results: ``camera.json`` and ``calibration.json``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..io.recording import Recording
from ..io.records import CameraCalibration, quat_to_matrix
from ..io.robot_poses import RobotPoses, natural_key, pair_views, read_robot_poses
from ..io.tables import RecordingError

__all__ = [
    "DEFAULT_ROBOT_SIGMA",
    "CalibrationOptions",
    "CalibrationReport",
    "calibrate_folder",
    "calibrate_recording",
    "calibrate_views",
]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
#: Robot pose noise assumed when none is given: 0.1 mm, 0.02 deg (an assumption, about a
#: good industrial arm's repeatability; pass the controller's own figures when known).
DEFAULT_ROBOT_SIGMA = (1e-4, float(np.radians(0.02)))


@dataclass(frozen=True)
class CalibrationOptions:
    """Options of the calibration (the ``jaxtraj calibrate`` flags).

    Attributes:
        robot_format, length_unit, angle_unit: how to read the robot poses
            (:func:`jaxtraj.io.robot_poses.read_robot_poses`).
        method: an OpenCV hand-eye method (:data:`jaxtraj.vision.handeye.METHODS`) or
            ``"auto"``: the one with the most consistent result on the data.
        refine: run the JAX bundle adjustment after the closed form.
        eye_to_hand: the camera stands still and the target is on the flange.
        robot_sigma: (position [m], rotation [rad]) noise of the robot's reported poses;
            None: a recording's ``robot_noise``, else :data:`DEFAULT_ROBOT_SIGMA`.
        max_position_spread, max_rotation_spread: acceptance limits [m], [rad] on the
            spread of the implied target pose; None: derived from the data.
        min_corners: fewest target points a view needs.
        solver: the bundle adjustment's optimiser (``"lm"``, ``"gauss-newton"``,
            ``"dogleg"``; :func:`jaxtraj.calibration.refine_hand_eye`).
    """

    robot_format: str = "auto"
    length_unit: str = "m"
    angle_unit: str = "rad"
    method: str = "auto"
    refine: bool = True
    eye_to_hand: bool = False
    robot_sigma: tuple[float, float] | None = None
    max_position_spread: float | None = None
    max_rotation_spread: float | None = None
    min_corners: int = 6
    solver: str = "lm"

    def __post_init__(self):
        from ..io.robot_poses import FORMS
        from ..vision.handeye import METHODS

        choices = {
            "robot_format": ("auto", *FORMS),
            "length_unit": ("m", "mm"),
            "angle_unit": ("rad", "deg"),
            "method": ("auto", *METHODS),
            "solver": ("lm", "gauss-newton", "dogleg"),
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name}: expected one of {allowed}, got {getattr(self, name)!r}")
        if self.robot_sigma is not None and not (
            len(self.robot_sigma) == 2 and all(np.isfinite(v) and v > 0 for v in self.robot_sigma)
        ):
            raise ValueError(
                f"robot_sigma: expected (position [m], rotation [rad]) > 0, got {self.robot_sigma}"
            )
        for name in ("max_position_spread", "max_rotation_spread"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive limit or None, got {v!r}")
        if not isinstance(self.min_corners, int) or self.min_corners < 4:
            raise ValueError(f"min_corners: expected an integer >= 4, got {self.min_corners!r}")


@dataclass(frozen=True)
class CalibrationReport:
    """Outcome of a calibration.

    Attributes:
        camera: the calibration to write as ``camera.json`` (``T_f_c`` eye-in-hand).
        views_used, views_skipped: view names used / (name, reason) left out.
        rms_px: reprojection RMS of the final intrinsics [px] (``calibrateCamera``'s, or
            the bundle adjustment's over all corners).
        hand_eye: None without robot poses; else a dict: the chosen result's residuals
            (``rotation_residual_deg``, ``translation_residual_mm``), target spread
            (``target_spread_position_mm``, ``target_spread_rotation_deg``), limits,
            ``ok``, ``reasons`` (why not ok), ``method``, ``methods`` (every OpenCV method's
            consistency), ``refined`` (the bundle adjustment's, with standard deviations),
            ``T_x`` and ``T_b`` (4x4 lists; eye-in-hand ``T_f_c``, ``T_b_t``; eye-to-hand
            ``T_b_c``, ``T_f_t``).
    """

    camera: CameraCalibration
    views_used: list
    views_skipped: list
    rms_px: float
    hand_eye: dict | None
    intrinsics: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        """A JSON-ready dict of the report (``calibration.json``)."""
        return {
            "K": self.camera.K.tolist(),
            "dist": self.camera.dist.tolist(),
            "image_size": list(self.camera.image_size),
            "rms_px": self.rms_px,
            "views_used": list(self.views_used),
            "views_skipped": [list(v) for v in self.views_skipped],
            "intrinsics": self.intrinsics,
            "hand_eye": self.hand_eye,
        }


def _read_image(path):
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise ValueError(f"{path}: cannot read the image (not an image file, or damaged)")
    return image


def calibrate_views(
    corners: dict,
    target,
    image_size,
    *,
    robot: RobotPoses | None = None,
    options: CalibrationOptions | None = None,
    skipped=(),
    T_i_c=None,
) -> CalibrationReport:
    """Calibrate from the target points of named views (steps 2-5 of the module doc).

    Args:
        corners: ``{view name: (ids, uv)}``.
        target: the :class:`~jaxtraj.vision.calibration.CalibrationTarget`.
        image_size: (width, height) [px].
        robot: the robot poses, paired with the views by :func:`pair_views`; None: only
            the intrinsics.
        options: :class:`CalibrationOptions`.
        skipped: (name, reason) of views left out before (no target found).
        T_i_c: camera-in-IMU transform to keep in the camera calibration.
    """
    from ..vision.calibration import calibrate_from_corners
    from ._handeye import hand_eye_step

    options = CalibrationOptions() if options is None else options
    names = list(corners) + [n for n, _ in skipped]
    if robot is not None:
        names, T_b_f = pair_views(names, robot)
    else:
        names, T_b_f = sorted(names, key=natural_key), None
    empty = (np.zeros(0, np.int64), np.zeros((0, 2)))
    views = [corners.get(n, empty) for n in names]
    result = calibrate_from_corners(
        views,
        target,
        image_size,
        names=names,
        skipped=list(skipped),
        min_corners=options.min_corners,
    )
    used = [names[k] for k in result.used]
    cal = result.calibration
    K, dist, rms, hand_eye = cal.K, cal.dist, float(cal.rms_px), None
    T_f_c = None
    intrinsics = {"opencv": {"K": cal.K.tolist(), "dist": cal.dist.tolist(), "rms_px": rms}}
    if T_b_f is not None:
        source = str(robot.path)
        K, dist, rms, X, hand_eye = hand_eye_step(
            result, target, T_b_f[result.used], options, source
        )
        if not options.eye_to_hand:
            T_f_c = X
    camera = CameraCalibration(K=K, dist=dist, image_size=cal.image_size, rms_px=rms)
    camera = replace(camera, T_f_c=T_f_c, T_i_c=T_i_c)
    return CalibrationReport(
        camera=camera,
        views_used=used,
        views_skipped=[(str(n), why) for n, why in result.skipped],
        rms_px=rms,
        hand_eye=hand_eye,
        intrinsics=intrinsics,
    )


def _detect_images(paths, target):
    from ..vision.calibration import detect_target
    from ..vision.markers import as_grey

    corners, skipped, size = {}, [], None
    for p in paths:
        grey = as_grey(_read_image(p), name=str(p))
        if size is None:
            size, first = grey.shape[::-1], p
        elif grey.shape[::-1] != size:
            raise ValueError(
                f"{p}: image size (width, height) {grey.shape[::-1]} differs from {first.name}'s "
                f"{size}"
            )
        ids, uv, why = detect_target(grey, target)
        if why:
            skipped.append((p.name, why))
        else:
            corners[p.name] = (ids, uv)
    return corners, skipped, size


def _read_target(path: Path):
    from ..vision.calibration import CalibrationTarget

    if not path.is_file():
        raise RecordingError(
            path,
            None,
            'no target description: write e.g. {"kind": "chessboard", "cols": 9, "rows": 6, '
            '"square": 0.03} (kinds: chessboard, charuco, asymmetric_circles)',
        )
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise RecordingError(path, err.lineno, f"not valid JSON ({err.msg})") from None
    if not isinstance(data, dict):
        raise RecordingError(path, None, "expected a JSON object")
    size = data.pop("image_size", None)
    try:
        target = CalibrationTarget.from_dict(data)
    except (ValueError, TypeError) as err:
        raise RecordingError(path, None, str(err)) from None
    return target, size


def calibrate_folder(
    folder: str | Path,
    *,
    options: CalibrationOptions | None = None,
    target_file: str | Path | None = None,
    robot_file: str | Path | None = None,
    corners_file: str | Path | None = None,
) -> CalibrationReport:
    """Calibrate from a calibration folder on its own (module doc for its files).

    Raises:
        ValueError / RecordingError: a missing or bad file (naming it and the line), too
            few usable views (listing the skipped ones), a robot pose file that does not
            pair with the views, degenerate robot motions (naming the axis).
    """
    from ..io.corners import read_corners

    folder = Path(folder)
    if not folder.is_dir():
        raise NotADirectoryError(f"{folder}: not a folder")
    options = CalibrationOptions() if options is None else options
    target_path = Path(target_file) if target_file else folder / "target.json"
    target, size = _read_target(target_path)
    corners_path = Path(corners_file) if corners_file else folder / "corners.csv"
    if corners_file or corners_path.is_file():
        corners = read_corners(corners_path)
        skipped = []
        if size is None:
            raise RecordingError(
                target_path, None, 'a corners CSV needs "image_size": [width, height] here'
            )
        try:
            size = tuple(int(v) for v in size)
            assert len(size) == 2 and min(size) > 0
        except (TypeError, ValueError, AssertionError):
            raise RecordingError(
                target_path, None, f'"image_size": expected [width, height], got {size!r}'
            ) from None
    else:
        paths = sorted(
            (p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES),
            key=lambda p: natural_key(p.name),
        )
        if not paths:
            raise ValueError(
                f"{folder}: no calibration images ({', '.join(IMAGE_SUFFIXES)}) and no corners.csv"
            )
        corners, skipped, size = _detect_images(paths, target)
    robot_path = Path(robot_file) if robot_file else folder / "robot.csv"
    robot = None
    if robot_file or robot_path.is_file():
        robot = read_robot_poses(
            robot_path,
            options.robot_format,
            length_unit=options.length_unit,
            angle_unit=options.angle_unit,
        )
    try:
        return calibrate_views(corners, target, size, robot=robot, options=options, skipped=skipped)
    except ValueError as err:
        if isinstance(err, RecordingError) or not str(err).startswith("images:"):
            raise
        source = corners_path if corners_file or corners_path.is_file() else folder
        raise ValueError(f"{source}: {err}") from None


def calibrate_recording(
    rec: Recording, options: CalibrationOptions | None = None
) -> CalibrationReport:
    """Calibrate the camera of a recording from its ``calibration/`` images.

    The same code as :func:`calibrate_folder`: the target comes from ``recording.json``'s
    ``calibration_target``, the robot poses from ``calibration/robot.csv`` (one row per
    image, in the images' natural order), the robot noise from ``recording.json``.

    Raises:
        ValueError: no calibration images or target description, too few usable views,
            or a calibration robot file whose length does not match the images.
    """
    from ..vision.calibration import CalibrationTarget

    if not rec.calibration_images:
        raise ValueError(f"{rec.root / 'calibration'}: no calibration images (*.png, *.jpg)")
    if rec.meta.calibration_target is None:
        raise ValueError(
            f'{rec.root / "recording.json"}: no "calibration_target" describing the target '
            'in the calibration images (e.g. {"kind": "chessboard", "cols": 9, "rows": 6, '
            '"square": 0.03})'
        )
    target = CalibrationTarget.from_dict(rec.meta.calibration_target)
    options = CalibrationOptions() if options is None else options
    noise = rec.meta.robot_noise
    if noise is not None and options.robot_sigma is None:
        options = replace(options, robot_sigma=(float(noise.position), float(noise.orientation)))
    paths = sorted(rec.calibration_images, key=lambda p: natural_key(p.name))
    corners, skipped, size = _detect_images(paths, target)
    robot = None
    if rec.calibration_robot is not None:
        flange = rec.calibration_robot
        source = rec.root / "calibration" / "robot.csv"
        if len(flange.times) != len(paths):
            raise ValueError(
                f"{source}: {len(flange.times)} flange poses for {len(paths)} calibration "
                "images (need one per image, same order)"
            )
        T = np.tile(np.eye(4), (len(paths), 1, 1))
        T[:, :3, :3], T[:, :3, 3] = quat_to_matrix(flange.q), flange.p
        robot = RobotPoses(T_b_f=T, files=None, lines=np.arange(len(paths)) + 2, path=source)
    T_i_c = rec.camera.T_i_c if rec.camera is not None else None
    return calibrate_views(
        corners, target, size, robot=robot, options=options, skipped=skipped, T_i_c=T_i_c
    )

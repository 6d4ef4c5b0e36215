"""The recording folder: everything one run of the robot cell produced.

Layout::

    recording/
      recording.json          sensor metadata: IMU and robot noise, robot latency, gravity,
                              calibration target (optional: documented defaults otherwise)
      camera.json             intrinsics (+ hand-eye T_f_c, T_i_c); or OpenCV's camera.yaml;
                              may be absent before `jaxtraj calibrate` has run
      calibration/            images of the calibration target (*.png), optional
      calibration/robot.csv   flange poses at each calibration image (one row per image, in
                              the images' natural order: 4.png before 12.png), optional:
                              enables hand-eye calibration
      images.csv + images/    the workpiece images and their times     } at least one
      detections.csv          detected reference points                } of the two
      imu.csv                 IMU samples
      robot.csv               robot controller flange poses T_w_f
      object.json             the workpiece's reference points
      truth/                  ground truth (simulated recordings only): object_pose.csv,
                              camera_pose.csv (T_w_c at image times), camera.json (true
                              intrinsics)

Required: ``object.json``, ``imu.csv``, ``robot.csv`` and ``images.csv`` or
``detections.csv``. All times are seconds on one clock. ``imu.csv`` may also be in
EuRoC's nanosecond form; its stamps then become seconds since the first IMU sample, and
the other files must use that clock. The file formats are described in
:mod:`jaxtraj.io.csv_formats` and :mod:`jaxtraj.io.json_formats`.

Writing: :func:`write_recording` builds the whole folder under a temporary name and
renames it into place at the end (:func:`~jaxtraj.io.tables.atomic_folder`), so a
half-written recording never looks complete. A simulator that renders images can instead
open ``atomic_folder(folder)`` itself, render into ``tmp / "images"``, and call
:func:`write_recording_files` on the temporary folder with a :class:`Recording` whose
image paths point there.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .csv_formats import (
    ImuSamples,
    read_detections,
    read_image_index,
    read_imu,
    read_poses,
    read_robot,
    write_detections,
    write_image_index,
    write_imu,
    write_poses,
    write_robot,
)
from .json_formats import (
    RecordingMeta,
    read_camera,
    read_meta,
    read_object,
    write_camera,
    write_meta,
    write_object,
)
from .records import CameraCalibration, Detections, ObjectModel, PoseStream
from .tables import RecordingError, atomic_folder

__all__ = [
    "Recording",
    "Truth",
    "read_recording",
    "read_truth",
    "write_recording",
    "write_recording_files",
]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


@dataclass(frozen=True)
class Recording:
    """The contents of a recording folder.

    Attributes:
        root: the folder.
        meta: sensor metadata (``recording.json``, defaults if absent).
        camera: intrinsics and hand-eye (``camera.json``/``camera.yaml``), or None.
        object: the workpiece model (``object.json``).
        imu: IMU samples (``imu.csv``).
        robot: flange poses ``T_w_f`` (``robot.csv``).
        image_index: ``(frames (F,), times (F,), files)`` from ``images.csv``, or None.
        detections: from ``detections.csv`` (frames of ``images.csv`` where present), or None.
        calibration_images: the calibration target images, sorted by name (maybe empty).
        calibration_robot: flange poses at the calibration images, or None.
    """

    root: Path
    meta: RecordingMeta
    camera: CameraCalibration | None
    object: ObjectModel
    imu: ImuSamples
    robot: PoseStream
    image_index: tuple[np.ndarray, np.ndarray, list[Path]] | None = None
    detections: Detections | None = None
    calibration_images: list[Path] = field(default_factory=list)
    calibration_robot: PoseStream | None = None


@dataclass(frozen=True)
class Truth:
    """Ground truth of a simulated recording (``truth/``).

    Attributes:
        object_pose: ``T_w_o`` (``truth/object_pose.csv``).
        camera_pose: ``T_w_c`` at the image times (``truth/camera_pose.csv``), or None.
        camera: the true intrinsics (``truth/camera.json``), or None.
    """

    object_pose: PoseStream
    camera_pose: PoseStream | None = None
    camera: CameraCalibration | None = None


REQUIRED = ("object.json", "imu.csv", "robot.csv")


def _camera_file(folder: Path) -> Path | None:
    found = [folder / n for n in ("camera.json", "camera.yaml", "camera.yml")]
    found = [f for f in found if f.exists()]
    if len(found) > 1:
        raise RecordingError(
            found[1],
            None,
            f"two camera files in the recording ({found[0].name} and {found[1].name}); keep one",
        )
    return found[0] if found else None


def read_recording(folder: str | Path, *, require_camera: bool = False) -> Recording:
    """Read a recording folder (layout in the module docstring).

    Args:
        folder: the recording folder.
        require_camera: raise if there is no ``camera.json``/``camera.yaml``.

    Raises:
        RecordingError: a missing required file, or the first problem in any file.
    """
    root = Path(folder)
    if not root.is_dir():
        raise RecordingError(root, None, "no such recording folder")
    for name in REQUIRED:
        if not (root / name).is_file():
            raise RecordingError(
                root / name,
                None,
                f"no such file (a recording needs {', '.join(REQUIRED)} and images.csv or "
                "detections.csv)",
            )
    has_images = (root / "images.csv").is_file()
    has_det = (root / "detections.csv").is_file()
    if not (has_images or has_det):
        raise RecordingError(
            root,
            None,
            "neither images.csv (with images/) nor detections.csv: a recording "
            "needs the workpiece images or their detected reference points",
        )
    cam_file = _camera_file(root)
    if cam_file is None and require_camera:
        raise RecordingError(
            root / "camera.json",
            None,
            "no such file: the camera intrinsics are needed; "
            "`jaxtraj calibrate` writes camera.json from the images in calibration/ "
            "(or put OpenCV's calibration as camera.yaml)",
        )
    meta = (
        read_meta(root / "recording.json")
        if (root / "recording.json").exists()
        else RecordingMeta()
    )
    obj = read_object(root / "object.json")
    index = read_image_index(root / "images.csv") if has_images else None
    det = None
    if has_det:
        frame_times = None if index is None else (index[0], index[1])
        det = read_detections(root / "detections.csv", obj.ids, frame_times=frame_times)
    calib = root / "calibration"
    images = (
        sorted(p for p in calib.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if calib.is_dir()
        else []
    )
    calib_robot = None
    if (calib / "robot.csv").is_file():
        calib_robot = read_robot(calib / "robot.csv")
        if len(calib_robot.times) != len(images):
            raise RecordingError(
                calib / "robot.csv",
                None,
                f"{len(calib_robot.times)} flange poses for "
                f"{len(images)} calibration images: expected one pose per image (same order)",
            )
    return Recording(
        root=root,
        meta=meta,
        camera=None if cam_file is None else read_camera(cam_file),
        object=obj,
        imu=read_imu(root / "imu.csv"),
        robot=read_robot(root / "robot.csv"),
        image_index=index,
        detections=det,
        calibration_images=images,
        calibration_robot=calib_robot,
    )


def _place(files: list[Path], folder: Path, sub: str) -> list[Path]:
    """Copy files into ``folder / sub`` unless they are already inside ``folder``."""
    out, target = [], folder / sub
    for f in map(Path, files):
        try:
            f.resolve().relative_to(folder.resolve())
            out.append(f)
            continue
        except ValueError:
            pass
        target.mkdir(exist_ok=True)
        dst = target / f.name
        if dst.exists():
            raise ValueError(f"files: two images named {f.name} would go to {target}")
        shutil.copy2(f, dst)
        out.append(dst)
    return out


def write_recording_files(
    folder: str | Path, rec: Recording, *, truth: Truth | None = None, kuka: bool = False
) -> None:
    """Write the files of ``rec`` into an existing folder (not atomic; see
    :func:`write_recording`). Images listed in ``rec`` that lie outside ``folder`` are
    copied into ``images/`` and ``calibration/``.

    Args:
        folder: the (temporary) recording folder.
        rec: what to write (``root`` is ignored).
        truth: ground truth to write into ``truth/``, or None.
        kuka: write ``robot.csv`` files in KUKA form.
    """
    folder = Path(folder)
    write_meta(folder / "recording.json", rec.meta)
    if rec.camera is not None:
        write_camera(folder / "camera.json", rec.camera)
    write_object(folder / "object.json", rec.object)
    write_imu(folder / "imu.csv", rec.imu)
    write_robot(folder / "robot.csv", rec.robot, kuka=kuka)
    if rec.image_index is not None:
        frames, times, files = rec.image_index
        files = _place(list(files), folder, "images")
        write_image_index(folder / "images.csv", frames, times, files)
    if rec.detections is not None:
        write_detections(folder / "detections.csv", rec.detections)
    if rec.calibration_images or rec.calibration_robot is not None:
        (folder / "calibration").mkdir(exist_ok=True)
        _place(list(rec.calibration_images), folder, "calibration")
        if rec.calibration_robot is not None:
            write_robot(folder / "calibration" / "robot.csv", rec.calibration_robot, kuka=kuka)
    if truth is not None:
        (folder / "truth").mkdir(exist_ok=True)
        write_poses(folder / "truth" / "object_pose.csv", truth.object_pose)
        if truth.camera_pose is not None:
            write_poses(folder / "truth" / "camera_pose.csv", truth.camera_pose)
        if truth.camera is not None:
            write_camera(folder / "truth" / "camera.json", truth.camera)


def write_recording(
    folder: str | Path, rec: Recording, *, truth: Truth | None = None, kuka: bool = False
) -> Path:
    """Write ``rec`` (and ``truth``) as the recording folder ``folder``, atomically.

    The folder is built under a temporary name beside ``folder`` and renamed into place at
    the end; an existing ``folder`` is replaced only then, and left as it was on error.

    Returns:
        ``folder`` as a Path.
    """
    folder = Path(folder)
    with atomic_folder(folder) as tmp:
        write_recording_files(tmp, rec, truth=truth, kuka=kuka)
    return folder


def read_truth(folder: str | Path) -> Truth | None:
    """Read ``truth/`` of a (simulated) recording, or None if the folder has none."""
    truth = Path(folder) / "truth"
    if not truth.is_dir():
        return None
    cam = truth / "camera_pose.csv"
    intr = truth / "camera.json"
    return Truth(
        object_pose=read_poses(truth / "object_pose.csv"),
        camera_pose=read_poses(cam) if cam.exists() else None,
        camera=read_camera(intr) if intr.exists() else None,
    )

"""Pipeline step ``detect``: the workpiece's reference points in every image.

Each image is read, checked against the calibrated image size, and searched for the
object model's ArUco markers (:func:`jaxtraj.vision.detect_markers`); a marker's
reference point is its centre (the intersection of its refined diagonals). Images
without any detection are kept as frames with all points missing and reported.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from ..io.records import CameraCalibration, Detections, ObjectModel

__all__ = ["detect_images"]


def detect_images(
    frames: np.ndarray,
    times: np.ndarray,
    files: list[Path],
    model: ObjectModel,
    camera: CameraCalibration | None = None,
    *,
    progress: Callable[[Iterable, str, int], Iterable] | None = None,
) -> tuple[Detections, list[tuple[int, str]]]:
    """Detect the model's markers in the images.

    Args:
        frames, times, files: the image index (F,) of the recording.
        model: the object model (marker ids and dictionary).
        camera: if given, every image must have its ``image_size``.
        progress: ``progress(iterable, description, total)`` (e.g. a tqdm bar) or None.

    Returns:
        ``(detections, notes)``: (F, M) detections in the model's id order, and
        (frame, note) for images without detections or with unknown/duplicate markers.

    Raises:
        ValueError: an unreadable image or one whose size does not match ``camera``.
    """
    import cv2

    from ..vision.markers import detect_markers

    F, M = len(times), len(model.ids)
    uv = np.zeros((F, M, 2))
    found = np.zeros((F, M), bool)
    column = {int(i): m for m, i in enumerate(model.ids)}
    notes = []
    steps = range(F) if progress is None else progress(range(F), "detect markers", F)
    for f in steps:
        image = cv2.imread(str(files[f]), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise ValueError(f"{files[f]}: cannot read the image (not an image file, or damaged)")
        if camera is not None and image.shape[::-1] != tuple(camera.image_size):
            raise ValueError(
                f"{files[f]}: image size {image.shape[1]}x{image.shape[0]} does not match the "
                f"camera calibration's {camera.image_size[0]}x{camera.image_size[1]}"
            )
        det = detect_markers(image, model.marker_dictionary)
        for marker_id, centre in zip(det.ids, det.centres, strict=False):
            m = column.get(int(marker_id))
            if m is not None:
                uv[f, m], found[f, m] = centre, True
        if len(det.duplicates):
            notes.append(
                (int(frames[f]), f"markers seen twice and ignored: {list(det.duplicates)}")
            )
        if not found[f].any():
            notes.append((int(frames[f]), "no reference point detected"))
    return Detections(times=times, ids=model.ids, uv=uv, detected=found, frames=frames), notes

"""Fiducial detection at sub-pixel accuracy: ArUco marker corners and centres.

Host-side (NumPy + OpenCV 4.x ``cv2.aruco.ArucoDetector``; OpenCV is imported lazily).
The marker centre is the intersection of the two diagonals of the refined corners, which
is the exact image of the square's centre under any perspective (the corner mean is not).
Pixel coordinates follow OpenCV: (0, 0) is the centre of the top-left pixel.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

__all__ = ["REFINE_METHODS", "MarkerDetections", "detect_markers", "diagonal_centres"]

#: Corner refinement methods of :func:`detect_markers` (OpenCV's CORNER_REFINE_*).
REFINE_METHODS = ("none", "subpix", "contour", "apriltag")


@dataclass(frozen=True, eq=False)
class MarkerDetections:
    """ArUco markers found in one image.

    Attributes:
        ids: (n,) int64 marker ids, sorted ascending, each once.
        corners: (n, 4, 2) float64 corners [px] in OpenCV's order (top-left, top-right,
            bottom-right, bottom-left of the marker as printed).
        centres: (n, 2) float64 marker centres [px] (intersection of the diagonals).
        duplicates: (k,) int64 ids found more than once in the image; they are left out of
            ``ids`` (a mis-detection or a repeated marker cannot be told apart).
    """

    ids: np.ndarray
    corners: np.ndarray
    centres: np.ndarray
    duplicates: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def __len__(self) -> int:
        return len(self.ids)


def diagonal_centres(corners) -> np.ndarray:
    """Intersection of the diagonals (corner 0-2 and corner 1-3) of quadrilaterals.

    Args:
        corners: (n, 4, 2) corners [px].

    Returns:
        (n, 2) intersections [px]; the corner mean where the diagonals are parallel.
    """
    c = np.asarray(corners, np.float64).reshape(-1, 4, 2)
    h = np.concatenate([c, np.ones((*c.shape[:2], 1))], -1)
    lines = np.cross(np.cross(h[:, 0], h[:, 2]), np.cross(h[:, 1], h[:, 3]))
    ok = np.abs(lines[:, 2]) > 1e-12 * np.maximum(1.0, np.abs(lines[:, :2]).max(axis=1))
    mean = c.mean(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        centre = lines[:, :2] / lines[:, 2:3]
    return np.where(ok[:, None], centre, mean)


def _dictionary_id(name):
    import cv2

    if not isinstance(name, str) or not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
        raise ValueError(
            f"dictionary: unknown ArUco dictionary {name!r}; expected e.g. 'DICT_4X4_50', "
            "'DICT_5X5_100', 'DICT_6X6_250', 'DICT_ARUCO_ORIGINAL', 'DICT_APRILTAG_36h11'"
        )
    return getattr(cv2.aruco, name)


@functools.lru_cache(maxsize=16)
def _detector(dictionary: str, refine: str):
    import cv2

    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = {
        "none": cv2.aruco.CORNER_REFINE_NONE,
        "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
        "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
        "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
    }[refine]
    # Window: half of a marker cell, at most 6 px (measured best on rendered boards).
    params.cornerRefinementWinSize = 6
    params.cornerRefinementMaxIterations = 100
    params.cornerRefinementMinAccuracy = 1e-3
    if hasattr(params, "relativeCornerRefinmentWinSize"):  # OpenCV >= 4.9
        params.relativeCornerRefinmentWinSize = 0.5
    dic = cv2.aruco.getPredefinedDictionary(_dictionary_id(dictionary))
    return cv2.aruco.ArucoDetector(dic, params)


def as_grey(image, name: str = "image") -> np.ndarray:
    """A (H, W) uint8 grey view of a grey (H, W), (H, W, 1) or BGR (H, W, 3) uint8 image."""
    import cv2

    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f"{name}: expected a uint8 image, got dtype {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    elif img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.ndim != 2 or min(img.shape) < 1:
        raise ValueError(f"{name}: expected a (H, W) grey or (H, W, 3) BGR image, got {img.shape}")
    return np.ascontiguousarray(img)


def detect_markers(
    image, dictionary: str = "DICT_4X4_50", *, refine: str = "subpix"
) -> MarkerDetections:
    """Detect ArUco markers and locate their corners and centres to sub-pixel accuracy.

    ``cv2.aruco.ArucoDetector`` with corner refinement ``refine``: ``"subpix"`` (default,
    ``CORNER_REFINE_SUBPIX``) measured best on rendered 640x480 images of 6 cm markers at
    0.5-1 m with k1 = -0.1 (centre RMS 0.05 px, max 0.10 px; corners RMS 0.19 px, biased
    inwards by the rounded blurred corner, which the diagonal centre cancels);
    ``"contour"`` (centre RMS 0.11 px), ``"apriltag"`` (0.65 px, 25x slower) and
    ``"none"`` (0.38 px) are there to compare. Centres are the intersection of the refined
    corners' diagonals.

    Args:
        image: (H, W) grey or (H, W, 3) BGR uint8 image.
        dictionary: OpenCV ArUco dictionary name, e.g. ``"DICT_4X4_50"``.
        refine: one of :data:`REFINE_METHODS`.

    Returns:
        :class:`MarkerDetections` (empty when no marker is seen; ids found twice are left
        out and listed in ``duplicates``).
    """
    if refine not in REFINE_METHODS:
        raise ValueError(f"refine: expected one of {REFINE_METHODS}, got {refine!r}")
    _dictionary_id(dictionary)
    grey = as_grey(image)
    corners, ids, _ = _detector(dictionary, refine).detectMarkers(grey)
    if ids is None or len(ids) == 0:
        empty = np.zeros(0, np.int64)
        return MarkerDetections(empty, np.zeros((0, 4, 2)), np.zeros((0, 2)), empty)
    ids = np.asarray(ids, np.int64).ravel()
    corners = np.asarray(corners, np.float64).reshape(-1, 4, 2)
    uniq, counts = np.unique(ids, return_counts=True)
    duplicates = uniq[counts > 1]
    keep = ~np.isin(ids, duplicates)
    ids, corners = ids[keep], corners[keep]
    order = np.argsort(ids, kind="stable")
    ids, corners = ids[order], corners[order]
    return MarkerDetections(ids, corners, diagonal_centres(corners), duplicates)

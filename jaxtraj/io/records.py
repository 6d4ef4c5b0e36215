"""Plain host-side records that travel between the files of a recording and the library.

They are NumPy dataclasses (not JAX pytrees): the edge of the library reads files into
them, checks them, and hands their arrays to the JAX core. Times are float seconds,
lengths metres, quaternions (w, x, y, z), poses ``T_a_b`` as in DESIGN section 4.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "CameraCalibration",
    "Detections",
    "ObjectModel",
    "PoseStream",
    "matrix_to_quat",
    "quat_to_matrix",
]


def quat_to_matrix(q) -> np.ndarray:
    """(..., 3, 3) rotation matrices of (..., 4) quaternions (w, x, y, z), normalised first."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quat(R) -> np.ndarray:
    """(N, 4) quaternions (w, x, y, z) of (N, 3, 3) rotation matrices (jaxlie's conversion)."""
    import jax
    import jax.numpy as jnp
    import jaxlie

    return np.asarray(jax.vmap(lambda r: jaxlie.SO3.from_matrix(r).wxyz)(jnp.asarray(R)))


def _array(name: str, value, shape: tuple, dtype=np.float64) -> np.ndarray:
    arr = np.asarray(value, dtype)
    wrong = any(s is not None and s != a for s, a in zip(shape, arr.shape, strict=False))
    if arr.ndim != len(shape) or wrong:
        want = "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name}: expected shape {want}, got {arr.shape}")
    return arr


@dataclass(frozen=True)
class CameraCalibration:
    """Intrinsics of one camera (OpenCV model) and, optionally, its hand-eye transform.

    Attributes:
        K: (3, 3) camera matrix [px].
        dist: (5,) distortion (k1, k2, p1, p2, k3), OpenCV's model.
        image_size: (width, height) [px] of the images the calibration belongs to.
        rms_px: reprojection RMS of the calibration [px], or None if unknown.
        T_f_c: (4, 4) hand-eye transform (camera in the flange frame), or None.
        T_i_c: (4, 4) camera in the IMU frame, or None (identity).
    """

    K: np.ndarray
    dist: np.ndarray
    image_size: tuple[int, int]
    rms_px: float | None = None
    T_f_c: np.ndarray | None = None
    T_i_c: np.ndarray | None = None

    def __post_init__(self):
        object.__setattr__(self, "K", _array("K", self.K, (3, 3)))
        dist = np.zeros(5) if self.dist is None else np.ravel(np.asarray(self.dist, np.float64))
        if dist.shape[0] not in (4, 5):
            raise ValueError(f"dist: expected 4 or 5 coefficients, got {dist.shape[0]}")
        object.__setattr__(self, "dist", np.pad(dist, (0, 5 - dist.shape[0])))
        w, h = (int(v) for v in self.image_size)
        if w <= 0 or h <= 0:
            raise ValueError(f"image_size: expected positive (width, height), got {(w, h)}")
        object.__setattr__(self, "image_size", (w, h))
        for name in ("T_f_c", "T_i_c"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, _array(name, value, (4, 4)))


@dataclass(frozen=True)
class ObjectModel:
    """The workpiece: reference points (marker centres) in the object frame.

    Attributes:
        ids: (M,) marker ids, unique.
        points: (M, 3) reference points in the object frame [m].
        assembly_point: (3,) the point whose trajectory the robot needs, object frame [m].
        marker_dictionary: OpenCV ArUco dictionary name, e.g. ``"DICT_4X4_50"``.
        marker_size: side length of the square markers [m] (None for other targets).
    """

    ids: np.ndarray
    points: np.ndarray
    assembly_point: np.ndarray = field(default_factory=lambda: np.zeros(3))
    marker_dictionary: str = "DICT_4X4_50"
    marker_size: float | None = None

    def __post_init__(self):
        ids = np.asarray(self.ids)
        if ids.ndim != 1 or not np.issubdtype(ids.dtype, np.integer):
            raise ValueError(f"ids: expected a 1-D integer array, got {ids.dtype} {ids.shape}")
        if len(np.unique(ids)) != len(ids):
            raise ValueError(f"ids: marker ids must be unique, got {ids.tolist()}")
        object.__setattr__(self, "ids", ids.astype(np.int64))
        object.__setattr__(self, "points", _array("points", self.points, (len(ids), 3)))
        object.__setattr__(
            self, "assembly_point", _array("assembly_point", self.assembly_point, (3,))
        )
        if len(ids) < 3:
            raise ValueError(f"an object model needs >= 3 reference points, got {len(ids)}")


@dataclass(frozen=True)
class Detections:
    """Reference-point detections, one row per image and one column per model point.

    Attributes:
        times: (F,) image times [s], strictly increasing.
        ids: (M,) marker ids of the columns (the object model's order).
        uv: (F, M, 2) pixel positions (OpenCV convention); arbitrary where not detected.
        detected: (F, M) bool, whether the point was found in the image.
        frames: (F,) frame numbers (e.g. the image index in the recording).
    """

    times: np.ndarray
    ids: np.ndarray
    uv: np.ndarray
    detected: np.ndarray
    frames: np.ndarray | None = None

    def __post_init__(self):
        t = _array("times", self.times, (None,))
        ids = np.asarray(self.ids, np.int64)
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "uv", _array("uv", self.uv, (len(t), len(ids), 2)))
        object.__setattr__(
            self, "detected", _array("detected", self.detected, (len(t), len(ids)), bool)
        )
        frames = np.arange(len(t)) if self.frames is None else self.frames
        object.__setattr__(self, "frames", _array("frames", frames, (len(t),), np.int64))

    @property
    def weights(self) -> np.ndarray:
        """(F, M) 1.0 where detected, 0.0 where missing (the solver's weights)."""
        return self.detected.astype(np.float64)


@dataclass(frozen=True)
class PoseStream:
    """A stream of poses ``T_w_x`` (e.g. the workpiece ``T_w_o`` or the camera ``T_w_c``).

    Attributes:
        times: (N,) [s]; p: (N, 3) positions [m]; q: (N, 4) orientations (w, x, y, z).
    """

    times: np.ndarray
    p: np.ndarray
    q: np.ndarray

    def __post_init__(self):
        t = _array("times", self.times, (None,))
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "p", _array("p", self.p, (len(t), 3)))
        q = _array("q", self.q, (len(t), 4))
        norm = np.linalg.norm(q, axis=1, keepdims=True)
        if np.any(~np.isfinite(norm)) or np.any(norm < 1e-9):
            raise ValueError("q: quaternions must be finite and non-zero")
        object.__setattr__(self, "q", q / norm)

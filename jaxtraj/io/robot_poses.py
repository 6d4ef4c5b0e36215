"""Robot poses of calibration views in the forms controllers report, and image pairing.

A calibration pose file is a CSV with a header; one row per view; the columns of one
form (order free, extra columns ignored), an optional ``file`` column naming the image (or
the ``view`` of a detections CSV) and an optional time column that is not used (static
poses need no time). Every form gives the flange pose in the robot base, ``T_b_f``:

===========  ==============================  =============================================
form         columns                         meaning
===========  ==============================  =============================================
``pq``       x y z qw qx qy qz               position, unit quaternion (w first)
``kuka``     X Y Z A B C                     KUKA: mm and deg always; R = Rz(A) Ry(B) Rx(C)
                                             (intrinsic Z-Y'-X'')
``rpy``      x y z roll pitch yaw            R = Rz(yaw) Ry(pitch) Rx(roll): rotations
                                             about the FIXED base axes x, then y, then z
                                             (= intrinsic Z-Y'-X''; ROS/URDF convention)
``rotvec``   x y z rx ry rz                  rotation vector (axis * angle; UR controllers)
``matrix``   m00 m01 m02 m03 ... m23         the top 3 rows of the 4x4 matrix, row-major
             (m30..m33 optional)             (translation in m03, m13, m23)
===========  ==============================  =============================================

Lengths are metres and angles radians unless ``length_unit="mm"`` / ``angle_unit="deg"``
(not for ``kuka``, which is mm and degrees by definition). ``form="auto"`` picks the form
from the header.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .records import quat_to_matrix
from .tables import RecordingError, read_header, read_table

__all__ = [
    "FORMS",
    "RobotPoses",
    "from_matrices",
    "natural_key",
    "pair_views",
    "read_robot_poses",
    "to_matrices",
]

_COLUMNS = {
    "pq": ("x", "y", "z", "qw", "qx", "qy", "qz"),
    "kuka": ("X", "Y", "Z", "A", "B", "C"),
    "rpy": ("x", "y", "z", "roll", "pitch", "yaw"),
    "rotvec": ("x", "y", "z", "rx", "ry", "rz"),
    "matrix": tuple(f"m{r}{c}" for r in range(3) for c in range(4)),
}
#: The robot pose forms of :func:`read_robot_poses`.
FORMS = tuple(_COLUMNS)
_UNITS = {"m": 1.0, "mm": 1e-3}
_ANGLES = {"rad": 1.0, "deg": np.pi / 180}


@dataclass(frozen=True, eq=False)
class RobotPoses:
    """Flange poses of calibration views.

    Attributes:
        T_b_f: (V, 4, 4) flange poses in the robot base [m].
        files: (V,) the ``file`` column, or None when the file has none.
        lines: (V,) 1-based line of each row in ``path``.
        path: the file read (for messages).
    """

    T_b_f: np.ndarray
    files: list[str] | None
    lines: np.ndarray
    path: Path


def _axis(angle, axis):
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros((len(angle), 3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[:, axis, axis] = 1
    R[:, i, i], R[:, j, j] = c, c
    R[:, i, j], R[:, j, i] = -s, s
    return R


def _rotvec_to_matrix(w):
    th = np.linalg.norm(w, axis=1)
    small = th < 1e-12
    k = w / np.where(small, 1.0, th)[:, None]
    S = np.zeros((len(w), 3, 3))
    S[:, 0, 1], S[:, 0, 2], S[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    S = S - np.swapaxes(S, 1, 2)
    s, c = np.sin(th)[:, None, None], (1 - np.cos(th))[:, None, None]
    return np.eye(3) + s * S + c * S @ S


def _zyx(R):
    """(a, b, c) with R = Rz(a) Ry(b) Rx(c); b in [-pi/2, pi/2], c = 0 at gimbal lock."""
    cb = np.hypot(R[:, 0, 0], R[:, 1, 0])
    b = np.arctan2(-R[:, 2, 0], cb)
    lock = cb < 1e-10
    a = np.where(lock, np.arctan2(-R[:, 0, 1], R[:, 1, 1]), np.arctan2(R[:, 1, 0], R[:, 0, 0]))
    c = np.where(lock, 0.0, np.arctan2(R[:, 2, 1], R[:, 2, 2]))
    return a, b, c


def _log(R):
    """Rotation vectors of (n, 3, 3) rotations (accurate near 0 and pi)."""
    import cv2

    return np.stack([cv2.Rodrigues(np.ascontiguousarray(r))[0].ravel() for r in R])


def to_matrices(values, form: str, *, length_unit: str = "m", angle_unit: str = "rad"):
    """(V, 4, 4) poses from (V, k) values in the column order of ``form`` (module doc)."""
    _check_form(form, length_unit, angle_unit)
    v = np.asarray(values, np.float64)
    n = len(_COLUMNS[form])
    if v.ndim != 2 or v.shape[1] != n:
        raise ValueError(f"values: expected shape (V, {n}) for form {form!r}, got {v.shape}")
    L, A = _UNITS[length_unit], _ANGLES[angle_unit]
    T = np.tile(np.eye(4), (len(v), 1, 1))
    if form == "matrix":
        T[:, :3, :] = v.reshape(-1, 3, 4)
        T[:, :3, 3] *= L
        return T
    if form == "kuka":
        L, A = 1e-3, np.pi / 180
    T[:, :3, 3] = v[:, :3] * L
    if form == "pq":
        T[:, :3, :3] = quat_to_matrix(v[:, 3:])
    elif form == "rotvec":
        T[:, :3, :3] = _rotvec_to_matrix(v[:, 3:] * A)
    elif form == "kuka":  # A, B, C: about z, y', x''
        a, b, c = (v[:, k] * A for k in (3, 4, 5))
        T[:, :3, :3] = _axis(a, 2) @ _axis(b, 1) @ _axis(c, 0)
    else:  # rpy: roll x, pitch y, yaw z (fixed axes)
        r, p, y = (v[:, k] * A for k in (3, 4, 5))
        T[:, :3, :3] = _axis(y, 2) @ _axis(p, 1) @ _axis(r, 0)
    return T


def from_matrices(T, form: str, *, length_unit: str = "m", angle_unit: str = "rad"):
    """(V, k) values of ``form`` for (V, 4, 4) poses (inverse of :func:`to_matrices`).

    Quaternions come out with w >= 0; Euler angles with the middle one in [-90, 90] deg.
    """
    _check_form(form, length_unit, angle_unit)
    T = np.asarray(T, np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"T: expected shape (V, 4, 4), got {T.shape}")
    L, A = _UNITS[length_unit], _ANGLES[angle_unit]
    if form == "kuka":
        L, A = 1e-3, np.pi / 180
    if form == "matrix":
        M = T[:, :3, :].copy()
        M[:, :, 3] /= L
        return M.reshape(-1, 12)
    R, p = T[:, :3, :3], T[:, :3, 3] / L
    if form == "pq":
        from .records import matrix_to_quat

        q = matrix_to_quat(R)
        return np.concatenate([p, np.where(q[:, :1] < 0, -q, q)], 1)
    if form == "rotvec":
        return np.concatenate([p, _log(R) / A], 1)
    a, b, c = _zyx(R)
    if form == "kuka":
        return np.concatenate([p, np.stack([a, b, c], 1) / A], 1)
    return np.concatenate([p, np.stack([c, b, a], 1) / A], 1)  # roll, pitch, yaw


def _check_form(form, length_unit, angle_unit):
    if form not in _COLUMNS:
        raise ValueError(f"form: expected one of {FORMS}, got {form!r}")
    if length_unit not in _UNITS:
        raise ValueError(f"length_unit: expected 'm' or 'mm', got {length_unit!r}")
    if angle_unit not in _ANGLES:
        raise ValueError(f"angle_unit: expected 'rad' or 'deg', got {angle_unit!r}")


def _detect(path, line, cells):
    have = set(cells)
    found = [f for f, cols in _COLUMNS.items() if set(cols) <= have]
    if len(found) == 1:
        return found[0]
    forms = "; ".join(f"{f}: {','.join(c)}" for f, c in _COLUMNS.items())
    what = "no form's columns" if not found else f"the columns of several forms {found}"
    raise RecordingError(
        path,
        line,
        f"robot pose header {','.join(cells)} has {what}; expected one of {forms} "
        "(or choose the form with --robot-format)",
    )


def read_robot_poses(
    path: str | Path, form: str = "auto", *, length_unit: str = "m", angle_unit: str = "rad"
) -> RobotPoses:
    """Read a calibration pose file (module doc); errors name the file and line.

    Args:
        path: the CSV file.
        form: one of :data:`FORMS`, or ``"auto"`` (from the header).
        length_unit: ``"m"`` or ``"mm"``; angle_unit: ``"rad"`` or ``"deg"`` (not for kuka).

    Returns:
        :class:`RobotPoses`.
    """
    path = Path(path)
    names = {c for cols in _COLUMNS.values() for c in cols} | {"file"}
    line, cells = read_header(path, names)
    if form == "auto":
        form = _detect(path, line, cells)
    _check_form(form, length_unit, angle_unit)
    cols = dict.fromkeys(_COLUMNS[form], "float")
    if "file" in cells:
        cols["file"] = "str"
    tab = read_table(path, cols)
    v = np.stack([tab[c] for c in _COLUMNS[form]], 1)
    if form == "pq":
        norm = np.linalg.norm(v[:, 3:], axis=1)
        bad = np.flatnonzero(np.abs(norm - 1.0) > 1e-3)
        if bad.size:
            r = int(bad[0])
            raise tab.error(r, f"quaternion norm {norm[r]:.6g}: expected a unit quaternion")
    if form == "matrix":
        R = v.reshape(-1, 3, 4)[:, :, :3]
        err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
        det = np.linalg.det(R)
        bad = np.flatnonzero((err > 1e-6) | (det < 0))
        if bad.size:
            r = int(bad[0])
            raise tab.error(
                r, f"not a rotation (|R^T R - I| = {err[r]:.2g}, det {det[r]:.6g}): expected "
                "the top 3 rows of a rigid 4x4 matrix, row-major",
            )  # fmt: skip
    T = to_matrices(v, form, length_unit=length_unit, angle_unit=angle_unit)
    files = [str(f) for f in tab["file"]] if "file" in tab else None
    if files is not None:
        seen: dict[str, int] = {}
        for r, f in enumerate(files):
            if f in seen:
                raise tab.error(r, f"file {f!r} listed twice (first on line {seen[f]})")
            seen[f] = int(tab.lines[r])
    return RobotPoses(T_b_f=T, files=files, lines=np.asarray(tab.lines), path=path)


def natural_key(name: str) -> tuple:
    """Sort key that orders the digit runs of a name by value (``4.png`` before ``12.png``)."""
    parts = re.split(r"(\d+)", name)
    return tuple((0, int(p), p) if p.isdigit() else (1, 0, p.lower()) for p in parts)


def pair_views(names, poses: RobotPoses) -> tuple[list[str], np.ndarray]:
    """Pair views (image file names or detection view names) with robot pose rows.

    With a ``file`` column each view is looked up by name (by its stem when the column
    gives stems); without one, views in natural order (:func:`natural_key`) take the rows
    in file order, which needs as many rows as views and no two names that sort alike
    (``view1.png`` and ``view01.png``).

    Returns:
        (names in pairing order, (V, 4, 4) their flange poses).

    Raises:
        RecordingError: a view without a pose row (naming it), a count mismatch, or an
            ambiguous natural order.
    """
    names = [str(n) for n in names]
    if poses.files is not None:
        index = {f: k for k, f in enumerate(poses.files)}
        stems = {Path(f).stem: k for k, f in enumerate(poses.files)}
        order = []
        for n in sorted(names, key=natural_key):
            k = index.get(n, index.get(Path(n).name, stems.get(Path(n).stem)))
            if k is None:
                raise RecordingError(
                    poses.path, None, f"no row with file {n!r}: every view needs its robot pose"
                )
            order.append(k)
        return sorted(names, key=natural_key), poses.T_b_f[order]
    ordered = sorted(names, key=natural_key)
    keys = [tuple(p[:2] for p in natural_key(n)) for n in ordered]
    for a, b, ka, kb in zip(ordered, ordered[1:], keys, keys[1:], strict=False):
        if ka == kb:
            raise RecordingError(
                poses.path,
                None,
                f"views {a!r} and {b!r} have the same natural order; add a file column to "
                "say which pose row belongs to which view",
            )
    if len(ordered) != len(poses.T_b_f):
        raise RecordingError(
            poses.path,
            None,
            f"{len(poses.T_b_f)} robot pose rows for {len(ordered)} views: expected one row "
            "per view in the views' natural order (or a file column naming each view)",
        )
    return ordered, poses.T_b_f

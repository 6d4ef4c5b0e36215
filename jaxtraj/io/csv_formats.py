"""Readers and writers of a recording's CSV (and TUM text) files (exact round trips).

Every ``read_X`` stops bad input with one :class:`~jaxtraj.io.tables.RecordingError`
naming the file, the line and the problem. Every ``write_X`` writes atomically and with
enough digits that ``read_X(write_X(x)) == x`` exactly (floats use Python's shortest
round-trip repr).

Files (see :mod:`jaxtraj.io.recording` for the folder; the JSON and YAML files are in
:mod:`jaxtraj.io.json_formats`):

* ``imu.csv``: ``t,wx,wy,wz,ax,ay,az`` (s, rad/s, m/s^2, IMU frame) or EuRoC's
  ``#timestamp [ns],w_RS_S_x [rad s^-1],...,a_RS_S_z [m s^-2]``
  (:class:`ImuSamples`, :func:`read_imu`, :func:`write_imu`).
* ``robot.csv``: flange poses ``T_w_f``, ``t,x,y,z,qw,qx,qy,qz`` (m, unit quaternion w
  first) or KUKA ``t,X,Y,Z,A,B,C`` (mm, degrees, R = Rz(A) Ry(B) Rx(C))
  (:func:`read_robot`, :func:`write_robot`; :func:`kuka_to_pose`, :func:`pose_to_kuka`).
* poses CSV ``t,x,y,z,qw,qx,qy,qz`` (:func:`read_poses`, :func:`write_poses`) and TUM
  ``timestamp tx ty tz qx qy qz qw`` (:func:`read_tum`, :func:`write_tum`).
* ``detections.csv`` ``frame,t,id,u,v`` (:func:`read_detections`,
  :func:`write_detections`); ``images.csv`` ``frame,t,file`` (:func:`read_image_index`,
  :func:`write_image_index`); ``points.csv`` ``frame,t,id,x,y,z,ok``
  (:class:`ReconstructedPoints`, :func:`read_points`, :func:`write_points`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .records import Detections, ObjectModel, PoseStream, quat_to_matrix
from .tables import (
    RecordingError,
    Table,
    _check_file,
    _show,
    atomic_write_text,
    read_header,
    read_table,
    write_table,
)

__all__ = [
    "ImuSamples",
    "ReconstructedPoints",
    "kuka_to_pose",
    "pose_to_kuka",
    "read_detections",
    "read_image_index",
    "read_imu",
    "read_joint_path",
    "read_points",
    "read_poses",
    "read_robot",
    "read_tum",
    "write_detections",
    "write_image_index",
    "write_imu",
    "write_points",
    "write_poses",
    "write_robot",
    "write_tum",
]

# --------------------------------------------------------------------------- IMU

IMU_COLUMNS = ("t", "wx", "wy", "wz", "ax", "ay", "az")
EUROC_IMU_COLUMNS = (
    "timestamp [ns]",
    "w_RS_S_x [rad s^-1]",
    "w_RS_S_y [rad s^-1]",
    "w_RS_S_z [rad s^-1]",
    "a_RS_S_x [m s^-2]",
    "a_RS_S_y [m s^-2]",
    "a_RS_S_z [m s^-2]",
)


@dataclass(frozen=True)
class ImuSamples:
    """IMU samples in the IMU frame.

    Attributes:
        t: (N,) times [s], strictly increasing.
        gyro: (N, 3) angular rate [rad/s].
        accel: (N, 3) specific force [m/s^2].
        t0_ns: for files with nanosecond stamps (EuRoC), the stamp [ns] of ``t = 0``.
    """

    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    t0_ns: int | None = None

    def __post_init__(self):
        t = np.asarray(self.t, np.float64)
        if t.ndim != 1:
            raise ValueError(f"t: expected shape (n,), got {t.shape}")
        for name in ("gyro", "accel"):
            arr = np.asarray(getattr(self, name), np.float64)
            if arr.shape != (t.shape[0], 3):
                raise ValueError(f"{name}: expected shape ({t.shape[0]}, 3), got {arr.shape}")
            object.__setattr__(self, name, arr)
        if np.any(np.diff(t) <= 0):
            raise ValueError("t: expected strictly increasing times")
        object.__setattr__(self, "t", t)


def read_imu(path: str | Path, t0_ns: int | None = None) -> ImuSamples:
    """Read ``imu.csv`` (``t,wx,wy,wz,ax,ay,az`` in s, or EuRoC's ns form).

    Args:
        path: the file.
        t0_ns: for EuRoC files, the stamp [ns] that becomes ``t = 0`` (default: the first
            sample); ignored for files in seconds.
    """
    _, cells = read_header(path, IMU_COLUMNS + EUROC_IMU_COLUMNS)
    if EUROC_IMU_COLUMNS[0] in cells:
        aliases = dict(zip(IMU_COLUMNS, ([c] for c in EUROC_IMU_COLUMNS), strict=True))
        kinds = {c: "float" for c in IMU_COLUMNS} | {"t": "int64ns"}
        tab = read_table(path, kinds, aliases=aliases, strictly_increasing="t")
        t_ns = tab["t"]
        t0 = int(t_ns[0]) if t0_ns is None else int(t0_ns)
        t = (t_ns - np.int64(t0)) / 1e9  # integer difference first: keeps ns precision
    else:
        tab = read_table(path, dict.fromkeys(IMU_COLUMNS, "float"), strictly_increasing="t")
        t, t0 = tab["t"], None
    gyro = np.stack([tab["wx"], tab["wy"], tab["wz"]], 1)
    accel = np.stack([tab["ax"], tab["ay"], tab["az"]], 1)
    return ImuSamples(t=t, gyro=gyro, accel=accel, t0_ns=t0)


def write_imu(path: str | Path, imu: ImuSamples) -> None:
    """Write ``imu.csv`` in the ``t,wx,wy,wz,ax,ay,az`` form (seconds)."""
    write_table(path, list(IMU_COLUMNS), [imu.t, *imu.gyro.T, *imu.accel.T])


# --------------------------------------------------------------------- rotations


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, v1, w2, v2 = a[:, :1], a[:, 1:], b[:, :1], b[:, 1:]
    return np.concatenate(
        [w1 * w2 - np.sum(v1 * v2, 1, keepdims=True), w1 * v2 + w2 * v1 + np.cross(v1, v2)], 1
    )


def _axis_quat(angle: np.ndarray, axis: int) -> np.ndarray:
    q = np.zeros((angle.shape[0], 4))
    q[:, 0] = np.cos(angle / 2)
    q[:, 1 + axis] = np.sin(angle / 2)
    return q


def kuka_to_pose(xyzabc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """KUKA ``X, Y, Z, A, B, C`` to position and quaternion.

    ``R = Rz(A) @ Ry(B) @ Rx(C)`` (intrinsic Z-Y'-X'' Euler angles).

    Args:
        xyzabc: (N, 6) X, Y, Z [mm] and A, B, C [deg].

    Returns:
        ``(p, q)``: (N, 3) positions [m] and (N, 4) unit quaternions (w, x, y, z), w >= 0.
    """
    v = np.asarray(xyzabc, np.float64)
    if v.ndim != 2 or v.shape[1] != 6:
        raise ValueError(f"xyzabc: expected shape (n, 6), got {v.shape}")
    a, b, c = np.deg2rad(v[:, 3]), np.deg2rad(v[:, 4]), np.deg2rad(v[:, 5])
    q = _quat_mul(_quat_mul(_axis_quat(a, 2), _axis_quat(b, 1)), _axis_quat(c, 0))
    q = np.where(q[:, :1] < 0, -q, q)
    return v[:, :3] / 1000.0, q


def pose_to_kuka(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Position and quaternion to KUKA ``X, Y, Z, A, B, C`` (inverse of :func:`kuka_to_pose`).

    A and C lie in (-180, 180], B in [-90, 90]. At gimbal lock (B = +-90 deg, where only
    A - C or A + C is defined) C is set to 0 and the whole turn about z goes into A.

    Args:
        p: (N, 3) positions [m]; q: (N, 4) quaternions (w, x, y, z) (normalised here).

    Returns:
        (N, 6): X, Y, Z [mm], A, B, C [deg].
    """
    p = np.asarray(p, np.float64)
    q = np.asarray(q, np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"p: expected shape (n, 3), got {p.shape}")
    if q.shape != (p.shape[0], 4):
        raise ValueError(f"q: expected shape ({p.shape[0]}, 4), got {q.shape}")
    R = quat_to_matrix(q)
    cos_b = np.hypot(R[:, 0, 0], R[:, 1, 0])
    b = np.arctan2(-R[:, 2, 0], cos_b)
    lock = cos_b < 1e-10
    a = np.where(lock, np.arctan2(-R[:, 0, 1], R[:, 1, 1]), np.arctan2(R[:, 1, 0], R[:, 0, 0]))
    # C from what is left after removing Rz(A) Ry(B): errors in A are absorbed by C.
    Ra = quat_to_matrix(_quat_mul(_axis_quat(a, 2), _axis_quat(b, 1)))
    M = np.einsum("nji,njk->nik", Ra, R)
    c = np.arctan2(M[:, 2, 1], M[:, 1, 1])
    angles = np.rad2deg(np.stack([a, b, c], 1))
    angles = np.where(angles <= -180.0, angles + 360.0, angles)
    return np.concatenate([p * 1000.0, angles], 1)


# ------------------------------------------------------------------------- poses

POSE_COLUMNS = ("t", "x", "y", "z", "qw", "qx", "qy", "qz")
KUKA_COLUMNS = ("t", "X", "Y", "Z", "A", "B", "C")


def _unit_quaternions(tab: Table, q: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > 1e-3)
    if bad.size:
        r = int(bad[0])
        raise tab.error(
            r, f"quaternion norm {norm[r]:.6g}: expected a unit quaternion (norm within 1e-3 of 1)"
        )
    return q / norm[:, None]


def _read_pose_table(path: str | Path, *, sep: str | None = ",", header: bool = True):
    tab = read_table(
        path, dict.fromkeys(POSE_COLUMNS, "float"), strictly_increasing="t", sep=sep, header=header
    )
    p = np.stack([tab["x"], tab["y"], tab["z"]], 1)
    q = _unit_quaternions(tab, np.stack([tab["qw"], tab["qx"], tab["qy"], tab["qz"]], 1))
    return PoseStream(times=tab["t"], p=p, q=q)


def read_poses(path: str | Path) -> PoseStream:
    """Read a pose CSV ``t,x,y,z,qw,qx,qy,qz`` (s, m, unit quaternion w first)."""
    return _read_pose_table(path)


def write_poses(path: str | Path, poses: PoseStream) -> None:
    """Write a pose CSV ``t,x,y,z,qw,qx,qy,qz``."""
    write_table(path, list(POSE_COLUMNS), [poses.times, *poses.p.T, *poses.q.T])


def read_robot(path: str | Path) -> PoseStream:
    """Read ``robot.csv``: flange poses ``T_w_f``; the header picks the form.

    ``t,x,y,z,qw,qx,qy,qz`` (m, unit quaternion w first) or KUKA ``t,X,Y,Z,A,B,C`` (mm,
    degrees, R = Rz(A) Ry(B) Rx(C)).
    """
    line, cells = read_header(path, POSE_COLUMNS + KUKA_COLUMNS)
    if "A" in cells and "qw" not in cells:
        tab = read_table(path, dict.fromkeys(KUKA_COLUMNS, "float"), strictly_increasing="t")
        p, q = kuka_to_pose(np.stack([tab[c] for c in KUKA_COLUMNS[1:]], 1))
        return PoseStream(times=tab["t"], p=p, q=q)
    if "qw" not in cells:
        raise RecordingError(
            path,
            line,
            f"unknown robot pose header {','.join(cells)}: expected "
            f"{','.join(POSE_COLUMNS)} or KUKA {','.join(KUKA_COLUMNS)}",
        )
    return _read_pose_table(path)


def write_robot(path: str | Path, poses: PoseStream, *, kuka: bool = False) -> None:
    """Write ``robot.csv`` as ``t,x,y,z,qw,qx,qy,qz`` or, with ``kuka=True``, ``t,X,Y,Z,A,B,C``."""
    if not kuka:
        write_poses(path, poses)
        return
    v = pose_to_kuka(poses.p, poses.q)
    write_table(path, list(KUKA_COLUMNS), [poses.times, *v.T])


def read_tum(path: str | Path) -> PoseStream:
    """Read a TUM trajectory: ``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments."""
    path = _check_file(path)
    tum = ("t", "x", "y", "z", "qx", "qy", "qz", "qw")
    tab = read_table(
        path, dict.fromkeys(tum, "float"), strictly_increasing="t", sep=None, header=False
    )
    p = np.stack([tab["x"], tab["y"], tab["z"]], 1)
    q = _unit_quaternions(tab, np.stack([tab["qw"], tab["qx"], tab["qy"], tab["qz"]], 1))
    return PoseStream(times=tab["t"], p=p, q=q)


def write_tum(path: str | Path, poses: PoseStream) -> None:
    """Write a TUM trajectory (quaternion order x, y, z, w in the file)."""
    cols = [poses.times, *poses.p.T, poses.q[:, 1], poses.q[:, 2], poses.q[:, 3], poses.q[:, 0]]
    rows = zip(*([repr(v) for v in c.tolist()] for c in cols), strict=True)
    body = "".join(" ".join(r) + "\n" for r in rows)
    atomic_write_text(path, "# timestamp tx ty tz qx qy qz qw\n" + body)


# -------------------------------------------------------------------- detections

DETECTION_COLUMNS = {"frame": "int", "t": "float", "id": "int", "u": "float", "v": "float"}


def _frame_checks(tab: Table, frame: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Check that rows come grouped by increasing frame with one, increasing, t per frame."""
    back = np.flatnonzero(frame[1:] < frame[:-1])
    if back.size:
        r = int(back[0]) + 1
        raise tab.error(
            r, f"column frame: frames must be increasing ({frame[r]} after {frame[r - 1]})"
        )
    same = frame[1:] == frame[:-1]
    diff_t = np.flatnonzero(same & (t[1:] != t[:-1]))
    if diff_t.size:
        r = int(diff_t[0]) + 1
        raise tab.error(
            r,
            f"column t: frame {frame[r]} has t = {_show(t[r])} here but {_show(t[r - 1])} on line "
            f"{tab.lines[r - 1]} (all rows of a frame need the same t)",
        )
    start = np.concatenate([[0], np.flatnonzero(~same) + 1])
    ft = t[start]
    bad = np.flatnonzero(ft[1:] <= ft[:-1])
    if bad.size:
        r = int(start[bad[0] + 1])
        word = "duplicate timestamp" if t[r] == t[r - 1] else "timestamp goes backwards"
        raise tab.error(
            r, f"column t: {word} ({_show(t[r])} after {_show(t[r - 1])} of frame {frame[r - 1]})"
        )
    return start, frame[start]


def _duplicate_pairs(tab: Table, frame: np.ndarray, ids: np.ndarray, what: str) -> None:
    order = np.lexsort((tab.lines, ids, frame))
    dup = np.flatnonzero(
        (frame[order][1:] == frame[order][:-1]) & (ids[order][1:] == ids[order][:-1])
    )
    if dup.size:
        a, b = order[dup[0]], order[dup[0] + 1]
        raise tab.error(
            b, f"duplicate {what} for frame {frame[b]}, id {ids[b]} (also on line {tab.lines[a]})"
        )


def read_detections(
    path: str | Path,
    model_ids: np.ndarray | ObjectModel,
    *,
    frame_times: tuple[np.ndarray, np.ndarray] | None = None,
    ignore_unknown: bool = False,
) -> Detections:
    """Read ``detections.csv`` (``frame,t,id,u,v``, one row per detected reference point).

    Args:
        path: the file.
        model_ids: (M,) the object model's ids (or the :class:`ObjectModel`); the columns of
            the result follow this order.
        frame_times: optional ``(frames (F,), times (F,))`` from ``images.csv``: every
            frame appears in the result (frames without rows: nothing detected), and each
            file row's t must match its frame's time (within 1 us).
        ignore_unknown: drop rows whose id is not in the model instead of raising.

    Returns:
        :class:`Detections` with uv (F, M, 2) [px] (0 where not detected).
    """
    ids_model = np.asarray(getattr(model_ids, "ids", model_ids), np.int64)
    tab = read_table(path, DETECTION_COLUMNS)
    frame, t, pid = tab["frame"], tab["t"], tab["id"]
    known = np.isin(pid, ids_model)
    if not np.all(known):
        if not ignore_unknown:
            r = int(np.flatnonzero(~known)[0])
            raise tab.error(
                r,
                f"column id: {pid[r]} is not a reference point of the object model "
                f"(ids {ids_model.tolist()})",
            )
        keep = np.flatnonzero(known)
        tab = Table(tab.path, tab.lines[keep], {k: v[keep] for k, v in tab.items()})
        frame, t, pid = tab["frame"], tab["t"], tab["id"]
    if frame.size:
        start, frames_seen = _frame_checks(tab, frame, t)
        _duplicate_pairs(tab, frame, pid, "detection")
    else:
        start, frames_seen = np.zeros(0, np.int64), np.zeros(0, np.int64)
    if frame_times is None:
        frames, times = frames_seen, t[start]
    else:
        frames = np.asarray(frame_times[0], np.int64)
        times = np.asarray(frame_times[1], np.float64)
        if frames.ndim != 1 or times.shape != frames.shape or np.any(np.diff(frames) <= 0):
            raise ValueError(
                "frame_times: expected (frames (F,) strictly increasing, times (F,)), got "
                f"shapes {frames.shape} and {times.shape}"
            )
        pos = np.searchsorted(frames, frame)
        missing = (pos >= frames.size) | (frames[np.minimum(pos, frames.size - 1)] != frame)
        if np.any(missing):
            r = int(np.flatnonzero(missing)[0])
            raise tab.error(r, f"column frame: frame {frame[r]} is not in the image index")
        off = np.abs(times[pos] - t) > 1e-6
        if np.any(off):
            r = int(np.flatnonzero(off)[0])
            raise tab.error(
                r,
                f"column t: {_show(t[r])} differs from the image index time {_show(times[pos[r]])} "
                f"of frame {frame[r]}",
            )
    row = np.searchsorted(frames, frame)
    col = np.searchsorted(ids_model, pid, sorter=np.argsort(ids_model))
    col = np.argsort(ids_model)[col]
    uv = np.zeros((frames.size, ids_model.size, 2))
    detected = np.zeros((frames.size, ids_model.size), bool)
    uv[row, col, 0], uv[row, col, 1] = tab["u"], tab["v"]
    detected[row, col] = True
    if frames.size == 0:
        raise RecordingError(tab.path, None, "no detections of the object model's reference points")
    return Detections(times=times, ids=ids_model, uv=uv, detected=detected, frames=frames)


def write_detections(path: str | Path, det: Detections) -> None:
    """Write ``detections.csv``: one row per detected point, frames in order (undetected
    points and frames without detections write no rows)."""
    f, m = np.nonzero(det.detected)
    uv = det.uv[f, m]
    if not np.all(np.isfinite(uv)):
        raise ValueError("det.uv: detected points must have finite pixel coordinates")
    write_table(
        path, list(DETECTION_COLUMNS), [det.frames[f], det.times[f], det.ids[m], uv[:, 0], uv[:, 1]]
    )


# ------------------------------------------------------------------ image index


def read_image_index(
    path: str | Path, *, check_files: bool = True
) -> tuple[np.ndarray, np.ndarray, list[Path]]:
    """Read ``images.csv`` (``frame,t,file``; files relative to the file's folder).

    Returns:
        ``(frames (F,) int64, times (F,) [s], files)``: ``files`` are paths joined with
        the folder of ``images.csv``. Frames and times strictly increase; with
        ``check_files`` every listed image must exist.
    """
    tab = read_table(path, {"frame": "int", "t": "float", "file": "str"}, strictly_increasing="t")
    frames = tab["frame"]
    bad = np.flatnonzero(frames[1:] <= frames[:-1])
    if bad.size:
        r = int(bad[0]) + 1
        raise tab.error(
            r, f"column frame: frames must increase strictly ({frames[r]} after {frames[r - 1]})"
        )
    folder = tab.path.parent
    files = [folder / f for f in tab["file"].tolist()]
    if check_files:
        for r, f in enumerate(files):
            if not f.is_file():
                raise tab.error(r, f"column file: image {f} does not exist")
    return frames, tab["t"], files


def write_image_index(
    path: str | Path, frames: np.ndarray, times: np.ndarray, files: Sequence[str | Path]
) -> None:
    """Write ``images.csv``; files inside the folder of ``path`` are written relative to it.

    Absolute paths and paths relative to the working directory that lie inside the folder
    become relative to the folder; other relative paths are taken as relative to the
    folder already and written as given.
    """
    folder = Path(path).parent.resolve()
    rel = []
    for f in files:
        f = Path(f)
        candidate = f if f.is_absolute() else Path.cwd() / f
        if f.is_absolute() or candidate.exists():
            try:
                f = candidate.resolve().relative_to(folder)
            except ValueError:
                pass
        rel.append(f.as_posix())
    write_table(
        path,
        ["frame", "t", "file"],
        [
            np.asarray(frames, np.int64),
            np.asarray(times, np.float64),
            np.asarray(rel, dtype=object),
        ],
    )


# ------------------------------------------------------------------------ points


@dataclass(frozen=True)
class ReconstructedPoints:
    """Reconstructed reference points per frame.

    Attributes:
        frames: (F,) frame numbers; times: (F,) [s]; ids: (M,) point ids.
        points: (F, M, 3) positions [m] (NaN where not available); ok: (F, M) bool.
    """

    frames: np.ndarray
    times: np.ndarray
    ids: np.ndarray
    points: np.ndarray
    ok: np.ndarray


def write_points(
    path: str | Path,
    times: np.ndarray,
    ids: np.ndarray,
    points: np.ndarray,
    ok: np.ndarray | None = None,
    frames: np.ndarray | None = None,
) -> None:
    """Write ``points.csv`` ``frame,t,id,x,y,z,ok`` (one row per frame and point).

    Args:
        times: (F,) [s]; ids: (M,); points: (F, M, 3) [m]; ok: (F, M) bool (default all
            True); frames: (F,) frame numbers (default 0..F-1).
    """
    times = np.asarray(times, np.float64)
    ids = np.asarray(ids, np.int64)
    F, M = times.shape[0], ids.shape[0]
    points = np.asarray(points, np.float64)
    if points.shape != (F, M, 3):
        raise ValueError(f"points: expected shape ({F}, {M}, 3), got {points.shape}")
    ok = np.ones((F, M), bool) if ok is None else np.asarray(ok, bool)
    if ok.shape != (F, M):
        raise ValueError(f"ok: expected shape ({F}, {M}), got {ok.shape}")
    frames = np.arange(F) if frames is None else np.asarray(frames, np.int64)
    if frames.shape != (F,):
        raise ValueError(f"frames: expected shape ({F},), got {frames.shape}")
    if np.any(ok & ~np.all(np.isfinite(points), -1)):
        raise ValueError("points: points marked ok must be finite")
    P = points.reshape(F * M, 3)
    write_table(
        path,
        ["frame", "t", "id", "x", "y", "z", "ok"],
        [
            np.repeat(frames, M),
            np.repeat(times, M),
            np.tile(ids, F),
            *P.T,
            ok.reshape(-1).astype(np.int64),
        ],
    )


def read_points(path: str | Path) -> ReconstructedPoints:
    """Read ``points.csv`` (inverse of :func:`write_points`); pairs missing from the file
    come back with ``ok = False`` and NaN points."""
    cols = {
        "frame": "int",
        "t": "float",
        "id": "int",
        "x": "float",
        "y": "float",
        "z": "float",
        "ok": "int",
    }
    tab = read_table(path, cols, allow_nonfinite=("x", "y", "z"))
    frame, t, pid, ok = tab["frame"], tab["t"], tab["id"], tab["ok"]
    bad = np.flatnonzero((ok != 0) & (ok != 1))
    if bad.size:
        raise tab.error(int(bad[0]), f"column ok: expected 0 or 1, got {ok[bad[0]]}")
    P = np.stack([tab["x"], tab["y"], tab["z"]], 1)
    bad = np.flatnonzero((ok == 1) & ~np.all(np.isfinite(P), 1))
    if bad.size:
        raise tab.error(int(bad[0]), "columns x, y, z: a point with ok = 1 must be finite")
    start, frames = _frame_checks(tab, frame, t)
    _duplicate_pairs(tab, frame, pid, "point")
    _, first = np.unique(pid, return_index=True)
    ids = pid[np.sort(first)]
    row = np.searchsorted(frames, frame)
    col = np.argsort(ids)[np.searchsorted(ids, pid, sorter=np.argsort(ids))]
    points = np.full((frames.size, ids.size, 3), np.nan)
    okm = np.zeros((frames.size, ids.size), bool)
    points[row, col] = P
    okm[row, col] = ok == 1
    return ReconstructedPoints(frames=frames, times=t[start], ids=ids, points=points, ok=okm)


def read_joint_path(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a joint path CSV ``t,A1,...,A6`` (s, deg; ``jaxtraj design``'s
    ``joint_path.csv``); returns times (N,) [s] and axis values (N, 6) [rad]."""
    axes = [f"A{i}" for i in range(1, 7)]
    tab = read_table(path, dict.fromkeys(["t", *axes], "float"), strictly_increasing="t")
    return tab["t"], np.radians(np.stack([tab[a] for a in axes], 1))

"""Reader for the EuRoC MAV dataset's CSV files (ASL format).

* ``imu0.csv``: timestamp [ns], gyro x, y, z [rad/s], accel x, y, z [m/s^2] in the body
  (IMU) frame S.
* ``groundtruth.csv``: timestamp [ns], position ``p_RS_R`` [m], quaternion ``q_RS``
  (w, x, y, z), velocity ``v_RS_R`` [m/s], gyro bias ``b_w_RS_S`` [rad/s], accel bias
  ``b_a_RS_S`` [m/s^2]. This is the IMU pose ``T_w_i`` in the Vicon world frame R
  (gravity along -z).

Timestamps stay integers (ns) while reading and become float seconds relative to a
reference ``t0_ns`` (by default the first IMU sample), which keeps microsecond
resolution even in float32.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["EurocRecording", "ground_truth_as_robot", "read_euroc", "read_euroc_csv"]


def read_euroc_csv(path: str | Path, columns: int) -> tuple[np.ndarray, np.ndarray]:
    """Read an EuRoC CSV: returns ``(t_ns (N,) int64, values (N, columns - 1) float64)``.

    Lines starting with ``#`` and blank lines are skipped. Raises ``ValueError`` naming
    the file and line for a wrong column count or an unparsable number, and
    ``FileNotFoundError`` for a missing file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    stamps, rows = [], []
    with path.open() as fh:
        for lineno, line in enumerate(fh, start=1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.split(",")
            if len(parts) != columns:
                raise ValueError(
                    f"{path}:{lineno}: expected {columns} comma-separated columns, got {len(parts)}"
                )
            try:
                stamps.append(int(parts[0]))
                rows.append([float(v) for v in parts[1:]])
            except ValueError as err:
                raise ValueError(f"{path}:{lineno}: cannot parse number ({err})") from None
    if not rows:
        raise ValueError(f"{path}: no data rows")
    return np.asarray(stamps, np.int64), np.asarray(rows, np.float64)


@dataclass(frozen=True)
class EurocRecording:
    """IMU samples and ground truth of one EuRoC sequence (NumPy, float64 seconds).

    Attributes:
        t0_ns: reference timestamp [ns]; all times are seconds since it.
        imu_t: (N,) IMU times [s]; gyro, accel: (N, 3).
        gt_t: (G,) ground-truth times [s]; gt_p: (G, 3) [m]; gt_q: (G, 4) (w, x, y, z);
        gt_v: (G, 3) [m/s]; gt_b_g: (G, 3) [rad/s]; gt_b_a: (G, 3) [m/s^2].
    """

    t0_ns: int
    imu_t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    gt_t: np.ndarray
    gt_p: np.ndarray
    gt_q: np.ndarray
    gt_v: np.ndarray
    gt_b_g: np.ndarray
    gt_b_a: np.ndarray

    def ground_truth_between(self, t_start: float, t_end: float) -> EurocRecording:
        """A copy with the ground truth restricted to ``t_start <= t <= t_end``."""
        keep = (self.gt_t >= t_start) & (self.gt_t <= t_end)
        return EurocRecording(
            t0_ns=self.t0_ns,
            imu_t=self.imu_t,
            gyro=self.gyro,
            accel=self.accel,
            gt_t=self.gt_t[keep],
            gt_p=self.gt_p[keep],
            gt_q=self.gt_q[keep],
            gt_v=self.gt_v[keep],
            gt_b_g=self.gt_b_g[keep],
            gt_b_a=self.gt_b_a[keep],
        )


def read_euroc(folder: str | Path, t0_ns: int | None = None) -> EurocRecording:
    """Read ``imu0.csv`` and ``groundtruth.csv`` from ``folder`` (either directly in it or
    in the ASL layout ``mav0/imu0/data.csv``, ``mav0/state_groundtruth_estimate0/data.csv``).

    Args:
        folder: the sequence folder.
        t0_ns: reference time [ns]; the first IMU timestamp if None.
    """
    folder = Path(folder)
    imu_path = folder / "imu0.csv"
    gt_path = folder / "groundtruth.csv"
    if not imu_path.is_file() and (folder / "mav0").is_dir():
        imu_path = folder / "mav0" / "imu0" / "data.csv"
        gt_path = folder / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    t_imu, imu = read_euroc_csv(imu_path, 7)
    t_gt, gt = read_euroc_csv(gt_path, 17)
    for path, t in ((imu_path, t_imu), (gt_path, t_gt)):
        bad = np.flatnonzero(np.diff(t) <= 0)
        if bad.size:
            raise ValueError(f"{path}: timestamps not increasing at data row {bad[0] + 2}")
    t0 = int(t_imu[0]) if t0_ns is None else int(t0_ns)
    q = gt[:, 3:7]
    return EurocRecording(
        t0_ns=t0,
        imu_t=(t_imu - t0) * 1e-9,
        gyro=imu[:, 0:3],
        accel=imu[:, 3:6],
        gt_t=(t_gt - t0) * 1e-9,
        gt_p=gt[:, 0:3],
        gt_q=q / np.linalg.norm(q, axis=1, keepdims=True),
        gt_v=gt[:, 7:10],
        gt_b_g=gt[:, 10:13],
        gt_b_a=gt[:, 13:16],
    )


def _quat_mul(a, b):
    w1, v1, w2, v2 = a[:, :1], a[:, 1:], b[:, :1], b[:, 1:]
    return np.concatenate(
        [w1 * w2 - np.sum(v1 * v2, 1, keepdims=True), w1 * v2 + w2 * v1 + np.cross(v1, v2)], 1
    )


def ground_truth_as_robot(
    rec: EurocRecording,
    every: int = 2,
    position_noise: float = 1e-3,
    orientation_noise: float = 2e-3,
    seed: int = 0,
):
    """Stand-in "robot controller" data from the ground truth, for fusion experiments.

    Keeps the ground-truth poses inside the IMU span; every ``every``-th one becomes a
    robot pose with isotropic position noise [m] and local orientation noise [rad]; the
    others, between the first and last robot pose, are held back for scoring.

    Returns:
        ``(robot, held)``: a :class:`~jaxtraj.fusion.RobotPoses` (stamped on the IMU
        clock, latency 0) and the indices of the held-back ground-truth rows.
    """
    import jax.numpy as jnp

    from ..fusion.events import RobotPoses

    if every < 2:
        raise ValueError(f"every: expected an integer >= 2, got {every}")
    inside = np.flatnonzero((rec.gt_t >= rec.imu_t[0]) & (rec.gt_t <= rec.imu_t[-1]))
    used = inside[::every]
    held = np.setdiff1d(inside, used)
    held = held[(held > used[0]) & (held < used[-1])]
    rng = np.random.default_rng(seed)
    p = rec.gt_p[used] + position_noise * rng.standard_normal((used.size, 3))
    phi = orientation_noise * rng.standard_normal((used.size, 3))
    angle = np.linalg.norm(phi, axis=1, keepdims=True)
    dq = np.concatenate([np.cos(angle / 2), np.sinc(angle / (2 * np.pi)) * phi / 2], 1)
    q = _quat_mul(rec.gt_q[used], dq)
    robot = RobotPoses(t=jnp.asarray(rec.gt_t[used]), p=jnp.asarray(p), q=jnp.asarray(q))
    return robot, held

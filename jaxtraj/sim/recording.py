"""Render a simulated cell into a recording folder, as a real cell would write it.

The workpiece is a plate with four ArUco markers plus two markers on posts of different
heights (so the reference points are not coplanar, which pins down the orientation).
Every image is rendered from the true camera and workpiece poses with lens distortion,
anti-aliasing, optical blur and sensor noise (:func:`jaxtraj.sim.render.render`); the
calibration images show a chessboard lying on the table. The folder follows
:mod:`jaxtraj.io.recording`; ``truth/`` holds the ground truth for ``jaxtraj evaluate``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from ..io.csv_formats import ImuSamples
from ..io.json_formats import ImuNoise, RecordingMeta, RobotNoise
from ..io.recording import Recording, Truth, write_recording_files
from ..io.records import CameraCalibration, ObjectModel, PoseStream, quat_to_matrix
from ..io.tables import atomic_folder
from .cell import SimulatedCell, _pose_stream, _rot, pose_matrix
from .render import PlanarTexture, chessboard_texture, marker_board, render

__all__ = ["CALIBRATION_TARGET", "workpiece", "write_simulated_recording"]

#: The chessboard of the simulated calibration images (inner corners, square [m]).
CALIBRATION_TARGET = {"kind": "chessboard", "cols": 9, "rows": 6, "square": 0.03}

Progress = Callable[[Iterable, str, int], Iterable]


def pose_matrices(poses: PoseStream) -> np.ndarray:
    """(N, 4, 4) transforms of a pose stream."""
    return pose_matrix(quat_to_matrix(poses.q), poses.p)


def workpiece(cell: SimulatedCell) -> tuple[list[PlanarTexture], ObjectModel]:
    """The workpiece's textures (object frame) and its model (marker centres, ids).

    The first ``n - 2`` markers lie on the base plate (z = 0); the last two sit on posts
    beside it, 6 cm and 10 cm high.
    """
    c = cell.config
    ids = list(c.marker_ids)
    base_ids, post_ids = ids[:-2], ids[-2:]
    cols = max(1, len(base_ids) // 2)
    base, centres, _ = marker_board(
        base_ids,
        dictionary="DICT_4X4_50",
        marker_size=c.marker_size,
        grid=(cols, int(np.ceil(len(base_ids) / cols))),
        spacing=c.marker_spacing,
    )
    textures, points = [base], [centres]
    half = 0.5 * base.size[0]
    for marker_id, side, height in zip(post_ids, (1.0, -1.0), (0.10, 0.06), strict=False):
        post, centre, _ = marker_board([marker_id], marker_size=c.marker_size, margin=0.015)
        shift = np.array([side * (half + 0.5 * post.size[0] + 0.02), 0.0, height])
        textures.append(PlanarTexture(post.image, post.size, post.R_o_p, post.t_o_p + shift))
        points.append(centre + shift)
    model = ObjectModel(
        ids=np.asarray(base_ids + post_ids),
        points=np.concatenate(points),
        assembly_point=np.asarray(c.assembly_point),
        marker_dictionary="DICT_4X4_50",
        marker_size=c.marker_size,
    )
    return textures, model


def _no_progress(items: Iterable, desc: str, total: int) -> Iterable:
    return items


def write_simulated_recording(
    cell: SimulatedCell,
    folder: str | Path,
    *,
    seed: int = 0,
    robot_latency_known: bool = False,
    kuka: bool = False,
    progress: Progress | None = None,
) -> Path:
    """Render the cell's images and write its recording folder (atomically).

    Args:
        cell: from :func:`jaxtraj.sim.cell.simulate_cell`.
        folder: the recording folder to create (replaced if it exists).
        seed: seed of the image noise.
        robot_latency_known: write the true latency into ``recording.json``; otherwise
            it is left for ``jaxtraj fuse`` to estimate.
        kuka: write the robot poses in KUKA form (X, Y, Z [mm], A, B, C [deg]).
        progress: ``progress(iterable, description, total)`` wrapping the render loops
            (e.g. a tqdm bar); None for none.

    Returns:
        the folder. ``camera.json`` is not written: ``jaxtraj calibrate`` makes it from
        the calibration images (the true one is in ``truth/camera.json``).
    """
    import cv2

    progress = progress or _no_progress
    c = cell.config
    rng = np.random.default_rng(seed)
    textures, model = workpiece(cell)
    T_w_o = pose_matrices(cell.object_pose)
    T_w_c = pose_matrices(cell.camera_pose)
    T_c_o = np.linalg.inv(T_w_c) @ T_w_o
    kw = dict(blur_px=c.blur_px, noise_std=c.pixel_noise)
    board, _ = chessboard_texture(CALIBRATION_TARGET["cols"], CALIBRATION_TARGET["rows"], 0.03)
    T_w_c_cal = pose_matrices(cell.calibration_flange) @ c.T_f_c
    T_c_t = np.linalg.inv(T_w_c_cal) @ cell.T_w_t
    true_camera = CameraCalibration(c.K, c.dist, c.image_size, T_f_c=c.T_f_c, T_i_c=c.T_i_c)
    meta = RecordingMeta(
        description=f"simulated robot cell (jaxtraj.sim, seed {seed})",
        imu_noise=ImuNoise(*(float(getattr(c.imu_noise, f)) for f in _IMU_FIELDS)),
        robot_noise=RobotNoise(float(c.robot_noise.position), float(c.robot_noise.orientation)),
        robot_latency=float(c.robot_latency) if robot_latency_known else None,
        calibration_target=dict(CALIBRATION_TARGET),
        T_i_c=c.T_i_c,
    )
    folder = Path(folder)
    with atomic_folder(folder) as tmp:
        (tmp / "images").mkdir()
        (tmp / "calibration").mkdir()
        files = []
        for f in progress(range(len(cell.times)), "render images", len(cell.times)):
            image = render(
                textures,
                T_c_o[f, :3, :3],
                T_c_o[f, :3, 3],
                c.K,
                c.dist,
                c.image_size,
                rng=rng,
                **kw,
            )
            files.append(tmp / "images" / f"{f:06d}.png")
            cv2.imwrite(str(files[-1]), image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        calib = []
        for v in progress(range(len(T_c_t)), "render calibration views", len(T_c_t)):
            image = render(
                board, T_c_t[v, :3, :3], T_c_t[v, :3, 3], c.K, c.dist, c.image_size, rng=rng, **kw
            )
            calib.append(tmp / "calibration" / f"view_{v:02d}.png")
            cv2.imwrite(str(calib[-1]), image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        rec = Recording(
            root=folder,
            meta=meta,
            camera=None,
            object=model,
            imu=ImuSamples(cell.imu_t, cell.gyro, cell.accel),
            robot=cell.robot,
            image_index=(np.arange(len(cell.times)), cell.times, files),
            calibration_images=calib,
            calibration_robot=_noisy(cell.calibration_flange, c.robot_noise, rng),
        )
        truth = Truth(
            object_pose=cell.object_pose, camera_pose=cell.camera_pose, camera=true_camera
        )
        write_recording_files(tmp, rec, truth=truth, kuka=kuka)
    return folder


_IMU_FIELDS = ("accel_noise_density", "gyro_noise_density", "accel_random_walk", "gyro_random_walk")


def _noisy(poses: PoseStream, noise, rng: np.random.Generator) -> PoseStream:
    """Flange poses as the controller reports them: position and orientation noise."""
    n = len(poses.times)
    R = quat_to_matrix(poses.q)
    dR = np.stack([_rot(v) for v in rng.normal(0, float(noise.orientation), (n, 3))])
    T = pose_matrix(R @ dR, poses.p + rng.normal(0, float(noise.position), (n, 3)))
    return _pose_stream(poses.times, T)

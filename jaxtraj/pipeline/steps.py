"""The pipeline's steps on folders: what each ``jaxtraj`` sub-command does.

Each step reads a recording folder (:mod:`jaxtraj.io.recording`), runs one stage, and
writes its outputs into a results folder (default ``RECORDING/results``). Every file is
written atomically; each step deletes its summary file (``fusion.json``,
``report.json``, ``evaluation.json``) first and writes it last, so a summary file is
present only when all of the step's outputs are complete.

Results folder::

    results/
      camera_poses.csv, camera_poses.tum   fused camera poses T_w_c at the image times
      fusion.json                          latency, filter consistency, pose sigmas
      detections.csv                       reference points found in the images
      pose.csv, pose.tum                   workpiece pose T_w_o per image
      assembly.csv                         the assembly point per image (t, x, y, z, ok)
      measurement.png                      assembly point and rotation over time
      points.csv                           reference points from the pose
      tracks.csv                           per-point trajectories (the paper's method)
      report.json                          what reconstruct did, skipped frames, methods
      evaluation.json, *.png               errors against truth/ (simulations)
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..io.csv_formats import read_poses, write_detections, write_points, write_poses, write_tum
from ..io.json_formats import write_camera, write_json
from ..io.recording import Recording, read_recording, read_truth
from ..io.tables import write_table

__all__ = [
    "default_results",
    "step_calibrate",
    "step_evaluate",
    "step_fuse",
    "step_reconstruct",
    "step_simulate",
]

Progress = Callable[[Iterable, str, int], Iterable]


def default_results(recording: Path) -> Path:
    """The default results folder of a recording."""
    return Path(recording) / "results"


def _start(out: Path, summary: str) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    (out / summary).unlink(missing_ok=True)
    return out / summary


def step_simulate(
    out: Path,
    *,
    seed: int = 0,
    frames: int = 150,
    duration: float = 10.0,
    latency_known: bool = False,
    kuka: bool = False,
    progress: Progress | None = None,
    camera_path: Path | None = None,
    cell_file: Path | None = None,
) -> Path:
    """Simulate a robot cell and write its recording folder with rendered images.

    With ``camera_path`` (a joint path CSV ``t,A1..A6``) the camera robot runs that path
    and the workpiece follows the prediction of ``cell_file`` (CELL.json or a
    ``design.json``; default: ``design.json`` beside the path); ``frames`` and ``duration``
    then come from the path (:func:`jaxtraj.sim.designed.designed_cell`).
    """
    from ..sim.cell import CellConfig, simulate_cell
    from ..sim.recording import write_simulated_recording

    if camera_path is not None:
        from ..io.cell import read_cell
        from ..io.csv_formats import read_joint_path
        from ..sim.designed import designed_cell

        camera_path = Path(camera_path)
        cell_file = camera_path.parent / "design.json" if cell_file is None else Path(cell_file)
        spec = read_cell(cell_file)
        t, q = read_joint_path(camera_path)
        try:
            cell = designed_cell(spec, t, q, seed=seed)
        except ValueError as err:
            raise ValueError(f"{camera_path}: {err}") from None
    else:
        cell = simulate_cell(CellConfig(n_images=frames, duration=duration), seed=seed)
    return write_simulated_recording(
        cell, out, seed=seed, robot_latency_known=latency_known, kuka=kuka, progress=progress
    )


def step_calibrate(folder: Path, options=None, **files):
    """Calibrate a recording (from ``calibration/``) or a calibration folder on its own.

    A folder with ``recording.json`` is a recording: ``camera.json`` is written into it.
    Any other folder is a calibration folder (:func:`.calibrate.calibrate_folder`, whose
    file options ``files`` takes): ``camera.json`` and ``calibration.json`` (the report)
    are written into it.
    """
    from .calibrate import calibrate_folder, calibrate_recording

    folder = Path(folder)
    if (folder / "recording.json").is_file():
        report = calibrate_recording(read_recording(folder), options)
    else:
        from ..io.json_formats import write_json

        report = calibrate_folder(folder, options=options, **files)
        write_json(folder / "calibration.json", report.to_json())
    write_camera(folder / "camera.json", report.camera)
    return report


def _camera(rec: Recording):
    if rec.camera is None:
        raise ValueError(
            f"{rec.root}: no camera.json (or camera.yaml); run `jaxtraj calibrate "
            f"{rec.root}` or provide the calibration"
        )
    return rec.camera


def _image_times(rec: Recording) -> tuple[np.ndarray, np.ndarray]:
    if rec.image_index is not None:
        return rec.image_index[0], rec.image_index[1]
    return rec.detections.frames, rec.detections.times


def step_fuse(
    recording: Path, out: Path | None = None, *, latency: float | None = None, smooth: bool = True
) -> dict:
    """Fuse IMU and robot poses; write the camera poses at the image times."""
    from ..fusion.events import RobotNoise
    from ..fusion.imu import ImuNoise
    from .fuse import fuse_camera_path

    rec = read_recording(recording)
    out = default_results(recording) if out is None else Path(out)
    camera = _camera(rec)
    if camera.T_f_c is None:
        raise ValueError(
            f"{rec.root}: the camera calibration has no hand-eye transform T_f_c; run "
            "`jaxtraj calibrate` with calibration/robot.csv, or add T_f_c to camera.json"
        )
    summary_path = _start(out, "fusion.json")
    T_i_c = camera.T_i_c if camera.T_i_c is not None else rec.meta.T_i_c
    _, times = _image_times(rec)
    latency = rec.meta.robot_latency if latency is None else latency
    m = rec.meta
    fused = fuse_camera_path(
        rec.imu.t,
        rec.imu.gyro,
        rec.imu.accel,
        rec.robot,
        times,
        T_f_c=camera.T_f_c,
        T_i_c=T_i_c,
        imu_noise=ImuNoise(**asdict(m.imu_noise)),
        robot_noise=RobotNoise(m.robot_noise.position, m.robot_noise.orientation),
        latency=latency,
        gravity_w=m.gravity_w,
        smooth=smooth,
    )
    write_poses(out / "camera_poses.csv", fused.pose)
    write_tum(out / "camera_poses.tum", fused.pose)
    summary = {
        "images": len(times),
        "imu_samples": fused.num_imu,
        "robot_poses": fused.num_robot,
        "robot_latency_s": fused.latency,
        "latency_estimated": fused.latency_estimated,
        "smoothed": smooth,
        "nis_mean": fused.nis_mean,
        "nis_expected": 6.0,
        "camera_position_sigma_mm": {
            "mean": float(fused.position_sigma.mean() * 1e3),
            "max": float(fused.position_sigma.max() * 1e3),
        },
        "camera_orientation_sigma_deg": {
            "mean": float(np.degrees(fused.orientation_sigma.mean())),
            "max": float(np.degrees(fused.orientation_sigma.max())),
        },
    }
    write_json(summary_path, summary)
    return summary


def step_reconstruct(
    recording: Path,
    out: Path | None = None,
    *,
    pose_method: str = "pnp",
    track_method: str = "estimate",
    k: int = 20,
    plots: bool = True,
    progress: Progress | None = None,
) -> dict:
    """Detect (if images), then measure trajectories and the 6-DoF pose; write results
    (and ``measurement.png``: the assembly point and rotation over time)."""
    from .detect import detect_images
    from .reconstruct import reconstruct_recording

    rec = read_recording(recording)
    out = default_results(recording) if out is None else Path(out)
    camera = _camera(rec)
    if not (out / "camera_poses.csv").exists() or not (out / "fusion.json").exists():
        raise ValueError(
            f"{out}: no complete camera poses (camera_poses.csv, fusion.json); run "
            f"`jaxtraj fuse {rec.root}` first"
        )
    summary_path = _start(out, "report.json")
    cameras = read_poses(out / "camera_poses.csv")
    notes = []
    if rec.image_index is not None:
        frames, times, files = rec.image_index
        det, notes = detect_images(frames, times, files, rec.object, camera, progress=progress)
        write_detections(out / "detections.csv", det)
    else:
        det = rec.detections
    meas = reconstruct_recording(
        det, camera, cameras, rec.object, pose_method=pose_method, track_method=track_method, k=k
    )
    write_poses(out / "pose.csv", meas.pose)
    write_tum(out / "pose.tum", meas.pose)
    write_table(
        out / "assembly.csv",
        ["frame", "t", "x", "y", "z", "ok"],
        [meas.frames, meas.times, *meas.assembly.T, meas.pose_ok.astype(np.int64)],
    )
    ok_points = np.repeat(meas.pose_ok[:, None], len(meas.ids), axis=1)
    write_points(out / "points.csv", meas.times, meas.ids, meas.points, ok_points, meas.frames)
    if track_method != "none":
        track_ok = np.isfinite(meas.track_points).all(-1) & meas.track_ok[None, :]
        write_points(
            out / "tracks.csv",
            meas.times,
            meas.ids,
            meas.track_points,
            track_ok,
            meas.frames,
        )
    if plots:
        from ..io.plots import plot_measurement
        from .evaluate import quat_to_matrix, rotation_error_deg

        R = quat_to_matrix(meas.pose.q)
        first = int(np.flatnonzero(meas.pose_ok)[0])
        angles = rotation_error_deg(R[first], R)  # rotation since the first pose
        plot_measurement(out / "measurement.png", meas.times, meas.assembly, angles, meas.pose_ok)
    detected = det.detected.sum(axis=1)
    summary = {
        "frames": len(meas.times),
        "frames_with_pose": int(meas.pose_ok.sum()),
        "pose_method": pose_method,
        "track_method": track_method,
        "k": k if track_method == "dct" or pose_method == "joint" else None,
        "detections_per_frame": {"mean": float(detected.mean()), "min": int(detected.min())},
        "pose_reprojection_rms_px": {
            "mean": float(np.nanmean(meas.pose_rms_px)),
            "max": float(np.nanmax(meas.pose_rms_px)),
        },
        "tracks": {
            str(int(i)): {
                "ok": bool(o),
                "reprojection_rms_px": float(r),
                "max_posterior_std_mm": float(sd * 1e3),
            }
            for i, o, r, sd in zip(
                meas.ids, meas.track_ok, meas.track_rms_px, meas.track_std, strict=True
            )
        }
        if track_method != "none"
        else None,
        "skipped_frames": [{"frame": f, "reason": why} for f, why in meas.skipped],
        "notes": [{"frame": f, "note": n} for f, n in notes],
    }
    write_json(summary_path, summary)
    return summary


def step_evaluate(recording: Path, out: Path | None = None, *, plots: bool = True) -> dict:
    """Compare the results with ``truth/``; write evaluation.json and plots."""
    from ..io.tables import read_table
    from .evaluate import evaluate_results

    recording = Path(recording)
    out = default_results(recording) if out is None else Path(out)
    truth = read_truth(recording)
    if truth is None:
        raise ValueError(f"{recording}: no truth/ folder; evaluate needs a simulated recording")
    if not (out / "report.json").exists():
        raise ValueError(f"{out}: no complete results (report.json); run `jaxtraj reconstruct`")
    summary_path = _start(out, "evaluation.json")
    rec = read_recording(recording)
    pose = read_poses(out / "pose.csv")
    ok = read_table(out / "assembly.csv", {"frame": "int", "t": "float", "ok": "int"})["ok"] > 0
    tracks = None
    if (out / "tracks.csv").exists():
        from ..io.csv_formats import read_points

        tr = read_points(out / "tracks.csv")
        tracks = tr.points  # all of them, also those flagged as uncertain (tr.ok)
    camera_pose = (
        read_poses(out / "camera_poses.csv") if (out / "camera_poses.csv").exists() else None
    )
    summary, series = evaluate_results(
        times=pose.times,
        pose=pose,
        pose_ok=ok,
        assembly_point=rec.object.assembly_point,
        model_points=rec.object.points,
        track_points=tracks,
        camera_pose=camera_pose,
        camera=rec.camera,
        truth_object=truth.object_pose,
        truth_camera_pose=truth.camera_pose,
        truth_camera=truth.camera,
    )
    if plots:
        from ..io.plots import plot_errors, plot_trajectory

        a_true, a_meas = series["assembly_true"], series["assembly_measured"]
        plot_trajectory(
            out / "trajectory.png",
            a_true,
            a_meas[ok],
            title="Assembly point: measured (red +) vs true",
        )
        plot_errors(out / "errors.png", pose.times[ok], a_true[ok], a_meas[ok])
        summary["plots"] = ["trajectory.png", "errors.png"]
    write_json(summary_path, summary)
    return summary

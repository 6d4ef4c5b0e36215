"""The ``jaxtraj`` command.

Sub-commands (``jaxtraj COMMAND --help`` explains each option):
    simulate     write the recording folder of a simulated robot cell, images rendered
    calibrate    camera intrinsics and hand-eye transform from a calibration folder
    fuse         camera poses at the image times from the IMU and robot logs
    reconstruct  detect the markers, measure the trajectories and the 6-DoF pose
    evaluate     compare the results with the simulation's ground truth
    batch        many point tracks from .npy files: chunked, sharded, resumable
    design       a joint-space camera path for a robot cell (CELL.json or --example)
    demo         all of the above on a simulated cell (``--paper``: the paper's
                 section-5 experiment on ideal detections instead)

Exit codes: 0 success; 1 the run finished but its result failed a check (a degenerate
reconstruction, accuracy targets missed); 2 bad usage or input (one line on stderr
naming the file, line and problem); 130 interrupted.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

# defined in ._cli_common (shared with .commands and .demo); re-exported here
from ._cli_common import EXIT_FAILED as EXIT_FAILED
from ._cli_common import EXIT_OK as EXIT_OK
from ._cli_common import EXIT_USAGE as EXIT_USAGE
from ._cli_common import SIMULATE_DURATION, SIMULATE_FRAMES
from ._cli_common import TARGET_ORIENTATION_DEG as TARGET_ORIENTATION_DEG
from ._cli_common import TARGET_POSITION_MM as TARGET_POSITION_MM
from ._cli_common import UsageError as UsageError


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return value


def _nonneg_float(text: str) -> float:
    value = float(text)
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"expected a non-negative number, got {text}")
    return value


def _positive_float(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return value


def _add_results(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", type=Path, help="the recording folder")
    p.add_argument(
        "--out", type=Path, default=None, help="results folder (default: RECORDING/results)"
    )


def _add_reconstruct_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--pose-method",
        choices=("pnp", "joint"),
        default="pnp",
        help="6-DoF pose: 'pnp' per image (PnP + Levenberg-Marquardt with the fused camera "
        "pose; default) or 'joint' (one smooth rigid motion in a DCT basis of --k vectors, "
        "fitted to all pixels, started from the per-image poses)",
    )
    p.add_argument(
        "--track-method",
        choices=("estimate", "smoother", "dct", "none"),
        default="estimate",
        help="per-point trajectories without the object model (the paper's method): "
        "'estimate' (jaxtraj.estimate_points: motion model chosen per point, flagged where "
        "the depth is not determined; default), 'smoother' (smoothness prior of order 2), "
        "'dct' (plain DCT with --k vectors) or 'none'",
    )
    p.add_argument("--k", type=_positive_int, default=20, help="DCT vectors (default 20)")


def _add_simulate_options(
    p: argparse.ArgumentParser, frames_default: int = SIMULATE_FRAMES, resolved_later: bool = False
) -> None:
    """``--frames``, ``--duration``, ``--seed``; ``resolved_later``: frames and duration
    default to None (the command fills in the defaults or takes them from elsewhere)."""
    p.add_argument(
        "--frames",
        type=_positive_int,
        default=None if resolved_later else frames_default,
        help=f"number of images (default {frames_default}, as in the paper)",
    )
    p.add_argument(
        "--duration",
        type=_positive_float,
        default=None if resolved_later else SIMULATE_DURATION,
        help=f"recording length [s] (default {SIMULATE_DURATION:g})",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxtraj",
        description="Trajectory and 6-DoF pose of a moving workpiece from a robot-carried "
        "monocular camera, its IMU and the robot controller's poses.",
        epilog="Exit codes: 0 ok, 1 result failed a check, 2 bad usage or input.",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    sim = sub.add_parser(
        "simulate",
        help="write a simulated robot cell's recording folder (rendered images)",
        description="Simulate a robot cell: a workpiece with six ArUco markers on a smooth "
        "6-DoF path, a camera with an IMU on a second robot sweeping over it, images "
        "rendered with lens distortion, blur and noise at irregular times, IMU and robot "
        "controller logs, chessboard calibration images. Writes the recording folder "
        "(format: jaxtraj.io.recording) with the ground truth in truth/.",
    )
    sim.add_argument("out", type=Path, help="the recording folder to write (replaced if present)")
    _add_simulate_options(sim, resolved_later=True)
    sim.add_argument(
        "--camera-path",
        type=Path,
        default=None,
        help="run the camera robot on this joint path (t, A1..A6 [s, deg]; jaxtraj design's "
        "joint_path.csv) with the workpiece on the cell's predicted trajectory; images at "
        "the path's times",
    )
    sim.add_argument(
        "--cell",
        type=Path,
        default=None,
        help="--camera-path: the cell (CELL.json or design.json; default: design.json beside "
        "the path)",
    )
    sim.add_argument(
        "--latency-known",
        action="store_true",
        help="write the robot latency into recording.json (default: leave it to be estimated)",
    )
    sim.add_argument(
        "--kuka",
        action="store_true",
        help="write robot.csv in KUKA form (X, Y, Z in mm; A, B, C in degrees) instead of "
        "position + quaternion",
    )

    cal = sub.add_parser(
        "calibrate",
        help="intrinsics (+ hand-eye) from a calibration folder or a recording's calibration/",
        description="Calibrate K and the distortion (OpenCV) and, with robot poses, the "
        "hand-eye transform: every OpenCV method is scored by the consistency it achieves, "
        "the best one starts a JAX bundle adjustment of intrinsics, distortion, hand-eye and "
        "target pose over all corners. FOLDER is a recording (with recording.json: the "
        'target is its "calibration_target", the views calibration/*.png with '
        "calibration/robot.csv; writes FOLDER/camera.json) or a calibration folder: "
        "target.json, images (*.png, *.jpg, ...) or corners.csv (view,id,u,v), and "
        "robot.csv (optional; a file column or natural sort pairs rows with views); writes "
        "FOLDER/camera.json and FOLDER/calibration.json (the report).",
    )
    cal.add_argument(
        "recording", metavar="FOLDER", type=Path, help="a calibration folder or a recording folder"
    )
    cal.add_argument("--target", type=Path, default=None, help="target description (target.json)")
    cal.add_argument("--robot", type=Path, default=None, help="robot poses (robot.csv)")
    cal.add_argument(
        "--corners", type=Path, default=None, help="detected corners view,id,u,v (corners.csv)"
    )
    cal.add_argument(
        "--robot-format",
        choices=("auto", "pq", "kuka", "rpy", "rotvec", "matrix"),
        default="auto",
        help="robot pose columns: pq x,y,z,qw,qx,qy,qz; kuka X,Y,Z,A,B,C (mm, deg, "
        "Rz(A) Ry(B) Rx(C)); rpy x,y,z,roll,pitch,yaw (Rz(yaw) Ry(pitch) Rx(roll): fixed "
        "axes x, y, z); rotvec x,y,z,rx,ry,rz (axis-angle, UR); matrix m00..m23 (row-major "
        "3x4); auto: from the header (default)",
    )
    cal.add_argument(
        "--length-unit", choices=("m", "mm"), default="m", help="robot positions (not kuka)"
    )
    cal.add_argument(
        "--angle-unit", choices=("rad", "deg"), default="rad", help="robot angles (not kuka)"
    )
    cal.add_argument(
        "--method",
        choices=("auto", "tsai", "park", "horaud", "andreff", "daniilidis", "shah", "li"),
        default="auto",
        help="OpenCV hand-eye method that starts the refinement (auto: the most consistent)",
    )
    cal.add_argument(
        "--no-refine", action="store_true", help="keep OpenCV's result (no bundle adjustment)"
    )
    cal.add_argument(
        "--eye-to-hand",
        action="store_true",
        help="the camera stands still and the target is on the flange",
    )
    cal.add_argument(
        "--robot-sigma-mm", type=_positive_float, default=None,
        help="robot position noise [mm] (default 0.1; a recording: its recording.json)",
    )  # fmt: skip
    cal.add_argument(
        "--robot-sigma-deg", type=_positive_float, default=None,
        help="robot rotation noise [deg] (default 0.02; a recording: its recording.json)",
    )  # fmt: skip
    cal.add_argument(
        "--max-spread-mm", type=_positive_float, default=None,
        help="accept when the implied target position spreads less (default: from the data)",
    )  # fmt: skip
    cal.add_argument(
        "--max-spread-deg", type=_positive_float, default=None,
        help="accept when the implied target orientation spreads less (default: from the data)",
    )  # fmt: skip
    cal.add_argument(
        "--min-corners", type=_positive_int, default=6, help="fewest target points per view (6)"
    )

    fuse = sub.add_parser(
        "fuse",
        help="camera poses at the image times from IMU + robot logs",
        description="Error-state Kalman filter and RTS smoother over imu.csv and robot.csv "
        "(hand-eye from camera.json); writes camera_poses.csv/.tum and fusion.json.",
    )
    _add_results(fuse)
    fuse.add_argument(
        "--latency",
        type=float,
        default=None,
        help="robot pose latency [s] (default: recording.json's, else estimated)",
    )
    fuse.add_argument(
        "--no-smoother", action="store_true", help="filter only (causal), no RTS smoother"
    )

    rec = sub.add_parser(
        "reconstruct",
        help="detect markers, measure trajectories and 6-DoF pose",
        description="Detect the object model's markers in the images (or read "
        "detections.csv), then measure the workpiece pose per image and the per-point "
        "trajectories; needs camera.json and the results of `jaxtraj fuse`. Writes "
        "pose.csv/.tum, assembly.csv, points.csv, tracks.csv, detections.csv, report.json and "
        "measurement.png.",
    )
    _add_results(rec)
    _add_reconstruct_options(rec)
    rec.add_argument("--no-plots", action="store_true", help="skip measurement.png")

    ev = sub.add_parser(
        "evaluate",
        help="errors against the ground truth of a simulated recording",
        description="Compare the results with RECORDING/truth/: assembly-point position, "
        "orientation, per-point trajectories, camera poses, calibration. Writes "
        "evaluation.json and trajectory.png/errors.png (the paper's Fig. 3/4).",
    )
    _add_results(ev)
    ev.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    ev.add_argument(
        "--max-position-mm",
        type=_positive_float,
        default=None,
        help="exit 1 if the mean assembly-point error exceeds this [mm]",
    )
    ev.add_argument(
        "--max-orientation-deg",
        type=_positive_float,
        default=None,
        help="exit 1 if the mean orientation error exceeds this [deg]",
    )

    batch = sub.add_parser(
        "batch",
        help="reconstruct millions of point tracks from .npy files, chunked and resumable",
        description="Reconstruct every track of a batch dataset (cameras.npz, tracks.npy, "
        "optional weights.npy; layout in jaxtraj.scale.chunked) with the DCT basis, in "
        "fixed-size chunks sharded over the devices, writing points.npy, coeffs.npy, "
        "rms_px.npy, gain.npy, status.npy into OUT. An interrupted run continues where it "
        "stopped when started again with the same options. Multi-host: start the same "
        "command on every host with --coordinator HOST:PORT --num-processes Q "
        "--process-id P (jax.distributed.initialize); OUT must be on a shared file system.",
    )
    batch.add_argument("dataset", type=Path, help="the dataset folder")
    batch.add_argument("out", type=Path, help="the output folder")
    batch.add_argument("--k", type=_positive_int, required=True, help="DCT basis vectors")
    batch.add_argument(
        "--chunk-size",
        type=_positive_int,
        default=4096,
        help="points per chunk (default 4096; a multiple of the device count)",
    )
    batch.add_argument(
        "--devices",
        type=_positive_int,
        default=None,
        help="local devices to shard each chunk over (default: all)",
    )
    batch.add_argument("--restart", action="store_true", help="discard earlier progress")
    batch.add_argument("--float32", action="store_true", help="compute in float32")
    batch.add_argument("--coordinator", default=None, help="multi-host: HOST:PORT of process 0")
    batch.add_argument("--num-processes", type=_positive_int, default=None, help="multi-host")
    batch.add_argument("--process-id", type=int, default=None, help="multi-host: this process")

    design = sub.add_parser(
        "design",
        help="design a camera path in the camera robot's joint space for a cell",
        description="Designs the camera robot's joint path (KUKA A1..A6) that measures the "
        "predicted workpiece best within the joint position/speed/acceleration/jerk limits, "
        "the field of view, stand-off, keep-out and floor. Writes OUT/joint_path.csv, "
        "joint_path_ipo.csv (12 ms, up to the last cycle before the end), camera_poses.tum, "
        "design.json and plots. Exits 1 if no start found a feasible design.",
    )
    design.add_argument("cell", nargs="?", type=Path, help="CELL.json (see jaxtraj.io.cell)")
    design.add_argument("out", type=Path, help="output folder")
    design.add_argument(
        "--example",
        action="store_true",
        help="the built-in simulated cell (KR 16-2 camera robot, KR 60-3 workpiece robot) "
        "instead of CELL.json",
    )
    design.add_argument(
        "--frames", type=_positive_int, default=60, help="--example: images (default 60)"
    )
    design.add_argument(
        "--starts", type=_positive_int, default=None, help="initial guesses (default 8)"
    )
    design.add_argument("--no-plots", action="store_true", help="skip the PNG figures")

    demo = sub.add_parser(
        "demo",
        help="simulate -> calibrate -> fuse -> reconstruct -> evaluate on a simulated cell",
        description="The whole pipeline on a simulated robot cell with rendered images: "
        "writes OUT/recording (with OUT/recording/results) and prints the errors. Exits 1 "
        f"if the mean assembly-point error exceeds {TARGET_POSITION_MM} mm or the mean "
        f"orientation error {TARGET_ORIENTATION_DEG} deg. With --paper: the paper's "
        "section-5 experiment on ideal detections (one point, random discontinuous camera; "
        "Fig. 3/4 and summary.json in OUT).",
    )
    demo.add_argument(
        "--out", type=Path, default=Path("jaxtraj-demo"), help="output folder (./jaxtraj-demo)"
    )
    demo.add_argument(
        "--frames", type=_positive_int, default=150, help="number of images (default 150)"
    )
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    demo.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    demo.add_argument(
        "--paper",
        action="store_true",
        help="the paper's experiment on ideal detections instead of the rendered cell",
    )
    demo.add_argument(
        "--method",
        choices=("dct", "auto-k", "regularised", "smoother"),
        default="dct",
        help="--paper only: 'dct' (the paper's plain DCT, fixed k), 'auto-k' (k chosen by "
        "cross-validation), 'regularised' (DCT with a cross-validated roughness penalty) or "
        "'smoother' (smoothness prior, no basis)",
    )
    demo.add_argument("--k", type=_positive_int, default=None, help="--paper --method dct: k")
    demo.add_argument(
        "--noise", type=_nonneg_float, default=0.3, help="--paper: pixel noise [px] (0.3)"
    )
    demo.add_argument("--float32", action="store_true", help="--paper: compute in float32")
    return parser


def _progress(quiet: bool):
    """A ``progress(iterable, description, total)`` wrapper: tqdm bars on a terminal."""
    if quiet or not sys.stderr.isatty():
        return None
    from tqdm import tqdm

    return lambda items, desc, total: tqdm(items, desc=desc, total=total, leave=False)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jaxtraj`` console script; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    from .io.tables import RecordingError

    try:
        if args.command == "demo" and args.paper:
            from .demo import run_demo

            return run_demo(args)
        from .commands import run_command

        return run_command(args, _progress(args.quiet))
    except (UsageError, RecordingError, ValueError, FileNotFoundError, NotADirectoryError) as err:
        print(f"jaxtraj {args.command}: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("jaxtraj: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

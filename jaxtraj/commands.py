"""What the ``jaxtraj`` sub-commands print and return (the CLI's body; see :mod:`.cli`)."""

from __future__ import annotations

import time
from argparse import Namespace
from pathlib import Path

import jax

from ._cli_common import (
    EXIT_FAILED,
    EXIT_OK,
    SIMULATE_DURATION,
    SIMULATE_FRAMES,
    TARGET_ORIENTATION_DEG,
    TARGET_POSITION_MM,
)
from .pipeline import steps


def _fmt(stats: dict, unit: str, digits: int = 2) -> str:
    if stats.get(f"mean_{unit}") is None:
        return "n/a"
    mean, top = stats[f"mean_{unit}"], stats[f"max_{unit}"]
    return f"mean {mean:.{digits}f} {unit}, max {top:.{digits}f} {unit}"


def _simulate(args: Namespace, progress) -> int:
    if args.camera_path is None and args.cell is not None:
        raise ValueError("--cell: needs --camera-path (the joint path the cell is run with)")
    if args.camera_path is not None and (args.frames is not None or args.duration is not None):
        raise ValueError("--frames, --duration: set by --camera-path (its times), not given")
    folder = steps.step_simulate(
        args.out,
        seed=args.seed,
        frames=SIMULATE_FRAMES if args.frames is None else args.frames,
        duration=SIMULATE_DURATION if args.duration is None else args.duration,
        latency_known=args.latency_known,
        kuka=args.kuka,
        progress=progress,
        camera_path=args.camera_path,
        cell_file=args.cell,
    )
    frames = len(list((Path(folder) / "images").glob("*.png")))
    seed = args.seed
    path = "" if args.camera_path is None else f", camera robot on {args.camera_path}"
    print(f"jaxtraj simulate: wrote the recording {folder} ({frames} images, seed {seed}{path})")
    return EXIT_OK


def _calibration_options(args: Namespace):
    import numpy as np

    from .pipeline.calibrate import DEFAULT_ROBOT_SIGMA, CalibrationOptions

    sigma = None  # default: recording.json's for a recording, else DEFAULT_ROBOT_SIGMA
    if args.robot_sigma_mm is not None or args.robot_sigma_deg is not None:
        sigma = (
            DEFAULT_ROBOT_SIGMA[0] if args.robot_sigma_mm is None else args.robot_sigma_mm * 1e-3,
            DEFAULT_ROBOT_SIGMA[1]
            if args.robot_sigma_deg is None
            else float(np.radians(args.robot_sigma_deg)),
        )
    options = CalibrationOptions(
        robot_format=args.robot_format,
        length_unit=args.length_unit,
        angle_unit=args.angle_unit,
        method=args.method,
        refine=not args.no_refine,
        eye_to_hand=args.eye_to_hand,
        robot_sigma=sigma,
        max_position_spread=None if args.max_spread_mm is None else args.max_spread_mm * 1e-3,
        max_rotation_spread=(
            None if args.max_spread_deg is None else float(np.radians(args.max_spread_deg))
        ),
        min_corners=args.min_corners,
    )
    return options


def _calibrate(args: Namespace, progress) -> int:
    options = _calibration_options(args)
    folder = Path(args.recording)
    files = {"target_file": args.target, "robot_file": args.robot, "corners_file": args.corners}
    if (folder / "recording.json").is_file():
        if any(v is not None for v in files.values()):
            raise ValueError("--target, --robot, --corners: only for a calibration folder")
        files = {}
    report = steps.step_calibrate(folder, options, **files)
    K = report.camera.K
    print(
        f"jaxtraj calibrate: {len(report.views_used)} views used, reprojection RMS "
        f"{report.rms_px:.3f} px; fx {K[0, 0]:.2f}, fy {K[1, 1]:.2f}, cx {K[0, 2]:.2f}, "
        f"cy {K[1, 2]:.2f} px"
    )
    for name, why in report.views_skipped:
        print(f"  skipped {name}: {why}")
    he = report.hand_eye
    if he is not None:
        setup = "eye-in-hand" if he["eye_in_hand"] else "eye-to-hand"
        print(
            f"  hand-eye ({setup}): consistency (target pose implied by each view, RMS spread; "
            f"limits {he['limits']}: {he['position_limit_mm']:.2f} mm, "
            f"{he['rotation_limit_deg']:.3f} deg)"
        )
        rows = [(m, c) for m, c in he["methods"].items()]
        if he["refined"] is not None:
            rows.append((f"refined ({he['method']} start)", he["refined"]))
        for name, c in rows:
            if "error" in c:
                print(f"    {name:22s} failed: {c['error']}")
                continue
            mark = " <- start" if name == he["method"] else ""
            spread = (
                f"{c['target_spread_position_mm']:7.3f} mm {c['target_spread_rotation_deg']:7.4f}"
            )
            axxb = f"{c['translation_residual_mm']:7.3f} mm {c['rotation_residual_deg']:7.4f}"
            print(f"    {name:22s} spread {spread} deg; AX=XB {axxb} deg{mark}")
        if he["refined"] is not None:
            sd = he["refined"]["std"]
            print(
                f"  refined: RMS {he['refined']['rms_px']:.3f} px, hand-eye std "
                f"{max(sd['hand_eye_translation_mm']):.3f} mm, "
                f"{max(sd['hand_eye_rotation_deg']):.4f} deg (largest axis)"
            )
        print(
            f"  hand-eye: residual {he['rotation_residual_deg']:.3f} deg, "
            f"{he['translation_residual_mm']:.2f} mm ({'OK' if he['ok'] else 'NOT OK'})"
        )
        for why in he["reasons"]:
            print(f"  rejected: {why}")
    print(f"  wrote {folder / 'camera.json'}")
    return EXIT_OK if he is None or he["ok"] else EXIT_FAILED


def _fuse(args: Namespace, progress) -> int:
    s = steps.step_fuse(args.recording, args.out, latency=args.latency, smooth=not args.no_smoother)
    lat = "estimated" if s["latency_estimated"] else "given"
    print(
        f"jaxtraj fuse: {s['imu_samples']} IMU samples, {s['robot_poses']} robot poses -> "
        f"{s['images']} camera poses; latency {s['robot_latency_s'] * 1e3:.2f} ms ({lat}); "
        f"NIS {s['nis_mean']:.2f} (expected 6); camera sigma "
        f"{s['camera_position_sigma_mm']['mean']:.3f} mm, "
        f"{s['camera_orientation_sigma_deg']['mean']:.4f} deg"
    )
    return EXIT_OK


def _reconstruct(args: Namespace, progress) -> int:
    s = steps.step_reconstruct(
        args.recording,
        args.out,
        pose_method=args.pose_method,
        track_method=args.track_method,
        k=args.k,
        plots=not args.no_plots,
        progress=progress,
    )
    print(
        f"jaxtraj reconstruct: {s['frames_with_pose']}/{s['frames']} images with a pose "
        f"({s['pose_method']}), {s['detections_per_frame']['mean']:.1f} reference points per "
        f"image, pose reprojection RMS {s['pose_reprojection_rms_px']['mean']:.3f} px"
    )
    for item in s["skipped_frames"]:
        print(f"  frame {item['frame']} skipped: {item['reason']}")
    for item in s["notes"]:
        print(f"  frame {item['frame']}: {item['note']}")
    if s["tracks"] is not None:
        bad = [i for i, t in s["tracks"].items() if not t["ok"]]
        worst = max(t["max_posterior_std_mm"] for t in s["tracks"].values())
        print(
            f"  per-point trajectories ({s['track_method']}, no object model): "
            + ("all OK" if not bad else f"NOT OK (uncertain/degenerate): ids {', '.join(bad)}")
            + f"; largest posterior std {worst:.1f} mm"
        )
    return EXIT_OK if s["frames_with_pose"] > 0 else EXIT_FAILED


def _print_evaluation(s: dict, indent: str = "  ") -> None:
    print(f"{indent}assembly point: {_fmt(s['assembly_point_position'], 'mm')}")
    print(f"{indent}orientation:    {_fmt(s['orientation'], 'deg', 3)}")
    if "per_point_trajectories" in s:
        print(
            f"{indent}per-point trajectories (no model): {_fmt(s['per_point_trajectories'], 'mm')}"
        )
    if "camera_pose" in s:
        cp = s["camera_pose"]
        print(
            f"{indent}fused camera pose vs truth: {_fmt(cp['position'], 'mm')}; "
            f"{_fmt(cp['orientation'], 'deg', 3)}"
        )
    if "calibration" in s:
        c = s["calibration"]
        he = ""
        if "hand_eye_position_error_mm" in c:
            he = (
                f"; hand-eye {c['hand_eye_position_error_mm']:.2f} mm, "
                f"{c['hand_eye_rotation_error_deg']:.3f} deg"
            )
        print(
            f"{indent}calibration vs truth: focal {c['focal_error_px']:.2f} px, principal "
            f"point {c['principal_point_error_px']:.2f} px{he}"
        )


def _passes(s: dict, max_mm: float | None, max_deg: float | None) -> bool:
    pos, ang = s["assembly_point_position"]["mean_mm"], s["orientation"]["mean_deg"]
    if pos is None or ang is None:
        return False
    return (max_mm is None or pos <= max_mm) and (max_deg is None or ang <= max_deg)


def _evaluate(args: Namespace, progress) -> int:
    s = steps.step_evaluate(args.recording, args.out, plots=not args.no_plots)
    print(f"jaxtraj evaluate: {s['frames_with_pose']}/{s['frames']} images with a pose")
    _print_evaluation(s)
    return EXIT_OK if _passes(s, args.max_position_mm, args.max_orientation_deg) else EXIT_FAILED


def _true_latency_ms() -> float:
    from .sim.cell import CellConfig

    return CellConfig.__dataclass_fields__["robot_latency"].default * 1e3


def _demo(args: Namespace, progress) -> int:
    out = Path(args.out)
    recording = out / "recording"
    t0 = time.perf_counter()
    print(f"jaxtraj demo: simulated robot cell, {args.frames} rendered images, seed {args.seed}")
    steps.step_simulate(recording, seed=args.seed, frames=args.frames, progress=progress)
    print(f"  1 simulate    wrote {recording} ({time.perf_counter() - t0:.0f} s)")
    cal = steps.step_calibrate(recording)
    he = cal.hand_eye or {}
    print(
        f"  2 calibrate   {len(cal.views_used)} chessboard views, RMS {cal.rms_px:.3f} px, "
        f"hand-eye {'OK' if he.get('ok') else 'NOT OK'}"
    )
    fu = steps.step_fuse(recording)
    print(
        f"  3 fuse        ESKF + RTS smoother, latency {fu['robot_latency_s'] * 1e3:.2f} ms "
        f"(estimated; true {_true_latency_ms():.2f} ms), NIS {fu['nis_mean']:.2f}"
    )
    rc = steps.step_reconstruct(recording, plots=not args.no_plots, progress=progress)
    print(
        f"  4 reconstruct {rc['frames_with_pose']}/{rc['frames']} images with a pose, "
        f"{rc['detections_per_frame']['mean']:.1f} markers per image, "
        f"{len(rc['skipped_frames'])} skipped"
    )
    ev = steps.step_evaluate(recording, plots=not args.no_plots)
    print(f"  5 evaluate    ({time.perf_counter() - t0:.0f} s in all)")
    _print_evaluation(ev, indent="      ")
    print(
        f"  targets: assembly point <= {TARGET_POSITION_MM} mm, orientation <= "
        f"{TARGET_ORIENTATION_DEG} deg (mean); paper (real cell): < 6 mm mean"
    )
    print(f"  results in {recording / 'results'}")
    if not _passes(ev, TARGET_POSITION_MM, TARGET_ORIENTATION_DEG):
        print("  WARNING: the accuracy targets were missed")
        return EXIT_FAILED
    return EXIT_OK


def _batch(args: Namespace, progress) -> int:
    import jax.numpy as jnp

    from .scale import point_mesh, run_batch

    if args.coordinator is not None:
        jax.distributed.initialize(args.coordinator, args.num_processes, args.process_id)
    devices = jax.local_devices()
    if args.devices is not None:
        if args.devices > len(devices):
            raise ValueError(f"--devices {args.devices}: only {len(devices)} local device(s)")
        devices = devices[: args.devices]
    mesh = point_mesh(devices) if len(devices) > 1 else None
    s = run_batch(
        args.dataset,
        args.out,
        k=args.k,
        chunk_size=args.chunk_size,
        mesh=mesh,
        restart=args.restart,
        progress=progress,
        dtype=jnp.float32 if args.float32 else jnp.float64,
    )
    rate = s.computed_points / s.seconds if s.seconds > 0 and s.computed else 0.0
    print(
        f"jaxtraj batch: {s.points} points in {s.chunks} chunks on {len(devices)} device(s); "
        f"{s.computed} computed now ({s.seconds:.1f} s incl. compilation, ~{rate:,.0f} points/s), "
        f"{s.skipped} done before; status counts {s.status_counts}"
    )
    return EXIT_OK


def _design(args: Namespace, progress) -> int:
    from .design_command import design_cell, example_cell, write_design
    from .io.cell import read_cell

    if args.example == (args.cell is not None):
        raise ValueError("give either CELL.json or --example (not both, not neither)")
    spec = example_cell(frames=args.frames) if args.example else read_cell(args.cell)
    if args.starts is not None:
        spec.starts = args.starts
    result = design_cell(spec)
    write_design(args.out, spec, result, plots=not args.no_plots)
    best = result["best"]
    print(
        f"design: expected mean error {1000 * float(best.expected_mean_error):.2f} mm "
        f"(worst frame {1000 * float(best.expected_worst_error):.1f} mm), "
        f"max violation {float(best.max_violation):.2e}, stationarity "
        f"{float(best.stationarity):.2e}, converged starts "
        f"{int(result['designs'].converged.sum())}/{spec.starts}, "
        f"{result['seconds']:.1f} s -> {args.out}"
    )
    return EXIT_OK if bool(best.feasible) else EXIT_FAILED


_COMMANDS = {
    "simulate": _simulate,
    "calibrate": _calibrate,
    "fuse": _fuse,
    "reconstruct": _reconstruct,
    "evaluate": _evaluate,
    "batch": _batch,
    "demo": _demo,
    "design": _design,
}


def run_command(args: Namespace, progress=None) -> int:
    """Run one parsed sub-command (not ``demo --paper``); returns the exit code."""
    jax.config.update("jax_enable_x64", True)  # host-side program, not library code
    return _COMMANDS[args.command](args, progress)

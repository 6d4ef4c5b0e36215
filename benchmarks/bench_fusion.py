"""Benchmark of the camera-pose fusion: throughput of the jit-compiled scan against a
straightforward NumPy per-step loop of the same filter (measured in the same run), and
accuracy on simulated and EuRoC data.

    python benchmarks/bench_fusion.py [--quick] [--output benchmarks/results/fusion.md]

Throughput is IMU samples processed per second (the stream also holds robot poses every
12 ms and image times at 30 Hz); the real-time factor is that rate divided by the IMU's
250 Hz. Times are the minimum over repeats after compilation.

Importing jaxtraj lets XLA:CPU compile the filter's scan into one kernel (see
``jaxtraj/_xla.py``); for comparison the benchmark also times the scan in a subprocess with
that option off (``JAXTRAJ_XLA_SMALL_LOOPS=0``: one XLA runtime dispatch per fused op).
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import jaxlie  # noqa: E402
import numpy as np  # noqa: E402

from jaxtraj.fusion import (  # noqa: E402
    ImuData,
    ImuNoise,
    RobotNoise,
    build_events,
    eskf,
    eskf_batch,
    initial_covariance,
    initial_state,
    interpolate_poses,
    nees,
    rts_smoother,
)
from jaxtraj.fusion.reference import eskf_numpy  # noqa: E402
from jaxtraj.fusion.simulate import LissajousTrajectory, simulate_recording, true_states  # noqa: E402

IMU_RATE = 250.0
TRAJ = LissajousTrajectory()
IMU_NOISE = ImuNoise.xsens_mti()
ROBOT_NOISE = RobotNoise.kuka_class()
P0 = initial_covariance(1e-3, 0.05, 0.02, 0.1, 0.01)


def _time(fn, repeats):
    jax.block_until_ready(fn())
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t)
    return best


def _cast(tree, dtype):
    return jax.tree_util.tree_map(
        lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, tree
    )


def _recording(key, duration):
    rec = simulate_recording(
        key,
        TRAJ,
        duration=duration,
        imu_noise=IMU_NOISE,
        robot_noise=ROBOT_NOISE,
        imu_rate=IMU_RATE,
        robot_period=0.012,
        image_rate=30.0,
        latency=0.004,
    )
    ev = build_events(rec.imu, rec.robot, rec.image_times, noise=ROBOT_NOISE, latency=rec.latency)
    return rec, ev, initial_state(ev)


def one_kernel(ev, x0) -> bool:
    """Whether XLA compiled the filter's scan into one kernel (the small-loop option)."""
    return "xla_cpu_small_call" in eskf.lower(ev, x0, P0, IMU_NOISE).compile().as_text()


def scan_rate(duration, repeats, store="diag"):
    """IMU samples per second of the float64 single-stream scan."""
    rec, ev, x0 = _recording(jax.random.PRNGKey(0), duration)
    dt = _time(lambda: eskf(ev, x0, P0, IMU_NOISE, store=store).x.p, repeats)
    return int(rec.imu.t.shape[0]) / dt


def scan_rate_without_small_loops(duration, repeats):
    """:func:`scan_rate` in a fresh interpreter with the small-loop option off."""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["JAXTRAJ_XLA_SMALL_LOOPS"] = "0"
    cmd = [sys.executable, __file__, "--rate-only", str(duration), str(repeats)]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    return float(out.stdout.split()[-1])


def throughput(duration, numpy_duration, streams, repeats):
    rec, ev, x0 = _recording(jax.random.PRNGKey(0), duration)
    n_imu = int(rec.imu.t.shape[0])
    rows = []

    # NumPy loop on a prefix of the same stream
    n_np = int(np.searchsorted(np.asarray(ev.t), numpy_duration))
    prefix = jax.tree_util.tree_map(lambda a: a[:n_np], ev)
    t0 = time.perf_counter()
    ref, _ = eskf_numpy(prefix, x0, P0, IMU_NOISE)
    t_np = time.perf_counter() - t0
    imu_np = int(np.sum(np.asarray(prefix.kind) == 0))
    np_rate = imu_np / t_np
    jx = eskf(prefix, x0, P0, IMU_NOISE)
    agree = float(np.max(np.abs(np.asarray(jx.x.p) - ref["p"])))
    rows.append(("NumPy loop (float64, 1 stream)", np_rate, 1.0))

    for dtype, name in ((jnp.float64, "float64"), (jnp.float32, "float32")):
        e, x, P = _cast((ev, x0, P0), dtype)
        for store in ("full", "diag"):
            dt = _time(
                lambda e=e, x=x, P=P, s=store: eskf(e, x, P, IMU_NOISE, store=s).x.p, repeats
            )
            rows.append(
                (f"jax scan, {name}, 1 stream, store={store}", n_imu / dt, n_imu / dt / np_rate)
            )
    rate = scan_rate_without_small_loops(duration, repeats)
    rows.append(
        (
            "jax scan, float64, 1 stream, store=diag, small-loop option off (op-by-op dispatch)",
            rate,
            rate / np_rate,
        )
    )
    dt = _time(lambda: rts_smoother(eskf(ev, x0, P0, IMU_NOISE), IMU_NOISE).x.p, repeats)
    rows.append(("jax filter + RTS smoother, float64, 1 stream", n_imu / dt, n_imu / dt / np_rate))

    keys = jax.random.split(jax.random.PRNGKey(1), streams)
    evs, x0s = jax.vmap(lambda k: _recording(k, duration)[1:])(keys)
    for dtype, name in ((jnp.float64, "float64"), (jnp.float32, "float32")):
        e, x, P = _cast((evs, x0s, P0), dtype)
        run = jax.jit(jax.vmap(lambda e, x, P=P: eskf(e, x, P, IMU_NOISE, store="diag").x.p))
        dt = _time(lambda run=run, e=e, x=x: run(e, x), max(1, repeats // 2))
        rate = streams * n_imu / dt
        rows.append(
            (f"jax scan, {name}, {streams} streams, plain vmap, total", rate, rate / np_rate)
        )
        dt = _time(
            lambda e=e, x=x, P=P: eskf_batch(e, x, P, IMU_NOISE, store="diag").x.p,
            max(1, repeats // 2),
        )
        rate = streams * n_imu / dt
        rows.append(
            (f"jax scan, {name}, {streams} streams, eskf_batch, total", rate, rate / np_rate)
        )
    events_per_imu = ev.t.shape[0] / n_imu
    return rows, agree, n_imu, events_per_imu, imu_np, one_kernel(ev, x0)


def _rmse(p, q, p_ref, q_ref):
    e_p = np.sqrt(np.mean(np.sum((np.asarray(p) - np.asarray(p_ref)) ** 2, 1)))
    rv = jax.vmap(lambda a, b: (jaxlie.SO3(a).inverse() @ jaxlie.SO3(b)).log())(
        jnp.asarray(q), jnp.asarray(q_ref)
    )
    return e_p, np.sqrt(np.mean(np.sum(np.asarray(rv) ** 2, 1)))


def accuracy_simulated(duration):
    rec, ev, x0 = _recording(jax.random.PRNGKey(5), duration)
    res = eskf(ev, x0, P0, IMU_NOISE)
    sm = rts_smoother(res, IMU_NOISE)
    t_img = rec.image_times
    truth = true_states(TRAJ, t_img, rec.imu.t, rec.b_a, rec.b_g)
    robot_valid_t = rec.robot.t - rec.latency
    rows = []
    # robot poses alone: flange == IMU here (identity hand-eye), interpolated on SE(3)
    rows.append(
        (
            "robot poses, SE(3) interpolation",
            *_rmse(
                *interpolate_poses(robot_valid_t, rec.robot.p, rec.robot.q, t_img), truth.p, truth.q
            ),
        )
    )
    rows.append(
        (
            "ESKF (causal)",
            *_rmse(*interpolate_poses(res.t, res.x.p, res.x.q, t_img), truth.p, truth.q),
        )
    )
    rows.append(
        (
            "ESKF + RTS smoother",
            *_rmse(*interpolate_poses(sm.t, sm.x.p, sm.x.q, t_img), truth.p, truth.q),
        )
    )
    tr_all = true_states(TRAJ, ev.t, rec.imu.t, rec.b_a, rec.b_g)
    return rows, float(np.mean(np.asarray(nees(res, tr_all))))


def accuracy_euroc():
    from jaxtraj.io.euroc import ground_truth_as_robot, read_euroc

    folder = Path(
        os.environ.get(
            "JAXTRAJ_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"
        )
    )
    folder = folder / "euroc_v1_02_excerpt"
    if not folder.is_dir():
        return None
    rec = read_euroc(folder)
    noise = ImuNoise(0.04, 0.002, 3.0e-3, 1.9393e-5)  # ADIS16448 in flight, see tests
    robot, held = ground_truth_as_robot(rec, every=2, position_noise=1e-3, orientation_noise=2e-3)
    imu = ImuData(
        t=jnp.asarray(rec.imu_t), gyro=jnp.asarray(rec.gyro), accel=jnp.asarray(rec.accel)
    )
    t_held = rec.gt_t[held]
    ev = build_events(imu, robot, t_held, noise=RobotNoise(1e-3, 2e-3))
    res = eskf(ev, initial_state(ev), initial_covariance(0.05, 0.5, 0.1, 0.3, 0.05), noise)
    sm = rts_smoother(res, noise)
    ref = (rec.gt_p[held], rec.gt_q[held])
    rows = [
        (
            "robot poses (every 2nd GT, 1 mm / 2 mrad noise), interpolation",
            *_rmse(*interpolate_poses(robot.t, robot.p, robot.q, t_held), *ref),
        ),
        ("ESKF (causal)", *_rmse(*interpolate_poses(res.t, res.x.p, res.x.q, t_held), *ref)),
        ("ESKF + RTS smoother", *_rmse(*interpolate_poses(sm.t, sm.x.p, sm.x.q, t_held), *ref)),
    ]
    bias = (
        np.asarray(sm.x.b_g[-1]) - rec.gt_b_g[held[-1]],
        np.asarray(sm.x.b_a[-1]) - rec.gt_b_a[held[-1]],
    )
    return rows, bias, len(held)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="short streams, few repeats")
    ap.add_argument("--output", default=None, help="write the markdown report here")
    ap.add_argument("--rate-only", nargs=2, metavar=("SECONDS", "REPEATS"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.rate_only:
        print(scan_rate(float(args.rate_only[0]), int(args.rate_only[1])))
        return 0
    duration, np_dur, streams, repeats = (4.0, 1.0, 64, 3) if args.quick else (20.0, 4.0, 64, 5)

    rows, agree, n_imu, epi, imu_np, fused = throughput(duration, np_dur, streams, repeats)
    out = []
    out.append("# Fusion benchmark\n")
    out.append(
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPU(s), "
        f"jax {jax.__version__} on {jax.devices()[0].platform}. Stream: {duration:g} s at "
        f"{IMU_RATE:g} Hz IMU ({n_imu} samples), robot poses every 12 ms, images at 30 Hz "
        f"({epi:.2f} events per IMU sample). NumPy loop timed on the first {imu_np} IMU "
        f"samples; it agrees with the scan to {agree:.1e} m in position. Small-loop option "
        f"(XLA compiles the single-stream scan into one kernel): "
        f"{'active' if fused else 'NOT active'}.\n"
    )
    out.append("| implementation | IMU samples / s | real-time factor (250 Hz) | x NumPy |")
    out.append("|---|---:|---:|---:|")
    for name, rate, ratio in rows:
        out.append(f"| {name} | {rate:,.0f} | {rate / IMU_RATE:,.0f} | {ratio:,.1f} |")
    sim_rows, sim_nees = accuracy_simulated(duration)
    out.append(
        f"\n## Accuracy, simulated ({duration:g} s, Xsens MTi-class IMU, KUKA-class robot: "
        f"0.03 mm, 0.1 mrad, 4 ms latency), camera poses at the image times\n"
    )
    out.append("| estimate | position RMSE [mm] | orientation RMSE [mdeg] |")
    out.append("|---|---:|---:|")
    for name, ep, er in sim_rows:
        out.append(f"| {name} | {ep * 1e3:.4f} | {np.degrees(er) * 1e3:.2f} |")
    out.append(f"\nFilter NEES averaged over all events: {sim_nees:.1f} (15 expected).\n")
    eu = accuracy_euroc()
    if eu is None:
        out.append("\nEuRoC: data not found (../shared/data), skipped.\n")
    else:
        eu_rows, (d_bg, d_ba), n_held = eu
        out.append(
            f"\n## Accuracy, EuRoC V1_02 excerpt (real IMU), {n_held} held-back "
            "ground-truth poses\n"
        )
        out.append("| estimate | position RMSE [mm] | orientation RMSE [deg] |")
        out.append("|---|---:|---:|")
        for name, ep, er in eu_rows:
            out.append(f"| {name} | {ep * 1e3:.3f} | {np.degrees(er):.4f} |")
        out.append(
            f"\nFinal bias minus ground-truth column: gyro {np.array2string(d_bg, precision=5)} "
            f"rad/s, accel {np.array2string(d_ba, precision=4)} m/s^2.\n"
        )
    text = "\n".join(out)
    print(text)
    if args.output:
        Path(args.output).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

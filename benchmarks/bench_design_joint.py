"""Benchmark: joint-space camera-path design on the built-in cell (issue 21).

Designs the KR 16-2's joint path for the simulated cell of ``jaxtraj design --example``
(workpiece carried by a KR 60-3 along a smooth 3D curve) and reports: the design time
with compilation (first call), a warm re-plan (the prediction moved by 5 mm along every
axis, started from the design and its multipliers: with all starts, the design's shapes,
and with the best start alone, whose first call compiles and whose later calls, moved by
10 and 20 mm along every axis, are the warm figures, each with the first round's BFGS
started from the identity and from the design's inverse Hessian), convergence and
evaluations per start (largest violation, KKT stationarity), the expected mean error and
the constraints on a grid 10x finer.

With ``--compare``, designs the path once for each estimator (the paper's DCT with
k = 12 and the order-2 smoothness prior of ``estimate_points``) and measures every path,
the start weaves (smooth heuristics the KR 16 executes) included, by Monte-Carlo: noisy
pixels of every plausible workpiece trajectory (``--draws`` per trajectory, the cell's
pixel noise) reconstructed by ``estimate_points`` and by the DCT (``reconstruct``, k = 12).
``--scenes sim,cmu131_01,cmu131_03`` repeats this with the workpiece on the shared
motion-capture takes' root paths (scaled by 0.25 to the workpiece robot's reach, 8 s) and
ends with the issue's two ratios per scene: the design for ``estimate_points`` against the
best joint weave (target >= 3x) and against the random discontinuous camera (target <= 1).

The random camera's rows say how far the KR 16 is from following it (inverse kinematics
per image: images out of reach, or the jumps' speed and acceleration as multiples of the
joint limits), and a second reference keeps it within the robot's reach (per image the
first reachable of 32 draws). ``--limits-sweep 1,2,4`` designs for ``estimate_points``
with the ``--swept`` limits (default acceleration and jerk) scaled by each factor, against
both random cameras: what separates the design from the paper's camera.

Usage::

    python benchmarks/bench_design_joint.py [--frames 60] [--starts 8] [--inner-steps 500]
        [--replans N [--replan-move 10]] [--replan-penalty 30] [--n-control 12]
        [--estimator dct|smoother1|smoother2|pose] [--out OUT/]
        [--compare [--draws 200] [--scenes sim,cmu131_01,cmu131_03]]
        [--limits-sweep 1,2,4 [--swept velocity,acceleration,jerk] [--scenes ...]]

``--estimator pose`` designs for the known-layout pose (the simulated workpiece's six
marker centres, error of its assembly point) and checks the prediction against ``--draws``
Monte-Carlo runs per image of OpenCV's SQPnP + LM with the designed cameras.

Float64 is enabled below (a benchmark script may do so; library code never does).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxtraj import Status, dct_basis, estimate_points, reconstruct_points  # noqa: E402
from jaxtraj.design.joint_optimise import (  # noqa: E402
    REPLAN_PENALTY,
    design_joint_path,
    evaluate_joint_path,
)
from jaxtraj.design.joint_path import camera_poses, projection_matrices  # noqa: E402
from jaxtraj.design.objectives import project_points  # noqa: E402
from jaxtraj.design_command import (  # noqa: E402
    _initial_guesses,
    design_cell,
    example_cell,
    example_layout,
    write_design,
)


def monte_carlo(P, samples, times, pixel_sigma, draws, seed=0):
    """Mean Euclidean error [m] of estimate_points and of the DCT (k = 12) over ``draws``
    noisy pixel sets per sample trajectory, and estimate_points' share of flagged tracks."""
    key = jax.random.PRNGKey(seed)
    basis = dct_basis(times - times[0], 12)
    ep, dct, flagged = [], [], []
    for x in samples:
        key, sub = jax.random.split(key)
        uv = project_points(P, x)[None] + pixel_sigma * jax.random.normal(
            sub, (draws, x.shape[0], 2), P.dtype
        )
        est = estimate_points(P, uv, times, pixel_sigma=pixel_sigma)
        rec = reconstruct_points(P, uv, basis)
        ep.append(np.linalg.norm(np.asarray(est.points) - np.asarray(x)[None], axis=-1).mean())
        dct.append(np.linalg.norm(np.asarray(rec.points) - np.asarray(x)[None], axis=-1).mean())
        flagged.append(np.mean(np.asarray(est.status) != Status.OK))
    return float(np.mean(ep)), float(np.mean(dct)), float(np.mean(flagged))


def monte_carlo_pnp(T_w_c, K, predicted, layout, pixel_sigma, draws, seed=0):
    """Mean and RMS error [m] of the followed object point from OpenCV's SQPnP + LM on
    ``draws`` noisy pixel sets per image (exact cameras, the predicted trajectory)."""
    import cv2

    points, point, R_w_o = (np.asarray(a, float) for a in layout)
    rng = np.random.default_rng(seed)
    K = np.asarray(K, float)
    errors = []
    for T, x in zip(np.asarray(T_w_c), np.asarray(predicted), strict=True):
        R_c_w, c = T[:3, :3].T, T[:3, 3]
        X_c = (points @ R_w_o.T + (x - R_w_o @ point) - c) @ R_c_w.T @ K.T
        clean = X_c[:, :2] / X_c[:, 2:]
        for _ in range(draws):
            uv = clean + pixel_sigma * rng.normal(size=clean.shape)
            _, rvec, tvec = cv2.solvePnP(points, uv, K, None, flags=cv2.SOLVEPNP_SQPNP)
            rvec, tvec = cv2.solvePnPRefineLM(points, uv, K, None, rvec, tvec)
            a_w = R_c_w.T @ (cv2.Rodrigues(rvec)[0] @ point + tvec.ravel()) + c
            errors.append(np.linalg.norm(a_w - x))
    e = np.asarray(errors)
    return float(e.mean()), float(np.sqrt(np.mean(e**2)))


#: the shared motion-capture takes used as workpiece paths (``--compare --scenes``)
MOCAP = {"cmu131_01": "scaled_131_01.bvh", "cmu131_03": "scaled_131_03.bvh"}
#: their root paths span 2.7-3.1 m at up to 2 m/s (a person walking); scaled by this factor
#: (spans of 0.7-0.8 m, up to 0.5 m/s) they fit the workpiece robot's reach
MOCAP_SCALE = 0.25
MOCAP_SECONDS = 8.0  # both takes are at least this long


#: the shared reference data beside the checkout
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def scene_cell(scene: str, frames: int, starts: int, data: Path = DATA):
    """The built-in cell with the workpiece path of ``scene``: ``sim`` (the KR 60's smooth
    curve) or a motion-capture take's root path (scaled by :data:`MOCAP_SCALE`, centred
    on the built-in path's mean, over :data:`MOCAP_SECONDS`); None when the take is
    absent (``data/cmu_bvh``)."""
    from jaxtraj.sim import bvh_curve

    spec = example_cell(frames=frames, starts=starts)
    if scene == "sim":
        return spec
    path = Path(data) / "cmu_bvh" / MOCAP[scene]
    if not path.exists():
        print(f"{path} not found: scene {scene} skipped", flush=True)
        return None
    times = np.linspace(0.0, MOCAP_SECONDS, frames)
    x = bvh_curve(path, times=times, centre=(0.0, 0.0, 0.0))
    spec.times = times
    spec.predicted = MOCAP_SCALE * x + spec.predicted.mean(axis=0)
    spec.camera_start = spec.predicted[0] + np.array([-0.9, 0.0, 0.35])
    return spec


def checked_scenes(args) -> list[str]:
    """The names of ``--scenes`` (an unknown one exits with a message)."""
    scenes = args.scenes.split(",")
    for scene in scenes:
        if scene != "sim" and scene not in MOCAP:
            raise SystemExit(f"--scenes: unknown scene {scene!r} (sim, {', '.join(MOCAP)})")
    return scenes


def scene_specs(args, scenes):
    """``(scene, spec)`` per scene whose data is present, with ``--n-control`` applied."""
    for scene in scenes:
        spec = scene_cell(scene, args.frames, args.starts)
        if spec is not None:
            spec.n_control = args.n_control
            yield scene, spec


def compare(args) -> int:
    """Per scene: design for each estimator and measure every path with both estimators."""
    scenes = checked_scenes(args)
    estimators = args.estimators.split(",")
    for e in estimators:
        if e not in ("temporal", "pose"):
            raise SystemExit(f"--estimators: unknown {e!r} (temporal, pose)")
    summary = []
    for scene, spec in scene_specs(args, scenes):
        if "temporal" in estimators:
            summary.append(("estimate_points", *compare_scene(args, scene, spec)))
        if "pose" in estimators:
            summary.append(("known-layout pose", *compare_pose_scene(args, scene, spec)))
    print(
        "\n| scene | estimator | designed for it [mm] | best weave [mm] | ratio (target >= 3) "
        "| random discontinuous [mm] | designed / random (target <= 1) | random within reach "
        "[mm] | designed / random within reach |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for estimator, scene, designed, weave, random_, reach in summary:
        print(
            f"| {scene} | {estimator} | {designed:.3g} | {weave:.3g} | {weave / designed:.2g}x | "
            f"{random_:.3g} | {designed / random_:.2g} | {reach:.3g} | {designed / reach:.2g} |"
        )
    return 0


def random_camera(spec, key=None):
    """The paper's random discontinuous camera about the scene's prediction (drawn with
    ``key``, default the scene's seed): ``(P, T_w_c)``."""
    from jaxtraj import projection_matrix
    from jaxtraj.sim import random_discontinuous_camera

    key = jax.random.PRNGKey(spec.seed) if key is None else key
    path = random_discontinuous_camera(key, jnp.asarray(spec.predicted), standoff=spec.standoff)
    K = jnp.asarray(spec.K)
    P = jax.vmap(lambda R, t: projection_matrix(K, R, t))(path.R_c_w, path.t_c_w)
    T_w_c = jnp.zeros((P.shape[0], 4, 4), P.dtype).at[:, 3, 3].set(1.0)
    T_w_c = T_w_c.at[:, :3, :3].set(jnp.swapaxes(path.R_c_w, 1, 2))
    return P, T_w_c.at[:, :3, 3].set(path.centres)


def flange_poses(cell, T_w_c):
    """Flange poses in the robot's base frame (..., 4, 4) for camera poses ``T_w_c``."""
    inv = np.linalg.inv
    return inv(np.asarray(cell.T_w_base)) @ np.asarray(T_w_c) @ inv(np.asarray(cell.T_f_c))


def joint_excess(spec, cell, q_start, T_w_c):
    """How far the KR 16 is from following the cameras ``T_w_c`` (F, 4, 4): inverse
    kinematics of every image's camera pose (each from the last reached image's solution,
    the nearest branch); returns (images out of reach or outside the joint ranges, the
    largest joint speed the jumps between consecutive reached images ask for as a
    multiple of that joint's limit, the median over those jumps of their largest, the
    largest joint acceleration, from second differences over three consecutive reached
    images, as a multiple of that joint's limit)."""
    from jaxtraj.robot.ik import inverse_kinematics

    chain = cell.chain
    q, qs, reached = np.asarray(q_start), [], []
    for T in flange_poses(cell, T_w_c):
        r = inverse_kinematics(chain, T, q, position_tol=1e-6, rotation_tol=1e-6)
        reached.append(bool(r.success))
        if r.success:
            q = np.asarray(r.q)
        qs.append(q)
    qs, reached = np.asarray(qs), np.asarray(reached)
    both = reached[1:] & reached[:-1]
    nan = float("nan")
    if not np.any(both):
        return int(np.sum(~reached)), nan, nan, nan
    dt = np.diff(np.asarray(spec.times))
    v = np.diff(qs, axis=0) / dt[:, None]
    worst = np.max(np.abs(v[both]) / np.asarray(chain.velocity)[None], axis=1)
    three = both[1:] & both[:-1]
    acc = np.abs(np.diff(v, axis=0)) / (0.5 * (dt[1:] + dt[:-1]))[:, None]
    acc = acc / np.asarray(chain.acceleration)[None]
    worst_acc = float(np.max(acc[three])) if np.any(three) else nan
    return int(np.sum(~reached)), float(np.max(worst)), float(np.median(worst)), worst_acc


def excess_text(excess, frames: int) -> str:
    """``joint_excess`` in words, for the tables' "within limits" column."""
    out, worst, median, acc = excess
    if out:
        return f"no: {out} of {frames} images out of reach"
    verdict = "no" if max(worst, acc) > 1.0 else "reached; the jumps within the limits"
    return (
        f"{verdict}: jumps at up to {worst:.1f}x a joint's speed limit (median "
        f"{median:.1f}x) and {acc:.1f}x its acceleration limit (second differences)"
    )


def random_reachable_camera(spec, cell, q_start, candidates=32):
    """The random discontinuous camera kept inside the KR 16's reach: per image the first
    of ``candidates`` draws (same distribution as :func:`random_camera`) whose camera
    pose the robot reaches within its joint limits; ``(P, T_w_c, reached)`` with
    ``reached`` the images where some draw was reachable (the others keep the first draw).
    A comparison that ignores only the speed of the jumps, not where the camera can be."""
    from jaxtraj.robot.ik import inverse_kinematics

    keys = jax.random.split(jax.random.PRNGKey(spec.seed + 1), candidates)
    P, T_w_c = (jnp.stack(a) for a in zip(*(random_camera(spec, k) for k in keys), strict=True))
    ik = jax.jit(
        jax.vmap(
            lambda T: (
                inverse_kinematics(
                    cell.chain, T, jnp.asarray(q_start), position_tol=1e-6, rotation_tol=1e-6
                ).success
            )
        )
    )
    T_base_f = jnp.asarray(flange_poses(cell, T_w_c)).reshape(-1, 4, 4)
    ok = np.asarray(ik(T_base_f)).reshape(P.shape[:2])  # (candidates, F)
    pick = np.argmax(ok, axis=0)
    frames = np.arange(P.shape[1])
    return P[pick, frames], T_w_c[pick, frames], ok[pick, frames]


def use_known_layout(spec):
    """Design ``spec`` for the known-layout pose: the simulated workpiece's six marker
    centres and its assembly point."""
    spec.method = "pose"
    spec.layout, spec.point = example_layout()


def start_weaves(res, spec, starts):
    """The design's start weaves by name (the smooth heuristics the KR 16 executes)."""
    weaves = jnp.asarray(_initial_guesses(res["model"], res["chain"], starts, spec.seed))
    return {f"joint weave {i} (start {i})": theta for i, theta in enumerate(weaves)}


def compare_pose_scene(args, scene, spec):
    """Known-layout pose on one scene: the path designed for it, the start weaves and the
    random discontinuous camera (also kept within reach), each measured by Monte-Carlo of
    OpenCV's SQPnP + LM (``--draws`` per image, the predicted trajectory); returns (scene,
    designed, best weave, random, random within reach) mean errors [mm] of the followed
    point."""
    use_known_layout(spec)
    res = design_cell(spec, inner_steps=args.inner_steps)
    best, designs = res["best"], res["designs"]
    print(
        f"[{scene}] designed for the known-layout pose: {res['seconds']:.1f} s with "
        f"compilation, converged {np.asarray(designs.converged).tolist()}, rounds "
        f"{np.asarray(designs.rounds).tolist()}",
        flush=True,
    )
    model, cell = res["model"], res["cell"]
    layout = res["layout"]
    paths = {"designed for the known-layout pose": best.theta}
    paths.update(start_weaves(res, spec, args.starts))
    rows, measured = [], {}
    for name, theta in paths.items():
        ev = evaluate_joint_path(
            model,
            jnp.asarray(theta)[None],
            cell,
            spec.predicted,
            res["samples"],
            res["basis"],
            estimator="pose",
            layout=layout,
            pixel_sigma=spec.pixel_sigma,
        )
        T_w_c = camera_poses(cell, model.joints_at_images(theta))
        mean, _ = monte_carlo_pnp(
            T_w_c, spec.K, spec.predicted, layout, spec.pixel_sigma, args.draws
        )
        measured[name] = 1000 * mean
        rows.append(
            f"| {name} | {'yes' if bool(ev.feasible[0]) else 'no'} | "
            f"{1000 * float(ev.expected_mean_error[0]):.3g} | {1000 * mean:.3g} |"
        )
        print(rows[-1], flush=True)
    from jaxtraj.design import expected_pose_errors_for_cameras

    q_start = np.asarray(model.q0)
    points, point, R_w_o = layout
    randoms = {}
    for name, (P, T_w_c) in (
        ("random discontinuous (paper)", random_camera(spec)),
        ("random discontinuous within reach", random_reachable_camera(spec, cell, q_start)[:2]),
    ):
        _, expected = expected_pose_errors_for_cameras(
            P, res["samples"], R_w_o, points, point, spec.pixel_sigma
        )
        mean, _ = monte_carlo_pnp(
            T_w_c, spec.K, spec.predicted, layout, spec.pixel_sigma, args.draws
        )
        randoms[name] = 1000 * mean
        limits = excess_text(joint_excess(spec, cell, q_start, T_w_c), T_w_c.shape[0])
        rows.append(f"| {name} | {limits} | {1000 * float(expected):.3g} | {1000 * mean:.3g} |")
        print(rows[-1], flush=True)
    print(
        f"\n[{scene}] known-layout pose (six marker centres, assembly point), F = "
        f"{args.frames}, {args.starts} starts, {args.inner_steps} BFGS steps per round, "
        f"{args.draws} draws per image, {spec.pixel_sigma} px\n"
    )
    print("| camera path | within limits | expected mean [mm] | PnP simulated mean [mm] |")
    print("|---|---|---|---|")
    print("\n".join(rows), flush=True)
    best_weave = min(v for k, v in measured.items() if k.startswith("joint weave"))
    return (
        scene,
        measured["designed for the known-layout pose"],
        best_weave,
        randoms["random discontinuous (paper)"],
        randoms["random discontinuous within reach"],
    )


def compare_scene(args, scene, spec):
    """The table of one scene; returns (scene, designed-for-smoother error, best weave
    error, random camera error, random camera within reach error) as measured with
    ``estimate_points`` [mm]."""
    rows = []
    results = {}
    for estimator in ("dct", "smoother2"):
        if estimator != "dct":
            spec.method, spec.order = "smoother", 2
        results[estimator] = res = design_cell(spec, inner_steps=args.inner_steps)
        print(
            f"[{scene}] designed for {estimator}: {res['seconds']:.1f} s with compilation, "
            f"converged {np.asarray(res['designs'].converged).tolist()}, rounds "
            f"{np.asarray(res['designs'].rounds).tolist()}",
            flush=True,
        )
    res = results["dct"]
    model, cell, samples = res["model"], res["cell"], res["samples"]
    times = jnp.asarray(spec.times)
    paths = {f"designed for {e}": r["best"].theta for e, r in results.items()}
    paths.update(start_weaves(res, spec, args.starts))
    measured = {}
    for name, theta in paths.items():
        thetas = jnp.asarray(theta)[None]
        report = {
            e: evaluate_joint_path(
                model,
                thetas,
                cell,
                spec.predicted,
                samples,
                res["basis"],
                estimator=e,
                pixel_sigma=spec.pixel_sigma,
            )
            for e in ("dct", "smoother2")
        }
        P = projection_matrices(cell, camera_poses(cell, model.joints_at_images(theta)))
        ep, dct, flagged = monte_carlo(P, samples, times, spec.pixel_sigma, args.draws)
        measured[name] = 1000 * ep
        rows.append(
            f"| {name} | {'yes' if bool(report['dct'].feasible[0]) else 'no'} | "
            f"{1000 * float(report['dct'].expected_mean_error[0]):.3g} | {1000 * dct:.3g} | "
            f"{1000 * float(report['smoother2'].expected_mean_error[0]):.3g} | "
            f"{1000 * ep:.3g} | {100 * flagged:.0f} % |"
        )
        print(rows[-1], flush=True)
    # the paper's random discontinuous camera (no robot path: jumps between images), and
    # the same kept inside the KR 16's reach (only the jumps' speed ignored)
    from jaxtraj.design import expected_errors_for_cameras, expected_smoother_errors_for_cameras

    q_start = np.asarray(model.q0)
    P_r, T_r = random_camera(spec)
    P_n, T_n, _ = random_reachable_camera(spec, cell, q_start)
    randoms = {}
    for name, P, T in (
        ("random discontinuous (paper)", P_r, T_r),
        ("random discontinuous within reach", P_n, T_n),
    ):
        _, dct_expected = expected_errors_for_cameras(P, samples, res["basis"], spec.pixel_sigma)
        _, sm_expected = expected_smoother_errors_for_cameras(P, samples, times, spec.pixel_sigma)
        ep, dct, flagged = monte_carlo(P, samples, times, spec.pixel_sigma, args.draws)
        randoms[name] = 1000 * ep
        limits = excess_text(joint_excess(spec, cell, q_start, T), T.shape[0])
        rows.append(
            f"| {name} | {limits} | {1000 * float(dct_expected):.3g} | "
            f"{1000 * dct:.3g} | {1000 * float(sm_expected):.3g} | {1000 * ep:.3g} | "
            f"{100 * flagged:.0f} % |"
        )
        print(rows[-1], flush=True)
    print(
        f"\n[{scene}] F = {args.frames}, {args.starts} starts, {spec.n_control} control points "
        f"per joint, {args.inner_steps} BFGS steps "
        f"per round, {samples.shape[0]} workpiece trajectories x {args.draws} draws, "
        f"{spec.pixel_sigma} px\n"
    )
    print(
        "| camera path | within limits | DCT k=12 expected [mm] | DCT k=12 simulated [mm] | "
        "smoother expected [mm] | estimate_points simulated [mm] | flagged |"
    )
    print("|---|---|---|---|---|---|---|")
    print("\n".join(rows), flush=True)
    best_weave = min(v for k, v in measured.items() if k.startswith("joint weave"))
    return (
        scene,
        measured["designed for smoother2"],
        best_weave,
        randoms["random discontinuous (paper)"],
        randoms["random discontinuous within reach"],
    )


def limits_sweep(args) -> int:
    """Per scene and factor: the path designed for ``estimate_points`` with the KR 16's
    ``--swept`` limits (by default acceleration and jerk, assumed defaults: the datasheet
    gives neither) scaled by the factor, measured by Monte-Carlo against the random
    discontinuous camera and the same kept within the robot's reach."""
    from jaxtraj.io.urdf import load_robot

    factors = [float(f) for f in args.limits_sweep.split(",")]
    swept = args.swept.split(",")
    for name in swept:
        if name not in ("velocity", "acceleration", "jerk"):
            raise SystemExit(f"--swept: unknown limit {name!r} (velocity, acceleration, jerk)")
    rows = []
    for scene, spec in scene_specs(args, checked_scenes(args)):
        spec.method, spec.order = "smoother", 2
        chain = load_robot(spec.robot)
        times = jnp.asarray(spec.times)
        for factor in factors:
            for name in swept:
                setattr(spec, name, factor * np.asarray(getattr(chain, name)))
            res = design_cell(spec, inner_steps=args.inner_steps)
            best, designs = res["best"], res["designs"]
            if factor == factors[0]:
                q_start = np.asarray(res["model"].q0)
                P_n = random_reachable_camera(spec, res["cell"], q_start)[0]
                random_, reach = (
                    monte_carlo(P, res["samples"], times, spec.pixel_sigma, args.draws)[0]
                    for P in (random_camera(spec)[0], P_n)
                )
            cams = projection_matrices(
                res["cell"], camera_poses(res["cell"], res["model"].joints_at_images(best.theta))
            )
            ep, _, flagged = monte_carlo(cams, res["samples"], times, spec.pixel_sigma, args.draws)
            active = [k for k, v in best.report().items() if v["active"]]
            rows.append(
                f"| {scene} | {factor:g}x | {int(np.sum(designs.converged))} of {args.starts} | "
                f"{'yes' if bool(best.feasible) else 'no'} | "
                f"{1000 * float(best.expected_mean_error):.3g} / {1000 * ep:.3g} | "
                f"{100 * flagged:.0f} % | {1000 * random_:.3g} | {ep / random_:.2g} | "
                f"{1000 * reach:.3g} | {ep / reach:.2g} | "
                f"{', '.join(active)} | {res['seconds']:.0f} s |"
            )
            print(rows[-1], flush=True)
    print(
        f"\nF = {args.frames}, {args.starts} starts, {args.n_control} B-spline control "
        f"points per joint, {args.draws} draws per plausible "
        f"trajectory; the {' and '.join(swept)} limits of every joint scaled, the others as "
        "shipped\n"
    )
    print(
        f"| scene | {' and '.join(swept)} limits | converged | feasible | estimate_points "
        "expected / simulated [mm] | flagged | random discontinuous [mm] | designed / random "
        "| random within reach [mm] | designed / random within reach | active constraints "
        "| design time |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows), flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument(
        "--n-control",
        type=int,
        default=12,
        help="B-spline control points per joint (default 12, the cell's)",
    )
    parser.add_argument("--starts", type=int, default=8)
    parser.add_argument("--inner-steps", type=int, default=500)
    parser.add_argument(
        "--replan-penalty",
        type=float,
        default=REPLAN_PENALTY,
        help="penalty of every round of the warm re-plans (100 in the figures before "
        "2026-12-06's last)",
    )
    parser.add_argument(
        "--replans",
        type=int,
        default=0,
        metavar="N",
        help="N more one-start warm re-plans, the prediction moved by --replan-move in a "
        "random direction each, from the identity and from the design's inverse Hessian",
    )
    parser.add_argument(
        "--replan-move",
        type=float,
        default=10.0,
        metavar="MM",
        help="length of the --replans moves [mm] (default 10)",
    )
    parser.add_argument(
        "--estimator",
        choices=("dct", "smoother1", "smoother2", "pose"),
        default="dct",
        help="the estimator whose expected error is minimised",
    )
    parser.add_argument("--out", default=None, help="also write the design's files here")
    parser.add_argument("--compare", action="store_true", help="design for each estimator")
    parser.add_argument("--draws", type=int, default=200, help="Monte-Carlo draws (--compare)")
    parser.add_argument(
        "--scenes",
        default="sim",
        help="--compare: comma-separated workpiece paths: sim, cmu131_01, cmu131_03",
    )
    parser.add_argument(
        "--estimators",
        default="temporal",
        help="--compare: 'temporal' (designs for the DCT and estimate_points, both measured), "
        "'pose' (the known-layout pose, measured by OpenCV PnP), or both comma-separated",
    )
    parser.add_argument(
        "--limits-sweep",
        default=None,
        metavar="FACTORS",
        help="design for estimate_points on --scenes with the acceleration and jerk limits "
        "scaled by each comma-separated factor (e.g. 1,2,4,8), against the random camera",
    )
    parser.add_argument(
        "--swept",
        default="acceleration,jerk",
        help="--limits-sweep: the limits scaled, comma-separated (velocity, acceleration, jerk)",
    )
    args = parser.parse_args(argv)
    if args.limits_sweep:
        return limits_sweep(args)
    if args.compare:
        return compare(args)
    spec = example_cell(frames=args.frames, starts=args.starts)
    spec.n_control = args.n_control
    if args.estimator == "pose":
        use_known_layout(spec)
    elif args.estimator != "dct":
        spec.method, spec.order = "smoother", int(args.estimator[-1])
    res = design_cell(spec, inner_steps=args.inner_steps)
    best, designs = res["best"], res["designs"]
    print(f"design with compilation: {res['seconds']:.1f} s")
    print(
        f"best: expected mean error {1000 * float(best.expected_mean_error):.2f} mm, "
        f"max violation {float(best.max_violation):.1e}, stationarity "
        f"{float(best.stationarity):.1e}, converged {bool(best.converged)}"
    )
    print("per start: converged", np.asarray(designs.converged).tolist())
    print("  ALM rounds", np.asarray(designs.rounds).tolist())
    print("  stationarity", np.asarray(designs.stationarity).round(5).tolist())
    print("  max violation", np.asarray(designs.max_violation).round(5).tolist())
    print("  mean error [mm]", (1000 * np.asarray(designs.expected_mean_error)).round(2).tolist())
    print("10x finer grid, largest value per constraint:", res["fine_violation"])
    if args.out:
        write_design(args.out, spec, res)
    if args.estimator == "pose":
        T_w_c = camera_poses(res["cell"], res["model"].joints_at_images(best.theta))
        mean, rms = monte_carlo_pnp(
            T_w_c, spec.K, spec.predicted, res["layout"], spec.pixel_sigma, args.draws
        )
        print(
            f"Monte-Carlo (OpenCV SQPnP + LM, {args.draws} draws x {args.frames} images, "
            f"{spec.pixel_sigma} px): mean {1000 * mean:.3f} mm, RMS {1000 * rms:.3f} mm; "
            f"predicted mean {1000 * float(best.expected_mean_error):.3f} mm, RMS "
            f"{1000 * float(best.expected_error):.3f} mm"
        )
    # warm re-plan: the best design and its multipliers, every round at --replan-penalty, all
    # starts (the design's shapes) and with the best one alone (the first call compiles);
    # the one-start re-plans with the BFGS started from the identity and from the design's
    # inverse Hessian, alternated, each moved by 10 mm and then by 20 mm along every axis
    print("per start: evaluations", np.asarray(designs.evaluations).tolist())
    for label, b, shifts, warm_h in (
        ("all starts", args.starts, (0.005,), True),
        ("one start", 1, (0.005,), True),
        ("one start, BFGS from the identity", 1, (0.01,), False),
        ("one start, BFGS from the design's inverse Hessian", 1, (0.01,), True),
        ("one start, BFGS from the identity", 1, (0.02,), False),
        ("one start, BFGS from the design's inverse Hessian", 1, (0.02,), True),
    ):
        for shift in shifts:
            warm, seconds = _replan(args, spec, res, best, shift, warm_h, b)
            print(
                f"warm re-plan, {label} (prediction moved by {1000 * shift:.0f} mm along each "
                f"axis, {1000 * shift * 3**0.5:.1f} mm in all, from the design and its "
                f"multipliers): {seconds:.2f} s, expected mean "
                f"error {1000 * float(warm.expected_mean_error):.2f} mm, stationarity "
                f"{float(warm.stationarity):.1e}, converged {bool(warm.converged)}, "
                f"{int(warm.rounds)} round(s), {int(warm.evaluations)} evaluations",
                flush=True,
            )
    if args.replans:
        replan_spread(args, spec, res, best)
    return 0


def _replan(args, spec, res, best, move, warm_h: bool, b: int = 1):
    """One warm re-plan of ``b`` copies of the best design, the prediction and samples
    moved by ``move`` [m], the BFGS from the design's inverse Hessian if ``warm_h``;
    returns the design and the seconds it took."""
    t0 = time.perf_counter()
    warm, _ = design_joint_path(
        res["model"],
        res["cell"],
        spec.predicted + move,
        res["samples"] + move,
        res["basis"],
        jnp.stack([best.theta] * b),
        multipliers=jnp.stack([best.multipliers] * b),
        inverse_hessian=jnp.stack([best.inverse_hessian] * b) if warm_h else None,
        objective=spec.objective,
        estimator=args.estimator,
        layout=res["layout"],
        pixel_sigma=spec.pixel_sigma,
        penalties=(args.replan_penalty,) * 8,  # as many as the design's: no recompilation
        inner_steps=args.inner_steps,
    )
    warm.theta.block_until_ready()
    return warm, time.perf_counter() - t0


def replan_spread(args, spec, res, best) -> None:
    """``--replans N``: one-start warm re-plans, each with the prediction moved by
    ``--replan-move`` mm in a random direction, alternating the BFGS start (identity, the
    design's inverse Hessian); prints each and the median and largest time of each start."""
    rng = np.random.default_rng(0)
    times = {False: [], True: []}
    for i in range(args.replans):
        d = rng.normal(size=3)
        move = jnp.asarray(1e-3 * args.replan_move * d / np.linalg.norm(d))
        for warm_h in (False, True):
            warm, seconds = _replan(args, spec, res, best, move, warm_h)
            times[warm_h].append(seconds)
            print(
                f"re-plan {i} ({'inverse Hessian' if warm_h else 'identity'}): {seconds:.2f} s, "
                f"{int(warm.evaluations)} evaluations, {int(warm.rounds)} round(s), converged "
                f"{bool(warm.converged)}",
                flush=True,
            )
    for warm_h, label in ((False, "identity"), (True, "the design's inverse Hessian")):
        t = np.asarray(times[warm_h])
        print(
            f"{args.replans} re-plans from {label}: median {np.median(t):.2f} s, largest "
            f"{t.max():.2f} s, {int(np.sum(t <= 1.0))} within 1 s"
        )


if __name__ == "__main__":
    raise SystemExit(main())

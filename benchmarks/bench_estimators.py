"""Benchmark: estimators beyond the plain DCT on robot-cell scenes and motion capture.

For every camera mode (slow/smooth drift to an independent random pose per frame) and
workpiece source (simulated conveyor motion, CMU motion-capture root trajectories), it
reports the mean 3D error [mm] and the time per trajectory [ms] (batched, jit-compiled,
after warm-up) of: the plain DCT with fixed k, the DCT with k chosen by cross-validation,
the same refined by maximum likelihood, and the smoothness prior (noise density chosen
per scene by the marginal likelihood, and per point); the refinement is kept only where the
linear solve reports ``Status.OK``. A last row treats the points as markers of one rigid
body with a known layout (per-image PnP, then one rigid motion fitted to all pixels), the
pipeline's case, which a slow camera does not defeat. ``--stonesoup`` adds the peer of
issue 8, a Stone Soup UKF + unscented RTS smoother (constant velocity, known sensor poses),
compared with the jaxtraj smoother on the same points: each smoother's process noise is
tuned on separate scenes of the same kind (by their true error), and both get the same
start prior (the true first state, or one drawn from the prior); see :func:`peer_rows`.

``--paired`` runs only the filter against Stone Soup, point by point on the same scenes,
and reports the ratio of their errors with a 95 % confidence interval (see
:func:`paired`). ``--k-choice`` runs only the plain DCT at every k against the k chosen by
cross-validation, with the paired difference to the best fixed k (see :func:`k_choice`).

``--trust`` (issue 20) runs only the trust benchmark of :func:`estimate_points` against
every other per-point estimator, F = 150 at 30 Hz, on the simulated cell and the shared
CMU takes: cameras orbiting at 1-90 deg/frame (noise-free and 0.5 px), the robot-like
modes and a camera that follows the subject (see :func:`trust_cameras`); per cell the
mean error, the share flagged, the error and NEES of the trajectories reported OK, how
many trajectories more than 5 reported standard deviations off are flagged, and the
batched time per point, then a summary against the issue's targets. It writes
``results/estimators_trust.json`` after every cell (``--cells`` takes fnmatch patterns of
``source/camera/noise`` names, e.g. ``'sim/orbit1/*,*/random/*'``; defaults ``--scenes 2
--points 12``). ``--trust --alone`` estimates every track of the same scenes alone and
compares it with its estimate in the scene's batch: model, status and error must not
depend on the batch's size (exit 1 and the tracks listed if they do for a track reported
OK either way).

Run: ``python benchmarks/bench_estimators.py [--scenes 6] [--points 8] [--stonesoup]
[--tune-scenes 1] [--out results.json]``; ``--markdown results.json`` reprints the tables
(with ``--trust``, those of a trust JSON).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine_info, time_call  # noqa: E402
from _common import markdown_table as common_table  # noqa: E402

import jaxtraj as jt  # noqa: E402
from jaxtraj.estimators import (  # noqa: E402
    dct_covariance,
    estimate_points,
    filter_points,
    fit_rigid_trajectory,
    reconstruct_regularised,
    refine_points,
    regularised_covariance,
    roughness_penalty,
    select_k_cv,
    select_penalty_cv,
    select_process_psd,
    smooth_points,
)
from jaxtraj.pipeline.reconstruct import _pnp  # noqa: E402
from tests.test_estimators_scenes import (  # noqa: E402
    K640,
    camera_centres,
    cameras_looking_at,
    project_np,
    workpiece_path,
)

MODES = ("slow", "smooth", "fast", "random")
FIXED_K = (6, 8, 10, 12)
KS = tuple(range(4, 21, 2))
START_COV = np.diag([0.05**2] * 3 + [0.2**2] * 3)  # Stone Soup's start prior (see below)
PEER_QS = (0.003, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0)  # process-noise grid [m^2/s^3]
FILTER_RULES = ("cubature", "extended")
RIGID_K = 40  # DCT vectors of the rigid motion (20 leaves 3 mm of truncation error at F = 120)


def load_bvh_root(path: Path) -> tuple[np.ndarray, float]:
    """Root-joint positions (frames, 3) [m] and frame time [s] of a BVH file."""
    lines = path.read_text().splitlines()
    i = next(n for n, line in enumerate(lines) if line.strip() == "MOTION")
    dt = float(lines[i + 2].split(":")[1])
    data = np.array(
        [[float(v) for v in line.split()[:3]] for line in lines[i + 3 :] if line.strip()]
    )
    return data[:, [0, 2, 1]], dt  # BVH is y-up; the cell is z-up


def scene(rng, F, mode, noise, source, mocap=None):
    times = np.arange(F) / 100.0
    if source == "sim":
        X = workpiece_path(rng, times)
    else:
        pos, dt = mocap
        start = rng.integers(0, len(pos) - int(F * 0.01 / dt) - 2)
        t_src = np.arange(len(pos)) * dt
        X = np.stack([np.interp(times + start * dt, t_src, pos[:, a]) for a in range(3)], 1)
        X = X - X.mean(0) + np.array([0.0, 0.0, 0.8])
    C = camera_centres(rng, times, X, mode)
    P = cameras_looking_at(rng, C, X)
    return times, X, P


def points_around(rng, X, n):
    """n points of a rigid-ish workpiece: the path plus small fixed offsets (5 cm)."""
    return X[None] + rng.normal(size=(n, 1, 3)) * 0.05


def draw_points(rng, args, source, mode, mocap):
    """One scene of a cell and ``args.points`` points on its workpiece: times (F,), the
    workpiece path (F, 3), the points' true tracks (N, F, 3), cameras (F, 3, 4) and noisy
    pixels (N, F, 2), drawn from ``rng`` in this order (so every mode of the bench sees
    the same scenes for the same seed)."""
    times, X, P = scene(rng, args.frames, mode, args.noise, source, mocap)
    Xs = points_around(rng, X, args.points)
    uv = np.stack([project_np(P, x) for x in Xs])
    return times, X, Xs, P, uv + args.noise * rng.normal(size=uv.shape)


K_RULES = ("gain_weighted", "reprojection")  # the rules of select_k_cv


def k_choosers():
    """Per k rule, a compiled function (P, uv (N, F, 2), times) -> each point's k (N,)."""
    return {
        rule: jax.jit(
            jax.vmap(lambda P, u, t, r=rule: select_k_cv(P, u, t, KS, rule=r).k, (None, 0, None))
        )
        for rule in K_RULES
    }


def scene_k(chosen) -> int:
    """One k per scene: the median of the points' choices (which falls between two
    candidates when an even number of points splits evenly); 0 (no candidate admissible
    anywhere) gives the smallest candidate."""
    return int(np.median(np.asarray(chosen))) or KS[0]


BVH = ROOT.parent / "shared" / "data" / "cmu_bvh" / "scaled_131_01.bvh"


def sources_and_mocap():
    """The workpiece sources to run (the simulated cell, and motion capture where
    ``../shared/data`` has it) and the motion-capture root path (None without it)."""
    mocap = load_bvh_root(BVH) if BVH.exists() else None
    return ["sim"] + (["mocap"] if mocap is not None else []), mocap


def timed(fn, *args, repeat=2):
    out = fn(*args)
    jax.block_until_ready(out)
    t = time.perf_counter()
    for _ in range(repeat):
        out = fn(*args)
        jax.block_until_ready(out)
    return out, (time.perf_counter() - t) / repeat


def point_err_mm(est, X):
    """RMS 3D error of each trajectory [mm] (leading axes of ``est`` and ``X``)."""
    return 1e3 * np.sqrt(np.mean(np.sum((np.asarray(est) - X) ** 2, -1), -1))


def err_mm(est, X):
    return float(np.mean(point_err_mm(est, X)))


# The lambdas below are called at once inside the loop body (B023 does not apply).
def run(args):  # noqa: C901, RUF100
    rng = np.random.default_rng(args.seed)
    tune_rng = np.random.default_rng(args.seed + 1000)  # tuning scenes, never tested on
    peer_rng = np.random.default_rng(args.seed + 2000)  # drawn starts: same scenes either way
    sources, mocap = sources_and_mocap()
    F, noise, N = args.frames, args.noise, args.points
    results = []
    cv = k_choosers()
    for source in sources:
        for mode in MODES:
            acc: dict[str, list] = {}
            if args.stonesoup:  # q of both smoothers tuned on separate scenes (their truth)
                tuned = tune_q(tune_rng, args, source, mode, mocap)
                print(source, mode, "tuned q [m^2/s^3]:", tuned)
            for _ in range(args.scenes):
                times, X, Xs, P, uv = draw_points(rng, args, source, mode, mocap)
                for k in FIXED_K:
                    b = jt.dct_basis(times, k)
                    r, dt = timed(lambda u, b=b, P=P: jt.reconstruct_points(P, u, b).points, uv)
                    acc.setdefault(f"dct_k{k}", []).append((err_mm(r, Xs), dt / N))
                ks, dt_cv = timed(lambda u, P=P, t=times: cv["reprojection"](P, u, t), uv)
                b = jt.dct_basis(times, scene_k(ks))
                r = jt.reconstruct_points(P, uv, b).points
                acc.setdefault("dct_cv_k_reprojection", []).append((err_mm(r, Xs), dt_cv / N))
                ks, dt_cv = timed(lambda u, P=P, t=times: cv["gain_weighted"](P, u, t), uv)
                b = jt.dct_basis(times, scene_k(ks))
                lin = jt.reconstruct_points(P, uv, b)
                acc.setdefault("dct_cv_k", []).append((err_mm(lin.points, Xs), dt_cv / N))
                # refined where the linear solve is trustworthy (status OK): on a flat
                # likelihood (a degenerate, flagged start) the optimiser lowers the cost
                # by moving the point metres along the ray, so refine_points keeps it
                ref, dt_r = timed(
                    lambda u, P=P, b=b, c=lin.coeffs, st=lin.status: (
                        refine_points(P, u, b, c, status=st, pixel_sigma=noise).points
                    ),
                    uv,
                )
                acc.setdefault("dct_cv_k_refined", []).append((err_mm(ref, Xs), (dt_cv + dt_r) / N))
                q, dt_q = timed(
                    lambda u, P=P, t=times: select_process_psd(P, u, t, pixel_sigma=noise), uv
                )
                sm, dt_s = timed(
                    lambda u, P=P, t=times, q=float(q): (
                        smooth_points(
                            P, u, t, pixel_sigma=noise, process_psd=q, covariance=False
                        ).points
                    ),
                    uv,
                )
                acc.setdefault("smooth_scene_q", []).append((err_mm(sm, Xs), (dt_s + dt_q) / N))
                sp, dt_p = timed(
                    lambda u, P=P, t=times: (
                        smooth_points(P, u, t, pixel_sigma=noise, covariance=False).points
                    ),
                    uv,
                )
                acc.setdefault("smooth_point_q", []).append((err_mm(sp, Xs), dt_p / N))
                rb = jt.DCTBasis.from_times(times, min(F, 60))
                lam, dt_l = timed(
                    lambda u, P=P, t=times, rb=rb: select_penalty_cv(P, u[0], rb, t).lam, uv
                )
                pen = float(lam) * roughness_penalty(rb)
                Phi_r = rb(times)
                rr, dt_rr = timed(
                    lambda u, P=P, Phi=Phi_r, pen=pen: (
                        jt.reconstruct_points(P, u, Phi, penalty=pen).points
                    ),
                    uv,
                )
                acc.setdefault("dct_regularised", []).append((err_mm(rr, Xs), (dt_l + dt_rr) / N))
                # the N points as markers of a rigid body whose layout is known (the
                # pipeline's use case): per-image PnP, then one smooth rigid motion
                model = Xs[:, 0] - X[0]
                rig, dt_rig = timed(lambda u, P=P, m=model, t=times: rigid_points(P, u, m, t), uv)
                acc.setdefault("rigid_known_layout", []).append((err_mm(rig, Xs), dt_rig / N))
                if args.stonesoup:
                    for name, val in peer_rows(peer_rng, P, uv, times, noise, Xs, tuned).items():
                        acc.setdefault(name, []).append(val)
            row = {"source": source, "mode": mode}
            for name, vals in acc.items():
                v = np.array(vals)
                row[name] = {
                    "err_mm": float(v[:, 0].mean()),
                    "ms_per_traj": 1e3 * float(v[:, 1].mean()),
                }
            results.append(row)
            print(
                source,
                mode,
                {n: round(d["err_mm"], 2) for n, d in row.items() if isinstance(d, dict)},
            )
    return results


def rigid_points(P, uv, model, times, k=RIGID_K):
    """All markers' trajectories (N, F, 3) from a rigid fit with the layout known: per-image
    PnP (world frame through the known camera poses), then :func:`fit_rigid_trajectory`."""
    Rt = np.linalg.solve(K640, P)  # (F, 3, 4): [R_c_w | t_c_w]
    R_w_o, t_w_o = [], []
    for f in range(len(P)):
        R_c_o, t_c_o, _ = _pnp(model, uv[:, f], K640)
        R_c_w, t_c_w = Rt[f, :, :3], Rt[f, :, 3]
        R_w_o.append(R_c_w.T @ R_c_o)
        t_w_o.append(R_c_w.T @ (t_c_o - t_c_w))
    fit = fit_rigid_trajectory(
        P, uv, model, jt.dct_basis(times, k), init=(np.array(R_w_o), np.array(t_w_o))
    )
    return np.einsum("fij,mj->mfi", np.asarray(fit.R), model) + np.asarray(fit.t)[None]


def true_start(Xs, times):
    """(N, 2, 3) true position and velocity at the first frame."""
    return np.stack([Xs[:, 0], (Xs[:, 1] - Xs[:, 0]) / (times[1] - times[0])], 1)


def stonesoup_errors(P, uv, times, sigma_px, Xs, q, starts):
    """Stone Soup's error per point [mm] and its mean time per trajectory [s]."""
    from _stonesoup import stonesoup_smoother

    t = time.perf_counter()
    est = [
        stonesoup_smoother(P, uv[n], times, K640, sigma_px, q, starts[n, 0], starts[n, 1])
        for n in range(len(Xs))
    ]
    return point_err_mm(np.array(est), Xs), (time.perf_counter() - t) / len(Xs)


def smoother_errors(P, uv, times, sigma_px, Xs, q, starts=None):
    """The jaxtraj smoother's error per point [mm] (optionally with a start prior)."""
    kw = {} if starts is None else {"start_mean": starts, "start_cov": START_COV}
    est = smooth_points(P, uv, times, pixel_sigma=sigma_px, process_psd=q, covariance=False, **kw)
    return point_err_mm(est.points, Xs)


def filter_errors(P, uv, times, sigma_px, Xs, q, starts, rule):
    """The jaxtraj Kalman filter + RTS smoother's error per point [mm] (same start prior
    as Stone Soup's)."""
    est = filter_points(
        P,
        uv,
        times,
        start_mean=starts,
        start_cov=START_COV,
        process_psd=q,
        pixel_sigma=sigma_px,
        rule=rule,
    )
    return point_err_mm(est.points, Xs)


def tune_q(rng, args, source, mode, mocap):
    """Process noise of each smoother tuned as a tracking engineer would: the grid value
    with the least mean error on ``--tune-scenes`` scenes of the same kind, generated from
    their own random stream (never the test scenes). Stone Soup is tuned with its true
    start; the jaxtraj smoother without and with the same start, and the jaxtraj filter
    with it."""
    errs: dict[str, list] = {}
    for _ in range(args.tune_scenes):
        times, _, Xs, P, uv = draw_points(rng, args, source, mode, mocap)
        starts = true_start(Xs, times)
        for q in PEER_QS:
            e_ss, _ = stonesoup_errors(P, uv, times, args.noise, Xs, q, starts)
            errs.setdefault("stonesoup", []).append(e_ss.mean())
            errs.setdefault("smoother", []).append(
                smoother_errors(P, uv, times, args.noise, Xs, q).mean()
            )
            errs.setdefault("smoother_start", []).append(
                smoother_errors(P, uv, times, args.noise, Xs, q, starts).mean()
            )
            for rule in FILTER_RULES:
                errs.setdefault(f"filter_{rule}", []).append(
                    filter_errors(P, uv, times, args.noise, Xs, q, starts, rule).mean()
                )
    shape = (args.tune_scenes, len(PEER_QS))
    return {k: PEER_QS[int(np.argmin(np.reshape(v, shape).mean(0)))] for k, v in errs.items()}


def peer_rows(rng, P, uv, times, sigma_px, Xs, tuned):
    """Stone Soup against the jaxtraj smoother on the same points, each with its tuned q.

    ``*_true_start``: both get the true first state as the mean of their start prior
    (5 cm, 0.2 m/s; Stone Soup needs a start). ``*_prior_start``: the mean is drawn from
    that prior, as a real hand-over estimate would be. ``stonesoup_oracle_q``: the best q
    of the grid per trajectory, picked by its true error (an optimistic bound on tuning).
    Values are (mean error [mm], time per trajectory [s])."""
    rows = {}
    exact = true_start(Xs, times)
    drawn = exact + rng.normal(size=exact.shape) * np.sqrt(np.diag(START_COV)).reshape(2, 3)
    # the true-start runs over the whole grid serve the oracle and the tuned-q row
    per_q = [stonesoup_errors(P, uv, times, sigma_px, Xs, q, exact) for q in PEER_QS]
    for tag, starts in (("true_start", exact), ("prior_start", drawn)):
        if tag == "true_start":
            e, dt = per_q[PEER_QS.index(tuned["stonesoup"])]
        else:
            e, dt = stonesoup_errors(P, uv, times, sigma_px, Xs, tuned["stonesoup"], starts)
        rows[f"stonesoup_{tag}"] = (e.mean(), dt)
        q_start = tuned["smoother_start"]
        e, dt = timed(
            lambda u, st=starts, q=q_start: smoother_errors(P, u, times, sigma_px, Xs, q, st), uv
        )
        rows[f"smooth_tuned_q_{tag}"] = (e.mean(), dt / len(Xs))
        for rule in FILTER_RULES:
            q_f = tuned[f"filter_{rule}"]
            e, dt = timed(
                lambda u, st=starts, q=q_f, r=rule: filter_errors(
                    P, u, times, sigma_px, Xs, q, st, r
                ),
                uv,
            )
            rows[f"filter_{rule}_{tag}"] = (e.mean(), dt / len(Xs))
    e, dt = timed(lambda u: smoother_errors(P, u, times, sigma_px, Xs, tuned["smoother"]), uv)
    rows["smooth_tuned_q"] = (e.mean(), dt / len(Xs))
    oracle = np.min([e for e, _ in per_q], axis=0).mean()
    rows["stonesoup_oracle_q"] = (oracle, rows["stonesoup_true_start"][1])
    return rows


LABEL = {"sim": "simulated", "mocap": "motion capture"}


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A markdown table from its header cells and one list of cells per row."""
    lines = ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    return "\n".join(lines + ["| " + " | ".join(cells) + " |" for cells in rows])


def paired(args):
    """The jaxtraj filter against Stone Soup on the same points, same start, each with its
    q tuned as in :func:`tune_q`: per cell and start, the geometric mean of the per-point
    error ratios (filter / Stone Soup) with a 95 % confidence interval (normal
    approximation on the log ratios) and the share of points where the filter is closer.
    Returns the rows and a markdown table."""
    rng = np.random.default_rng(args.seed)
    tune_rng = np.random.default_rng(args.seed + 1000)
    peer_rng = np.random.default_rng(args.seed + 2000)
    sources, mocap = sources_and_mocap()
    noise = args.noise
    rows = []
    for source in sources:
        for mode in MODES:
            tuned = tune_q(tune_rng, args, source, mode, mocap)
            errs: dict[str, list] = {}
            for _ in range(args.scenes):
                times, _, Xs, P, uv = draw_points(rng, args, source, mode, mocap)
                exact = true_start(Xs, times)
                sd = np.sqrt(np.diag(START_COV)).reshape(2, 3)
                drawn = exact + peer_rng.normal(size=exact.shape) * sd
                for tag, st in (("true start", exact), ("drawn start", drawn)):
                    q = tuned["stonesoup"]
                    e, _ = stonesoup_errors(P, uv, times, noise, Xs, q, st)
                    errs.setdefault(("Stone Soup", tag), []).append(e)
                    for rule in FILTER_RULES:
                        q = tuned[f"filter_{rule}"]
                        e = filter_errors(P, uv, times, noise, Xs, q, st, rule)
                        errs.setdefault((f"filter ({rule})", tag), []).append(e)
            e = {key: np.concatenate(v) for key, v in errs.items()}
            for tag in ("true start", "drawn start"):
                ss = e[("Stone Soup", tag)]
                for rule in FILTER_RULES:
                    ours = e[(f"filter ({rule})", tag)]
                    lr = np.log(ours / ss)
                    half = 1.96 * lr.std(ddof=1) / np.sqrt(lr.size)
                    row = dict(
                        source=source,
                        mode=mode,
                        start=tag,
                        rule=rule,
                        points=int(lr.size),
                        filter_mm=float(ours.mean()),
                        stonesoup_mm=float(ss.mean()),
                        ratio=float(np.exp(lr.mean())),
                        ratio_lo=float(np.exp(lr.mean() - half)),
                        ratio_hi=float(np.exp(lr.mean() + half)),
                        filter_closer=float(np.mean(ours < ss)),
                    )
                    rows.append(row)
                    print(row, flush=True)
    header = ["scene / camera", "start", "filter rule", "filter [mm]", "Stone Soup [mm]"]
    header += ["ratio (95 % CI)", "filter closer"]
    cells = [
        [
            f"{LABEL[r['source']]}, {r['mode']}",
            r["start"],
            r["rule"],
            f"{r['filter_mm']:.3g}",
            f"{r['stonesoup_mm']:.3g}",
            f"{r['ratio']:.3f} ({r['ratio_lo']:.3f}-{r['ratio_hi']:.3f})",
            f"{100 * r['filter_closer']:.0f} %",
        ]
        for r in rows
    ]
    return rows, markdown_table(header, cells)


ALL_K = tuple(range(4, 21))  # every k the error-optimal k is searched over


def k_choice(args):
    """How good is the k chosen by cross-validation? On the scenes of :func:`run` (same
    seed, same draws), per cell: the mean error of each fixed k, of the DCT with k chosen
    by each rule (one k per scene, the median of the points' choices), the paired
    difference between auto-k and the fixed k picked per cell with the truth (95 % CI over
    scenes, the independent units: the points of a scene share their k), the share of
    scenes where auto-k is at least as close, and how far the chosen k lies from each
    scene's error-optimal k (searched over 4-20). Returns the rows and a markdown table."""
    rng = np.random.default_rng(args.seed)
    sources, mocap = sources_and_mocap()
    rules = K_RULES
    cv = k_choosers()
    rows = []
    for source in sources:
        for mode in MODES:
            errs = {k: [] for k in ALL_K}
            auto: dict[str, list] = {r: [] for r in rules}
            k_gap: dict[str, list] = {r: [] for r in rules}
            k_auto: dict[str, list] = {r: [] for r in rules}
            k_best: list[int] = []
            for _ in range(args.scenes):
                times, _, Xs, P, uv = draw_points(rng, args, source, mode, mocap)
                e = {}
                for k in ALL_K:
                    e[k] = err_mm(jt.reconstruct_points(P, uv, jt.dct_basis(times, k)).points, Xs)
                    errs[k].append(e[k])
                k_opt = min(e, key=e.get)
                k_best.append(k_opt)
                for rule in rules:
                    k = scene_k(cv[rule](P, uv, times))
                    auto[rule].append(e[k])
                    k_gap[rule].append(abs(k - k_opt))
                    k_auto[rule].append(k)
            mean = {k: float(np.mean(v)) for k, v in errs.items()}
            best_k = min(FIXED_K, key=mean.get)
            ref = np.asarray(errs[best_k])
            for rule in rules:
                d = np.asarray(auto[rule]) - ref
                half = 1.96 * d.std(ddof=1) / np.sqrt(d.size)
                row = dict(
                    source=source,
                    mode=mode,
                    rule=rule,
                    scenes=int(d.size),
                    fixed_k_mm={k: mean[k] for k in FIXED_K},
                    best_fixed_k=int(best_k),
                    auto_mm=float(np.mean(auto[rule])),
                    diff_mm=float(d.mean()),
                    diff_lo=float(d.mean() - half),
                    diff_hi=float(d.mean() + half),
                    auto_as_close=float(np.mean(d <= 0)),
                    k_gap_median=float(np.median(k_gap[rule])),
                    k_mean=float(np.mean(k_auto[rule])),
                    k_opt_mean=float(np.mean(k_best)),
                )
                rows.append(row)
                print(row, flush=True)
    header = ["scene / camera", "k rule", "best fixed k [mm]", "auto-k [mm]"]
    header += ["auto - best fixed (95 % CI) [mm]", "scenes auto-k as close"]
    header += ["median abs(k - k_opt)", "mean k (k_opt)"]
    cells = [
        [
            f"{LABEL[r['source']]}, {r['mode']}",
            r["rule"].replace("_", "-"),
            f"{r['fixed_k_mm'][r['best_fixed_k']]:.3g} (k = {r['best_fixed_k']})",
            f"{r['auto_mm']:.3g}",
            f"{r['diff_mm']:+.3g} ({r['diff_lo']:+.3g} to {r['diff_hi']:+.3g})",
            f"{100 * r['auto_as_close']:.0f} %",
            f"{r['k_gap_median']:g}",
            f"{r['k_mean']:.1f} ({r['k_opt_mean']:.1f})",
        ]
        for r in rows
    ]
    return rows, markdown_table(header, cells)


ESTIMATOR_COLUMNS = {
    "best fixed-k DCT (k = 6-12)": None,  # the best of FIXED_K per cell
    "auto-k DCT (CV, reprojection)": "dct_cv_k_reprojection",
    "auto-k DCT (CV, gain-weighted)": "dct_cv_k",
    "CV + ML refinement": "dct_cv_k_refined",
    "regularised DCT": "dct_regularised",
    "smoother (one q per scene)": "smooth_scene_q",
    "smoother (q per point)": "smooth_point_q",
    "rigid, known layout": "rigid_known_layout",
}
PEER_COLUMNS = {  # Stone Soup and the jaxtraj estimators on the same points, exact start
    "smoother, q per point, no start": "smooth_point_q",
    "smoother, tuned q, no start": "smooth_tuned_q",
    "smoother, tuned q, true start": "smooth_tuned_q_true_start",
    "filter (cubature), tuned q, true start": "filter_cubature_true_start",
    "filter (extended), tuned q, true start": "filter_extended_true_start",
    "Stone Soup, tuned q, true start": "stonesoup_true_start",
    "Stone Soup, oracle q, true start": "stonesoup_oracle_q",
}
DRAWN_COLUMNS = {  # the same with the start's mean drawn from the prior
    "smoother, drawn start": "smooth_tuned_q_prior_start",
    "filter (cubature), drawn start": "filter_cubature_prior_start",
    "filter (extended), drawn start": "filter_extended_prior_start",
    "Stone Soup, drawn start": "stonesoup_prior_start",
}


def markdown(results) -> str:
    """The README's tables: mean 3D error [mm] per cell (and the peer's, if measured)."""

    def table(columns):
        rows = []
        for row in results:
            cells = [f"{LABEL[row['source']]}, {row['mode']}"]
            for key in columns.values():
                if key is None:
                    v = min(row[f"dct_k{k}"]["err_mm"] for k in FIXED_K)
                else:
                    v = row[key]["err_mm"] if key in row else float("nan")
                cells.append(f"{v:.0f}" if v >= 1000 else f"{v:.3g}")
            rows.append(cells)
        return markdown_table(["scene / camera", *columns], rows)

    out = table(ESTIMATOR_COLUMNS)
    if "stonesoup_true_start" in results[0]:
        out += "\n\n" + table(PEER_COLUMNS) + "\n\n" + table(DRAWN_COLUMNS) + "\n\nper trajectory:"
        ms = lambda key: np.array([r[key]["ms_per_traj"] for r in results])  # noqa: E731
        ss = ms("stonesoup_true_start")
        out += f" Stone Soup {ss.min():.0f}-{ss.max():.0f} ms"
        for name, key in (
            ("smoother (fixed q)", "smooth_tuned_q_true_start"),
            ("smoother (q per point)", "smooth_point_q"),
            ("filter (cubature)", "filter_cubature_true_start"),
            ("filter (extended)", "filter_extended_true_start"),
        ):
            if key in results[0]:
                t, ratio = ms(key), ss / ms(key)
                out += (
                    f"; {name} {t.min():.2f}-{t.max():.2f} ms,"
                    f" {ratio.min():.0f}-{ratio.max():.0f}x faster"
                )
    return out


# --------------------------------------------------------------------------- --trust
# Issue 20: can a user trust the per-point estimators at every camera speed? Accuracy,
# flags and the calibration of the reported uncertainty, cell by cell.

TRUST_F = 150  # frames per scene
TRUST_RATE = 30.0  # [Hz]
TRUST_K = np.array([[800.0, 0.0, 319.5], [0.0, 800.0, 239.5], [0.0, 0.0, 1.0]])  # 640x480
TRUST_DIST = 3.0  # camera stand-off from the subject [m] (orbits, follower, mocap robots)
ORBIT_DEG = (1, 2, 5, 10, 20, 45, 90)  # orbit speed [deg/frame] (Valmadre & Lucey, Fig. 3)
TRUST_CAMERAS = (*(f"orbit{d}" for d in ORBIT_DEG), *MODES, "follow")
# the order the cells are run in, so that a partial run has the slowest, the fastest and
# the follower first (the tables list them in TRUST_CAMERAS' order)
RUN_ORDER = ("orbit1", "random", "follow", "orbit2", "fast", "slow", "orbit5", "smooth")
RUN_ORDER += ("orbit10", "orbit20", "orbit45", "orbit90")
TRUST_NOISE = 0.5  # [px]
CLEAN_SIGMA = 0.05  # pixel_sigma given to the estimators on noise-free cells [px]
CMU = ROOT.parent / "shared" / "data" / "cmu_bvh"
CMU_TAKES = ("131_01", "131_03")
TRUST_ROWS = {  # key: label
    "ep": "estimate_points",
    "ep123": "estimate_points(orders=(1, 2, 3))",
    "sm1": "smooth_points, order 1",
    "sm2": "smooth_points, order 2",
    "reg": "regularised DCT",
    "cv": "auto-k DCT (CV)",
    "fixk": "fixed-k DCT, k picked with the truth",
}
TIMED_ROWS = ("ep", "ep123", "sm1", "sm2")
NEES_OK = (2.0, 4.5)  # the targets
TARGET_RATIO, TARGET_MAX_MM, TARGET_CAUGHT, TARGET_FLAGGED, TARGET_MS = 1.25, 100.0, 0.95, 0.05, 5.0


def load_takes() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The shared CMU takes: name -> (positions (T, J, 3) z-up [m], times (T,) [s]);
    empty (with a message) when ``../shared/data/cmu_bvh`` is absent."""
    from jaxtraj.io.bvh import load_bvh

    takes = {}
    for take in CMU_TAKES:
        path = CMU / f"scaled_{take}.bvh"
        if not path.exists():
            print(f"--trust: {path} not found, motion-capture cells skipped", file=sys.stderr)
            continue
        motion = load_bvh(path)
        takes[f"cmu{take}"] = (motion.positions(z_up=True), np.asarray(motion.times))
    return takes


def mocap_points(rng, take, n_points, F=TRUST_F, rate=TRUST_RATE):
    """A random window of F frames of a take, subsampled to ``rate``: times (F,) and
    ``n_points`` distinct joints (N, F, 3) centred 1 m above the floor's origin."""
    pos, t = take
    step = round((1 / rate) / (t[1] - t[0]))
    start = rng.integers(0, pos.shape[0] - F * step)
    X = pos[start : start + F * step : step]  # (F, J, 3)
    X = X - X.reshape(-1, 3).mean(0) + np.array([0.0, 0.0, 1.0])
    _, idx = np.unique(np.round(X[0], 6), axis=0, return_index=True)  # end sites repeat
    idx = np.sort(idx)
    if len(idx) > n_points:
        idx = np.sort(rng.choice(idx, n_points, replace=False))
    return np.arange(F) / rate, np.swapaxes(X[:, idx], 0, 1)


def _looking(C, targets, K=TRUST_K):
    """(F, 3, 4) cameras at centres C looking at targets (z up)."""
    R, t = jax.vmap(lambda c, x: jt.look_at(c, x, up_w=(0.0, 0.0, 1.0)))(C, targets)
    return K @ np.concatenate([np.asarray(R), np.asarray(t)[:, :, None]], axis=2)


def trust_cameras(rng, camera, Xs, times, robot_path=None):
    """Camera centres (F, 3) and matrices (F, 3, 4) for one scene.

    ``orbitD``: a circle of radius 3 m about the subject's mean, D deg/frame, elevation
    10-30 deg, start angle at random; ``follow``: the subject's centroid plus a fixed
    3 m offset; both look at the centroid of the frame (f = 800, 640x480). Robot modes
    (:func:`camera_centres`): on the simulated cell as in the rest of the bench (0.7-1.1 m,
    f = 700, ``robot_path`` the workpiece path); on motion capture their centres are
    pushed radially to 3 m from the subject's mean (a person does not fit in the image at
    1 m), which keeps their angular motion.
    """
    F = len(times)
    centroid = Xs.mean(axis=0)  # (F, 3)
    mean = centroid.mean(axis=0)
    if camera.startswith("orbit"):
        angle = rng.uniform(0, 2 * np.pi) + np.deg2rad(float(camera[5:])) * np.arange(F)
        el = np.deg2rad(rng.uniform(10, 30))
        ring = np.stack([np.cos(angle) * np.cos(el), np.sin(angle) * np.cos(el)], 1)
        C = mean + TRUST_DIST * np.concatenate([ring, np.full((F, 1), np.sin(el))], 1)
    elif camera == "follow":
        d = rng.normal(size=3)
        d[2] = abs(d[2]) + 0.3
        C = centroid + TRUST_DIST * d / np.linalg.norm(d)
    elif robot_path is not None:  # the simulated cell's robot
        C = camera_centres(rng, times, robot_path, camera)
        return C, cameras_looking_at(rng, C, robot_path)
    else:
        C = camera_centres(rng, times, centroid, camera) - mean
        C = mean + TRUST_DIST * C / np.linalg.norm(C, axis=1, keepdims=True)
    return C, _looking(C, centroid)


def trust_scene(rng, noise_rng, source, camera, noise, n_points, takes):
    """One scene: times (F,), true tracks (N, F, 3), cameras (F, 3, 4), pixels (N, F, 2)
    with ``noise`` px and weights (N, F) (0 outside the image or behind the camera)."""
    times = np.arange(TRUST_F) / TRUST_RATE
    path = None
    if source == "sim":
        path = workpiece_path(rng, times)
        Xs = points_around(rng, path, n_points)
    else:
        times, Xs = mocap_points(rng, takes[source], n_points)
    _, P = trust_cameras(rng, camera, Xs, times, path)
    h = np.einsum("fij,nfj->nfi", P[:, :, :3], Xs) + P[None, :, :, 3]
    uv = h[..., :2] / h[..., 2:]
    seen = (h[..., 2] > 0) & np.all((uv > 0) & (uv < [640.0, 480.0]), axis=-1)
    uv = np.where(seen[..., None], uv, 0.0) + noise * noise_rng.normal(size=uv.shape)
    return times, Xs, P, uv, seen.astype(float)


def trust_cells(takes, pattern):
    """(source, camera, noise) of every cell whose ``source/camera/noise`` name matches
    one of the comma-separated fnmatch patterns (all cells without a pattern)."""
    from fnmatch import fnmatch

    cells = []  # camera by camera, so that a partial run covers every source
    for camera in RUN_ORDER:
        for source in ("sim", *takes):
            for noise in (0.0, TRUST_NOISE) if camera.startswith("orbit") else (TRUST_NOISE,):
                name = cell_name(source, camera, noise)
                if pattern is None or any(fnmatch(name, p) for p in pattern.split(",")):
                    cells.append((source, camera, noise))
    return cells


def cell_name(source, camera, noise):
    return f"{source}/{camera}/{'clean' if noise == 0 else f'{noise:g}px'}"


def _trajectory_stats(est, cov, status, Xs):
    """Per trajectory: RMS 3D error [mm], mean sqrt(trace cov) [mm], NEES (3 dof, per
    frame, averaged over frames) and whether the status is OK. ``cov`` may be None."""
    est = np.asarray(est)
    out = {"err": point_err_mm(est, Xs), "ok": np.asarray(status) == jt.Status.OK}
    if cov is None:
        out["sd"] = out["nees"] = np.full(len(Xs), np.nan)
        return out
    cov = np.asarray(cov)
    d = est - Xs
    out["sd"] = 1e3 * np.sqrt(np.maximum(np.trace(cov, axis1=-2, axis2=-1), 0)).mean(-1)
    out["nees"] = np.einsum("nfi,nfij,nfj->nf", d, np.linalg.pinv(cov, hermitian=True), d).mean(-1)
    return out


def trust_estimators():
    """Compiled batched estimators (P, uv (N, F, 2), times, w (N, F), sigma) -> result."""
    ks = jax.jit(
        jax.vmap(
            lambda P, u, t, w: select_k_cv(P, u, t, KS, w, rule="gain_weighted").k,
            (None, 0, None, 0),
        )
    )

    def reg_one(P, u, t, w, s):  # the fit and its covariance (regularised_covariance)
        res, basis, choice = reconstruct_regularised(P, u, t, w)
        cov = regularised_covariance(P, u, t, basis, res.coeffs, choice.lam, w, pixel_sigma=s)
        return res, cov.points

    reg = jax.jit(jax.vmap(reg_one, (None, 0, None, 0, None)))
    cov = jax.jit(
        jax.vmap(
            lambda P, u, b, c, w, s: dct_covariance(P, u, b, c, w, pixel_sigma=s).points,
            (None, 0, None, 0, 0, None),
        )
    )
    return ks, reg, cov


def trust_scene_rows(P, uv, times, w, Xs, sigma, compiled):
    """Every estimator on one scene: per row, the per-trajectory statistics (and the
    batched time per point [s] of the timed rows); ``fixk`` holds one entry per k."""
    ks_fn, reg_fn, cov_fn = compiled
    N = len(Xs)
    calls = {
        "ep": lambda: estimate_points(P, uv, times, w, pixel_sigma=sigma),
        "ep123": lambda: estimate_points(P, uv, times, w, pixel_sigma=sigma, orders=(1, 2, 3)),
        "sm1": lambda: smooth_points(P, uv, times, w, order=1, pixel_sigma=sigma),
        "sm2": lambda: smooth_points(P, uv, times, w, order=2, pixel_sigma=sigma),
    }
    rows = {}
    for key, fn in calls.items():
        r = fn()
        rows[key] = _trajectory_stats(r.points, r.cov, r.status, Xs)
        if hasattr(r, "dct_k"):  # estimate_points: where the DCT basis was chosen
            rows[key]["dct"] = np.asarray(r.dct_k) > 0
        rows[key]["ms"] = 1e3 * time_call(fn, repeats=2).median / N
    r, reg_cov = reg_fn(P, uv, times, w, sigma)
    rows["reg"] = _trajectory_stats(r.points, reg_cov, r.status, Xs)

    def dct(k):
        b = jt.dct_basis(times, k)
        r = jt.reconstruct_points(P, uv, b, w)
        return _trajectory_stats(r.points, cov_fn(P, uv, b, r.coeffs, w, sigma), r.status, Xs)

    rows["fixk"] = {k: dct(k) for k in KS}
    k = scene_k(ks_fn(P, uv, times, w))
    rows["cv"] = dict(rows["fixk"][k]) if k in rows["fixk"] else dct(k)
    rows["cv"]["k"] = k
    return rows


def _summarise(stats):
    """One row's cell summary from its per-trajectory statistics (concatenated)."""
    err, ok, sd, nees = stats["err"], stats["ok"], stats["sd"], stats["nees"]
    big = err > 5 * sd  # NaN sd (no covariance): never
    nan = float("nan")
    out = {
        "trajectories": int(err.size),
        "err_mm": float(err.mean()),
        "flagged": float(np.mean(~ok)),
        "ok_err_mm": float(err[ok].mean()) if ok.any() else nan,
        "ok_max_mm": float(err[ok].max()) if ok.any() else nan,
        "ok_nees": float(np.mean(nees[ok])) if ok.any() else nan,
        "over_5sd": int(big.sum()),
        "over_5sd_flagged": float(np.mean(~ok[big])) if big.any() else nan,
        "has_cov": bool(np.isfinite(sd).any()),
    }
    if "ms" in stats:
        out["ms_per_point"] = float(np.median(stats["ms"]))
    if "dct" in stats:
        out["dct_chosen"] = float(np.mean(stats["dct"]))
    return out


def trust_cell_scenes(args, takes, source, camera, noise):
    """The ``args.scenes`` scenes of one cell (:func:`trust_scene`), seeded by the seed, the
    source and the camera (the same scenes at any noise level)."""
    i_src = (["sim", *takes]).index(source)
    i_cam = TRUST_CAMERAS.index(camera)
    rng = np.random.default_rng([args.seed, i_src, i_cam])
    noise_rng = np.random.default_rng([args.seed, i_src, i_cam, int(noise * 1000)])
    for _ in range(args.scenes):
        yield trust_scene(rng, noise_rng, source, camera, noise, args.points, takes)


def trust(args, on_cell=None):
    """The ``--trust`` benchmark (issue 20): returns the per-cell results
    (``on_cell(results)`` after each cell)."""
    takes = load_takes()
    compiled = trust_estimators()
    results = []
    for source, camera, noise in trust_cells(takes, args.cells):
        sigma = noise if noise > 0 else CLEAN_SIGMA
        acc: dict = {}
        t0 = time.perf_counter()
        for times, Xs, P, uv, w in trust_cell_scenes(args, takes, source, camera, noise):
            rows = trust_scene_rows(P, uv, times, w, Xs, sigma, compiled)
            acc.setdefault("seen", []).append(w.mean())
            for key, stats in rows.items():
                if key == "fixk":
                    for k, s in stats.items():
                        for f, v in s.items():
                            acc.setdefault(("fixk", k), {}).setdefault(f, []).append(v)
                    continue
                for f, v in stats.items():
                    acc.setdefault(key, {}).setdefault(f, []).append(np.atleast_1d(v))
        cat = lambda d: {f: np.concatenate([np.atleast_1d(x) for x in v]) for f, v in d.items()}  # noqa: E731
        best_k = min(KS, key=lambda k: np.concatenate(acc[("fixk", k)]["err"]).mean())
        row = {
            "cell": cell_name(source, camera, noise),
            "source": source,
            "camera": camera,
            "noise_px": noise,
            "pixel_sigma": sigma,
            "scenes": args.scenes,
            "seen": float(np.mean(acc["seen"])),
            "best_k": int(best_k),
            "cv_k": [int(k) for k in cat(acc["cv"])["k"]],
        }
        for key in TRUST_ROWS:
            stats = cat(acc[("fixk", best_k)] if key == "fixk" else acc[key])
            row[key] = _summarise(stats)
        results.append(row)
        if on_cell is not None:
            on_cell(results)
        print(
            f"{row['cell']}: "
            + ", ".join(f"{k} {row[k]['err_mm']:.3g}" for k in TRUST_ROWS)
            + f" mm; flagged by estimate_points {100 * row['ep']['flagged']:.0f} %"
            + f" ({time.perf_counter() - t0:.0f} s)",
            file=sys.stderr,
            flush=True,
        )
    return results


def _f(v, fmt="{:.3g}", nan="-"):
    if v is None or not np.isfinite(v):
        return nan
    return f"{v:.0f}" if fmt == "{:.3g}" and abs(v) >= 1000 else fmt.format(v)


def _pct(v):
    return "-" if v is None or not np.isfinite(v) else f"{100 * v:.0f} %"


def ratio_to_best(row):
    """estimate_points' mean error over the best of the other rows (and that row)."""
    others = {k: row[k]["err_mm"] for k in TRUST_ROWS if k not in ("ep", "ep123")}
    best = min(others, key=others.get)
    return row["ep"]["err_mm"] / others[best], best


def trust_markdown(results) -> str:
    """Per-cell tables (one per cell) and the summary against the issue's targets."""
    table = common_table
    sources = ["sim", *sorted({r["source"] for r in results} - {"sim"})]
    results = sorted(
        results,
        key=lambda r: (TRUST_CAMERAS.index(r["camera"]), sources.index(r["source"]), r["noise_px"]),
    )
    out = []
    header = ["estimator", "mean err [mm]", "flagged", "OK: mean err [mm]", "OK: max [mm]"]
    header += ["OK: NEES", "> 5 sd: n (flagged)", "ms / point"]
    for row in results:
        lines = []
        for key, label in TRUST_ROWS.items():
            r = row[key]
            if key == "fixk":
                label += f" (k = {row['best_k']})"
            over = f"{r['over_5sd']} ({_pct(r['over_5sd_flagged'])})" if r["has_cov"] else "-"
            lines.append(
                [
                    label,
                    _f(r["err_mm"]),
                    _pct(r["flagged"]),
                    _f(r["ok_err_mm"]),
                    _f(r["ok_max_mm"]),
                    _f(r["ok_nees"], "{:.3g}") if r["has_cov"] else "-",
                    over,
                    _f(r.get("ms_per_point", float("nan")), "{:.2f}"),
                ]
            )
        n = row["ep"]["trajectories"]
        out.append(
            f"**{row['cell']}** ({row['scenes']} scenes, {n} trajectories, "
            f"{100 * row['seen']:.0f} % of pixels in the image, pixel_sigma "
            f"{row['pixel_sigma']:g} px)\n\n" + table(header, lines)
        )
    hdr = ["cell", "ratio to best other (<= 1.25)", "OK: max err [mm] (<= 100)"]
    hdr += ["OK: NEES (2-4.5)", "> 5 sd flagged (>= 95 %)", "flagged (random, fast: <= 5 %)"]
    hdr += ["ms / point (<= 5)"]
    lines, misses = [], {h: 0 for h in hdr[1:]}

    def mark(ok, text, col):
        if ok is None:
            return text
        misses[col] += not ok
        return text if ok else f"**{text}** (missed)"

    for row in results:
        ep = row["ep"]
        ratio, best = ratio_to_best(row)
        fast = row["camera"] in ("random", "fast")
        cells = [
            row["cell"],
            mark(ratio <= TARGET_RATIO, f"{ratio:.2f} ({TRUST_ROWS[best]})", hdr[1]),
            mark(
                None if not np.isfinite(ep["ok_max_mm"]) else ep["ok_max_mm"] <= TARGET_MAX_MM,
                _f(ep["ok_max_mm"]),
                hdr[2],
            ),
            mark(
                None
                if not np.isfinite(ep["ok_nees"])
                else NEES_OK[0] <= ep["ok_nees"] <= NEES_OK[1],
                _f(ep["ok_nees"]),
                hdr[3],
            ),
            mark(
                None if ep["over_5sd"] == 0 else ep["over_5sd_flagged"] >= TARGET_CAUGHT,
                f"{_pct(ep['over_5sd_flagged'])} of {ep['over_5sd']}"
                if ep["over_5sd"]
                else "none over 5 sd",
                hdr[4],
            ),
            mark(ep["flagged"] <= TARGET_FLAGGED if fast else None, _pct(ep["flagged"]), hdr[5]),
            mark(ep["ms_per_point"] <= TARGET_MS, f"{ep['ms_per_point']:.2f}", hdr[6]),
        ]
        lines.append(cells)
    summary = table(hdr, lines)
    missed = "; ".join(
        f"{h.split(' (')[0]}: {m} of {len(results)} cells" for h, m in misses.items()
    )
    notes = (
        "Errors: RMS 3D error over the frames of each trajectory, averaged over "
        "trajectories. 'OK': status == Status.OK (estimate_points' and the smoother's "
        "status, the DCT's Reconstruction.status). NEES: (x - x_true)^T cov^-1 (x - x_true) "
        "per frame (3 dof, ideal 3), averaged over frames, then over OK trajectories "
        "(estimate_points: .cov with its along-ray term; smoother: posterior .cov; DCT: "
        "dct_covariance with its model-error term; regularised DCT: regularised_covariance"
        "). '> 5 sd': trajectories whose error exceeds 5x their mean sqrt(trace "
        "cov), and the share of them flagged. Noise-free cells ('clean') give "
        f"pixel_sigma = {CLEAN_SIGMA} px to estimate_points, the smoothers and the DCT "
        "covariance. Auto-k DCT: select_k_cv (gain-weighted) per point, one k per scene "
        "(median). Fixed-k DCT: the k of 4-20 (step 2) with the least mean error in the "
        "cell, picked with the truth. Time: batched (jit + vmap over the scene's points, "
        "after warm-up), F = 150, median over scenes, per point, on this machine under "
        "its current load."
    )
    return (
        "\n\n".join(out)
        + "\n\n**Summary against the targets of issue 20**\n\n"
        + summary
        + (f"\n\nMissed: {missed}.\n\n{notes}")
    )


TRUST_OUT = ROOT / "benchmarks" / "results" / "estimators_trust.json"


def trust_alone(args) -> int:
    """``--trust --alone``: every track of the trust scenes estimated alone (N = 1) against
    the same track in its scene's batch. A model choice, status or error that changes with
    the batch's size is a decision made by rounding (a 300 m-off status-OK track was found
    this way). Prints each track that differs and returns the number of those that are
    status OK in either estimate (a flagged track whose fallback picks another flagged fit
    is listed, not counted)."""
    takes = load_takes()
    differ = flagged_only = total = 0
    for source, camera, noise in trust_cells(takes, args.cells):
        sigma = noise if noise > 0 else CLEAN_SIGMA
        scenes = trust_cell_scenes(args, takes, source, camera, noise)
        for scene_i, (times, Xs, P, uv, w) in enumerate(scenes):
            batch = estimate_points(P, uv, times, w, pixel_sigma=sigma)
            err = point_err_mm(np.asarray(batch.points), Xs)
            for i in range(len(Xs)):
                one = estimate_points(P, uv[i : i + 1], times, w[i : i + 1], pixel_sigma=sigma)
                err1 = point_err_mm(np.asarray(one.points), Xs[i : i + 1])[0]
                keys = ("status", "order", "dct_k")
                a = [int(np.asarray(getattr(batch, k))[i]) for k in keys]
                b = [int(np.asarray(getattr(one, k))[0]) for k in keys]
                total += 1
                if a == b and abs(err1 - err[i]) <= 0.01 * err[i] + 0.01:
                    continue
                # a flagged track may fall back to another flagged fit: reported, not counted
                ok = a[0] == jt.Status.OK or b[0] == jt.Status.OK
                differ += ok
                flagged_only += not ok
                print(
                    f"{cell_name(source, camera, noise)} scene {scene_i} track {i}: "
                    f"in the batch {err[i]:.4g} mm (status, order, dct_k) {a}; "
                    f"alone {err1:.4g} mm {b}{'' if ok else ' (flagged either way)'}",
                    flush=True,
                )
    print(
        f"tracks whose estimate alone differs from the batch's: {differ} of {total} "
        f"(and {flagged_only} flagged either way that fell back to another fit)"
    )
    return differ


def trust_main(parser, args):
    """``--trust``: defaults --scenes 2 --points 12 (unless given); writes TRUST_OUT
    (or --out) and prints the tables; with --markdown, reprints a JSON's tables."""
    if args.markdown:
        print(trust_markdown(json.loads(args.markdown.read_text())["cells"]))
        return
    given = set(sys.argv[1:])
    if "--scenes" not in given:
        args.scenes = 2
    if "--points" not in given:
        args.points = 12
    if args.alone:
        sys.exit(1 if trust_alone(args) else 0)
    t0 = time.perf_counter()
    out = args.out or TRUST_OUT

    def write(results, done=False):
        meta = {
            "command": "python benchmarks/bench_estimators.py " + " ".join(sys.argv[1:]),
            "machine": machine_info(),
            "seconds": time.perf_counter() - t0,
            "complete": done,
            "frames": TRUST_F,
            "rate_hz": TRUST_RATE,
        }
        out.write_text(json.dumps({"meta": meta, "cells": results}, indent=1))

    results = trust(args, on_cell=write)
    write(results, done=True)
    print(trust_markdown(results))


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", type=int, default=4)
    p.add_argument("--points", type=int, default=8)
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--noise", type=float, default=0.4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--stonesoup", action="store_true")
    p.add_argument("--paired", action="store_true", help="only the filter vs Stone Soup")
    p.add_argument("--k-choice", action="store_true", help="only auto-k vs the fixed k")
    p.add_argument("--tune-scenes", type=int, default=1, help="scenes per cell to tune q on")
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--markdown", type=Path, default=None, help="print the tables of a JSON")
    p.add_argument("--trust", action="store_true", help="issue 20: accuracy, flags, calibration")
    p.add_argument("--cells", default=None, help="--trust: fnmatch patterns, e.g. 'sim/orbit1/*'")
    p.add_argument(
        "--alone",
        action="store_true",
        help="--trust: estimate_points on each track alone against the batch (exit 1: some differ)",
    )
    args = p.parse_args()
    if args.trust:
        trust_main(p, args)
        return
    if args.markdown:
        print(markdown(json.loads(args.markdown.read_text())))
        return
    sys.path.insert(0, str(Path(__file__).parent))
    if args.paired or args.k_choice:
        rows, table = (k_choice if args.k_choice else paired)(args)
        print(table)
        if args.out:
            args.out.write_text(json.dumps(rows, indent=1))
        return
    results = run(args)
    print(markdown(results))
    if args.out:
        args.out.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()

"""Benchmark: batched structured solver (jaxtraj.reconstruct_points) vs a dense NumPy port.

The baseline is the textbook form of the method (paper eq. 5-6) for one point at a time:
build the dense block-diagonal ``Q`` (2F x 3F) and ``q``, form ``A = Q Theta`` with
``Theta = kron(Phi, I_3)`` (3F x 3k, built once and shared by all points; not timed), and
call ``numpy.linalg.lstsq(A, q)``. jaxtraj solves the same weighted least-squares problem
from O(F k^2) normal equations, batched over points.

Usage::

    python benchmarks/bench_solve.py [--quick] [--out benchmarks/results/solve.md]
    python benchmarks/bench_solve.py --stress 50   # hang check: 50 batched solves
    python benchmarks/bench_solve.py --structured-only   # vs vectorised NumPy, gain cost

Float64 is enabled below (a benchmark script may do so; library code never does); the
float32 runs cast their inputs.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import faulthandler
import json
import os
import subprocess
import sys
import time
from pathlib import Path

if __name__ == "__main__":
    # Single-threaded BLAS for the NumPy baseline unless the caller says otherwise: on a
    # shared 2-core machine OpenBLAS' own threads made the dense products 20-100x slower
    # than one thread (F = 150: 0.5 ms vs 10-48 ms per point). Set before NumPy loads.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (  # noqa: E402
    DenseRun,
    Scene,
    add_watchdog_option,
    block,
    compiled_memory,
    dense_breakdown,
    fmt_mib,
    fmt_ms,
    fmt_times,
    fmt_us,
    machine_info,
    make_scene,
    markdown_table,
    relative_difference,
    run_dense,
    start_watchdog,
    stderr_logger,
    time_call,
)

from jaxtraj.solve import reconstruct, reconstruct_points  # noqa: E402


@dataclasses.dataclass(frozen=True)
class Config:
    """Problem sizes and time budgets of one benchmark run."""

    main: tuple[int, int, int] = (150, 10, 2000)  # F, k, N
    trials: int = 3
    repeats: int = 7
    dense_max_points: int = 200
    dense_budget_s: float = 3.0
    dense_cap_s: float = 5.0  # skip the baseline when one point takes longer than this
    Fs: tuple[int, ...] = (50, 150, 500, 1000, 2000)
    ks: tuple[int, ...] = (5, 10, 20, 40)
    Ns: tuple[int, ...] = (100, 1000, 10000)


FULL = Config()
QUICK = Config(
    main=(60, 6, 300),
    trials=1,
    repeats=3,
    dense_max_points=30,
    dense_budget_s=0.5,
    Fs=(30, 60, 120),
    ks=(4, 8),
    Ns=(50, 300),
)


# --------------------------------------------------------------------------- measurements


@dataclasses.dataclass(frozen=True)
class JaxRun:
    """Timing of ``reconstruct_points`` on all N points of a scene."""

    n_points: int
    first_s: float  # first call: trace + compile + run
    median_s: float  # warm call, median of the repeats
    spread_s: tuple[float, float]
    result: object  # the Reconstruction (NumPy leaves)

    @property
    def per_point_s(self) -> float:
        return self.median_s / self.n_points

    @property
    def compile_s(self) -> float:
        return max(self.first_s - self.median_s, 0.0)


def _inputs(scene: Scene, dtype) -> tuple[jax.Array, jax.Array, jax.Array]:
    P, uv, basis = (jax.device_put(jnp.asarray(x, dtype)) for x in (scene.P, scene.uv, scene.basis))
    return block((P, uv, basis))


def run_jaxtraj(scene: Scene, dtype=jnp.float64, repeats: int = 5) -> JaxRun:
    """Time the public ``reconstruct_points`` (host validation included) on every point."""
    P, uv, basis = _inputs(scene, dtype)
    timing = time_call(lambda: reconstruct_points(P, uv, basis), repeats=repeats)
    result = jax.tree_util.tree_map(np.asarray, reconstruct_points(P, uv, basis))
    return JaxRun(
        n_points=uv.shape[0],
        first_s=timing.first,
        median_s=timing.median,
        spread_s=timing.spread,
        result=result,
    )


def run_kernel(
    scene: Scene, dtype=jnp.float64, repeats: int = 5, diagnostics: bool = True
) -> float:
    """Warm seconds per point of the jitted batched kernel alone (no host-side validation)."""
    P, uv, basis = _inputs(scene, dtype)
    w = jnp.ones(uv.shape[:2], dtype)

    def one(P, uv, basis, w):
        return reconstruct(P, uv, basis, w, diagnostics=diagnostics)

    fn = jax.jit(jax.vmap(one, in_axes=(None, 0, None, 0)))
    return time_call(lambda: fn(P, uv, basis, w), repeats=repeats).median / uv.shape[0]


def numpy_structured(P: np.ndarray, uv: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """Coefficients (N, k, 3) from the same structured normal equations in vectorised NumPy.

    What a competent engineer writes in an afternoon: per-frame ``Q^T Q`` and ``Q^T q`` of
    all points by einsum, the Kronecker sums over frames as one matrix product with the
    (F, k^2) basis products, one batched ``numpy.linalg.solve`` (LAPACK), no refinement and
    no degeneracy test.
    """
    N, F, _ = uv.shape
    k = basis.shape[1]
    rows = P[None, :, :2, :] - uv[..., None] * P[None, :, 2:3, :]  # (N, F, 2, 4)
    Q, q = rows[..., :3], -rows[..., 3]
    QtQ = np.einsum("nfri,nfrj->nfij", Q, Q).reshape(N, F, 9)
    Qtq = np.einsum("nfri,nfr->nfi", Q, q)
    phiphi = (basis[:, :, None] * basis[:, None, :]).reshape(F, k * k)
    Nm = np.matmul(phiphi.T, QtQ).reshape(N, k, k, 3, 3).transpose(0, 1, 3, 2, 4)
    b = np.matmul(basis.T, Qtq)  # (N, k, 3)
    beta = np.linalg.solve(Nm.reshape(N, 3 * k, 3 * k), b.reshape(N, 3 * k, 1))
    return beta.reshape(N, k, 3)


def time_numpy_structured(scene: Scene, repeats: int = 5, dtype=np.float64) -> float:
    """Warm seconds per point of :func:`numpy_structured` on all points of the scene."""
    P, uv, basis = (np.asarray(x, dtype) for x in (scene.P, scene.uv, scene.basis))
    timing = time_call(lambda: numpy_structured(P, uv, basis), repeats=repeats)
    return timing.median / uv.shape[0]


def stress(scene: Scene, repeats: int, log) -> None:
    """Run ``repeats`` batched solves of each kind back to back (a hang check: with jaxlib
    0.10 vmapped LAPACK calls were seen to deadlock on 2 cores; the watchdog aborts with
    stack traces if a call never returns)."""
    P, uv, basis = _inputs(scene, jnp.float64)
    w = jnp.ones(uv.shape[:2], jnp.float64)
    vm = jax.jit(jax.vmap(reconstruct, in_axes=(None, 0, None, 0)))
    for name, fn in (
        ("reconstruct_points", lambda: reconstruct_points(P, uv, basis, w)),
        ("jit(vmap(reconstruct))", lambda: vm(P, uv, basis, w)),
    ):
        started = time.perf_counter()
        for i in range(repeats):
            out = jax.block_until_ready(fn())
            if i == 0:
                log(f"stress {name}: first call {time.perf_counter() - started:.1f} s")
        total = time.perf_counter() - started
        ok = int(np.sum(np.asarray(out.status) == 0))
        log(f"stress {name}: {repeats} calls in {total:.1f} s, last status OK {ok}/{uv.shape[0]}")


def dense_in_child(F: int, k: int, N: int, blas_threads: int, cfg: Config) -> float | None:
    """Seconds per point of the baseline in a child process with ``blas_threads`` OpenBLAS
    threads (the thread count is fixed when NumPy loads). None if the child failed."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS=str(blas_threads))
    spec = json.dumps(
        {"F": F, "k": k, "N": N, "max": cfg.dense_max_points, "budget": cfg.dense_budget_s}
    )
    try:
        out = subprocess.run(
            [sys.executable, str(Path(__file__).resolve()), "--dense-child", spec],
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
            check=True,
        )
        return float(json.loads(out.stdout.strip().splitlines()[-1])["per_point_s"])
    except (subprocess.SubprocessError, ValueError, KeyError, IndexError):
        return None


def _dense_child(spec: str) -> None:
    args = json.loads(spec)
    scene = make_scene(args["F"], args["k"], args["N"], seed=0)
    run = run_dense(scene, args["max"], args["budget"])
    print(json.dumps({"per_point_s": run.per_point_s, "n": int(run.indices.size)}))


@dataclasses.dataclass(frozen=True)
class Comparison:
    """One (F, k, N) case: jaxtraj on all points, the baseline on a subset."""

    F: int
    k: int
    N: int
    jax: JaxRun
    dense: DenseRun

    @property
    def ratio(self) -> float:
        return self.dense.per_point_s / self.jax.per_point_s

    @property
    def rel_diff(self) -> float:
        coeffs = np.asarray(self.jax.result.coeffs)[self.dense.indices]
        return relative_difference(coeffs, self.dense.coeffs)


def compare(
    F: int, k: int, N: int, cfg: Config, *, seed: int = 0, dense_budget_s: float | None = None
) -> Comparison:
    """Build a scene and time both solvers on it (float64)."""
    scene = make_scene(F, k, N, seed=seed)
    jr = run_jaxtraj(scene, jnp.float64, repeats=cfg.repeats if F <= 500 else 3)
    dr = run_dense(
        scene,
        cfg.dense_max_points,
        cfg.dense_budget_s if dense_budget_s is None else dense_budget_s,
        cap_s=cfg.dense_cap_s,
    )
    return Comparison(F, k, N, jr, dr)


def kernel_memory(F: int, k: int, N: int, dtype=jnp.float64) -> dict[str, float]:
    """Memory analysis and compile time of the batched kernel that ``reconstruct_points`` runs."""
    shapes = [(F, 3, 4), (N, F, 2), (F, k), (N, F)]
    fn = jax.jit(jax.vmap(reconstruct, in_axes=(None, 0, None, 0)))
    return compiled_memory(fn, *(jax.ShapeDtypeStruct(s, dtype) for s in shapes))


# --------------------------------------------------------------------------- report


def _row(c: Comparison) -> list[str]:
    if c.dense.skipped:
        dense = f"not run (1 point took {c.dense.times_s[0]:.1f} s)"
        ratio, rel = "-", "-"
    else:
        dense = f"{fmt_ms(c.dense.per_point_s)} ({c.dense.indices.size} pts)"
        ratio, rel = fmt_times(c.ratio), f"{c.rel_diff:.1e}"
    gain = np.median(np.asarray(c.jax.result.gain))
    jax_pp, compile_s = fmt_us(c.jax.per_point_s), f"{c.jax.compile_s:.1f}"
    return [str(c.F), str(c.k), str(c.N), jax_pp, compile_s, dense, ratio, rel, f"{gain:.2f}"]


ROW_HEADER = (
    "F|k|N|jaxtraj [us/point]|compile [s] (0: cached)|dense lstsq [ms/point] (subset)|"
    "speed-up|max rel. diff of coeffs|median gain"
).split("|")


def section_main(cfg: Config, log) -> list[str]:
    F, k, N = cfg.main
    scene = make_scene(F, k, N, seed=0)
    trials = []
    for t in range(cfg.trials):
        jr = run_jaxtraj(scene, jnp.float64, repeats=cfg.repeats)
        dr = run_dense(scene, cfg.dense_max_points, cfg.dense_budget_s)
        trials.append(Comparison(F, k, N, jr, dr))
        log(
            f"main trial {t + 1}: jaxtraj {fmt_us(jr.per_point_s)} us/pt, dense "
            f"{fmt_ms(dr.per_point_s)} ms/pt, ratio {fmt_times(trials[-1].ratio)}"
        )
    ratios = np.array([c.ratio for c in trials])
    med = float(np.median(ratios))
    parts = dense_breakdown(scene)
    res = trials[-1].jax.result
    kernel = run_kernel(scene, jnp.float64, repeats=cfg.repeats)
    kernel_fast = run_kernel(scene, jnp.float64, repeats=cfg.repeats, diagnostics=False)
    jax_pp = float(np.median([c.jax.per_point_s for c in trials]))
    dense_pp = float(np.median([c.dense.per_point_s for c in trials]))
    blas = os.environ.get("OPENBLAS_NUM_THREADS", "?")
    other = 2 if blas == "1" else 1
    child = dense_in_child(F, k, N, other, cfg)
    child_txt = (
        "failed"
        if child is None
        else f"{fmt_ms(child)} ms per point, i.e. jaxtraj is {fmt_times(child / jax_pp)} faster"
    )
    log(
        f"main: kernel only {fmt_us(kernel)} us/pt (no gain: {fmt_us(kernel_fast)}); "
        f"dense with {other} BLAS threads: {child_txt}"
    )
    lines = [
        f"## Main case: F = {F}, k = {k}, N = {N} points, float64",
        "",
        f"**Speed-up per point: {fmt_times(med)}** (median of {cfg.trials} trial(s); "
        f"min {fmt_times(ratios.min())}, max {fmt_times(ratios.max())}; target >= 100x).",
        "",
        markdown_table(
            ["trial", *ROW_HEADER[3:]], [[str(i + 1), *_row(c)[3:]] for i, c in enumerate(trials)]
        ),
        "",
        f"jaxtraj: all {N} points per call, warm median of {cfg.repeats} calls of the public "
        "`reconstruct_points` (host-side input validation included; compile time excluded "
        "and listed separately). Baseline: per point, median over the subset.",
        "",
        f"The jitted kernel alone (`jax.jit(jax.vmap(reconstruct))`, no host-side "
        f"validation): {fmt_us(kernel)} us per point, "
        f"{fmt_times(dense_pp / kernel)} faster than the baseline. With "
        f"`diagnostics=False` (no conditioning gain; singular systems still flagged): "
        f"{fmt_us(kernel_fast)} us per point, {fmt_times(dense_pp / kernel_fast)} faster.",
        "",
        f"The baseline above uses OpenBLAS with {blas} thread(s) "
        "(`OPENBLAS_NUM_THREADS`, set to 1 by this script unless given). The same baseline "
        f"with {other} BLAS thread(s), timed in a child process on the same scene: "
        f"{child_txt}. The baseline is embarrassingly parallel over points, so on idle "
        "cores one process per core would raise its throughput by up to the core count.",
        "",
        "Dense baseline breakdown (median per point, first 50 points): "
        + ", ".join(f"{name} {fmt_ms(s)} ms" for name, s in parts.items())
        + f". `Theta` ({3 * F} x {3 * k}) is built once and shared, outside the timing.",
        "",
        f"Solution quality (jaxtraj, all points): status OK {int(np.sum(res.status == 0))}/{N}, "
        f"median gain {np.median(res.gain):.2f}, median reprojection RMS "
        f"{np.median(res.rms_px):.2f} px, median 3D error vs truth "
        f"{1e3 * np.median(np.linalg.norm(res.points - scene.points, axis=-1)):.2f} mm.",
        "",
    ]
    return lines


def structured_rows(scene: Scene, cfg: Config, log) -> list[str]:
    """``reconstruct_points`` (with status) against the vectorised-NumPy structured baseline,
    float64 and float32, interleaved in this process (median of the trials' ratios)."""
    N = scene.uv.shape[0]
    rows, ratios = [], {}
    for dtype, npdtype in ((jnp.float64, np.float64), (jnp.float32, np.float32)):
        name = np.dtype(npdtype).name
        pairs = []
        for _ in range(cfg.trials):
            jr = run_jaxtraj(scene, dtype, repeats=cfg.repeats)
            nps = time_numpy_structured(scene, repeats=cfg.repeats, dtype=npdtype)
            pairs.append((jr.per_point_s, nps))
        jax_pp = float(np.median([a for a, _ in pairs]))
        np_pp = float(np.median([b for _, b in pairs]))
        ratio = float(np.median([b / a for a, b in pairs]))
        ratios[name] = ratio
        ok = int(np.sum(np.asarray(jr.result.status) == 0))
        ref = numpy_structured(*(np.asarray(x, npdtype) for x in (scene.P, scene.uv, scene.basis)))
        rel = relative_difference(np.asarray(jr.result.coeffs, np.float64), ref.astype(np.float64))
        rows.append(
            [name, fmt_us(jax_pp), fmt_us(np_pp), fmt_times(ratio), f"{ok}/{N}", f"{rel:.1e}"]
        )
        log(f"structured NumPy {name}: jaxtraj {fmt_us(jax_pp)} us/pt, NumPy {fmt_us(np_pp)}")
    header = [
        "dtype",
        "reconstruct_points with status [us/point]",
        "vectorised NumPy structured [us/point]",
        "speed-up",
        "status OK",
        "max rel. diff of coeffs",
    ]
    return [
        "Against the vectorised-NumPy structured baseline (`numpy_structured`: the same "
        "normal equations by einsum and one matrix product, one batched "
        "`numpy.linalg.solve`; no refinement, no degeneracy test), all points, "
        "interleaved trials in this process, medians:",
        "",
        markdown_table(header, rows),
        "",
    ]


def section_structured(cfg: Config, log) -> list[str]:
    """The issue-23 figures alone: ``reconstruct_points`` with status against the
    vectorised-NumPy baseline (float64, float32) and the cost of the degeneracy test."""
    F, k, N = cfg.main
    scene = make_scene(F, k, N, seed=0)
    lines = [f"## Structured baseline and gain cost: F = {F}, k = {k}, N = {N}", ""]
    lines += structured_rows(scene, cfg, log)
    P, uv, basis = _inputs(scene, jnp.float64)
    with_gain, without = [], []
    for _ in range(cfg.trials):
        for diag, out in ((True, with_gain), (False, without)):
            fn = lambda d=diag: reconstruct_points(P, uv, basis, diagnostics=d)  # noqa: E731
            out.append(time_call(fn, repeats=cfg.repeats).median / N)
    extra = float(np.median([a / b - 1.0 for a, b in zip(with_gain, without, strict=True)]))
    log(f"gain: {fmt_us(np.median(with_gain))} vs {fmt_us(np.median(without))} us/pt")
    lines += [
        f"`reconstruct_points` float64 with the conditioning-gain bound "
        f"{fmt_us(float(np.median(with_gain)))} us per point, with `diagnostics=False` "
        f"{fmt_us(float(np.median(without)))} us: the gain costs {100 * extra:.0f} % of the "
        "solve (median of interleaved trials).",
        "",
    ]
    return lines


def section_scaling(cfg: Config, log) -> list[str]:
    F0, k0, N0 = cfg.main
    lines = []
    for title, cases in (
        (f"Scaling with F (k = {k0}, N = {N0})", [(F, k0, N0) for F in cfg.Fs]),
        (f"Scaling with k (F = {F0}, N = {N0})", [(F0, k, N0) for k in cfg.ks]),
        (f"Scaling with N (F = {F0}, k = {k0})", [(F0, k0, N) for N in cfg.Ns]),
    ):
        rows = []
        for F, k, N in cases:
            c = compare(F, k, N, cfg, dense_budget_s=min(cfg.dense_budget_s, 2.0))
            rows.append(_row(c))
            log(
                f"{title}: F={F} k={k} N={N}: {fmt_us(c.jax.per_point_s)} us/pt, ratio "
                f"{'-' if c.dense.skipped else fmt_times(c.ratio)}"
            )
        lines += [f"## {title}", "", markdown_table(ROW_HEADER, rows), ""]
    lines += [
        "The baseline runs on an evenly spaced subset of the points, sized to about "
        f"{min(cfg.dense_budget_s, 2.0):.0f} s per case (at least 3 points); it is skipped "
        f"when one point takes more than {cfg.dense_cap_s:.0f} s.",
        "",
    ]
    return lines


def section_precision(cfg: Config, log) -> list[str]:
    F, k, N = cfg.main
    scene = make_scene(F, k, N, seed=0)
    r64 = run_jaxtraj(scene, jnp.float64, repeats=cfg.repeats)
    r32 = run_jaxtraj(scene, jnp.float32, repeats=cfg.repeats)
    p64, p32 = r64.result.points, r32.result.points.astype(np.float64)
    dev = np.linalg.norm(p32 - p64, axis=-1)  # (N, F)
    rel = np.linalg.norm((p32 - p64).reshape(N, -1), axis=1) / np.linalg.norm(
        p64.reshape(N, -1), axis=1
    )
    err64 = np.linalg.norm(p64 - scene.points, axis=-1)
    err32 = np.linalg.norm(p32 - scene.points, axis=-1)
    log(f"float32: {fmt_us(r32.per_point_s)} us/pt vs float64 {fmt_us(r64.per_point_s)} us/pt")
    rows = []
    for name, r, err in (("float64", r64, err64), ("float32", r32, err32)):
        res = r.result
        ok = int(np.sum(res.status == 0))
        rows.append(
            f"{name}|{fmt_us(r.per_point_s)}|{r.compile_s:.1f}|{ok}/{N}|{np.median(res.gain):.3f}|"
            f"{1e3 * np.median(err):.3f}|{1e3 * np.max(err):.3f}".split("|")
        )
    header = (
        "dtype|jaxtraj [us/point]|compile [s]|status OK|median gain|"
        "median error vs truth [mm]|max error vs truth [mm]"
    ).split("|")
    return [
        f"## float32 vs float64 (F = {F}, k = {k}, N = {N})",
        "",
        markdown_table(header, rows),
        "",
        f"float32 answer vs the float64 answer: points differ by median "
        f"{1e6 * np.median(dev):.2f} um, max {1e6 * np.max(dev):.2f} um; per-trajectory "
        f"relative difference median {np.median(rel):.1e}, max {np.max(rel):.1e} "
        f"(float32 eps = {np.finfo(np.float32).eps:.1e}). Speed-up of float32 over float64: "
        f"{r64.per_point_s / r32.per_point_s:.2f}x.",
        "",
    ]


MEMORY_HEADER = (
    "F|jaxtraj arguments [MiB]|jaxtraj outputs [MiB]|jaxtraj temp [MiB]|"
    "jaxtraj temp per point [KiB]|dense Q per point [MiB] (2F x 3F x 8 B)|"
    "dense A per point [MiB]|compile [s]"
).split("|")


def section_memory(cfg: Config, log) -> list[str]:
    _, k, N = cfg.main
    rows = []
    for F in cfg.Fs:
        m = kernel_memory(F, k, N)
        dense_q = 2 * F * 3 * F * 8
        dense_a = 2 * F * 3 * k * 8
        cells = [fmt_mib(m["argument"]), fmt_mib(m["output"]), fmt_mib(m["temp"])]
        cells += [f"{m['temp'] / N / 1024:.1f}", fmt_mib(dense_q), fmt_mib(dense_a)]
        rows.append([str(F), *cells, f"{m['compile_s']:.1f}"])
        log(f"memory F={F}: temp {fmt_mib(m['temp'])} MiB for {N} points")
    return [
        f"## Memory (k = {k}, N = {N}, float64)",
        "",
        "XLA's `memory_analysis()` of the compiled batched kernel (`jax.jit(jax.vmap(reconstruct))`"
        ", the computation `reconstruct_points` runs) for all N points, against the dense "
        "matrices the baseline allocates for each single point.",
        "",
        markdown_table(MEMORY_HEADER, rows),
        "",
        "jaxtraj's memory grows linearly in F (inputs, outputs and per-frame 3x3 blocks); the "
        "dense Q grows with F^2.",
        "",
    ]


def run_all(cfg: Config, log=lambda msg: None) -> str:
    """Run every section and return the markdown report."""
    started = time.perf_counter()
    header = [
        "# Benchmark: batched structured solver vs dense least squares",
        "",
        f"Generated by `benchmarks/bench_solve.py` on {datetime.date.today().isoformat()}.",
        "",
        f"Machine at start: {machine_info()}.",
        "",
        "The CPU is shared with other users' jobs, so absolute times are noisy; the main "
        "comparison is repeated and its spread reported. Both solvers run in the same "
        "process on the same data. Scenes: N points on a cloud (radius 0.1 m) moving "
        "rigidly plus a few mm non-rigidly along a smooth path; F random camera poses "
        "0.5-1.5 m from the cloud centre looking at it; 640x480 pinhole camera "
        "(f = 525 px); 0.3 px pixel noise; orthonormal DCT basis.",
        "",
    ]
    body = []
    body += section_main(cfg, log)
    body += section_structured(cfg, log)
    body += section_scaling(cfg, log)
    body += section_precision(cfg, log)
    body += section_memory(cfg, log)
    footer = [
        f"Total benchmark time {time.perf_counter() - started:.0f} s. Machine at end: "
        f"{machine_info()}.",
        "",
    ]
    return "\n".join(header + body + footer)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes: a smoke run")
    parser.add_argument("--out", type=Path, default=None, help="write the markdown report here")
    parser.add_argument("--dense-child", default=None, help=argparse.SUPPRESS)
    parser.add_argument(
        "--structured-only",
        action="store_true",
        help="only the structured-NumPy comparison and the gain cost of the main case",
    )
    parser.add_argument(
        "--stress",
        type=int,
        default=0,
        metavar="REPEATS",
        help="only run REPEATS batched solves of the main case back to back (a hang check)",
    )
    add_watchdog_option(parser)
    args = parser.parse_args(argv)
    if args.dense_child is not None:
        _dense_child(args.dense_child)
        return 0
    start_watchdog(args.watchdog)
    log = stderr_logger("bench_solve")
    if args.stress:
        import jaxlib

        F, k, N = (QUICK if args.quick else FULL).main
        log(f"jax {jax.__version__}, jaxlib {jaxlib.__version__}; F={F} k={k} N={N}")
        stress(make_scene(F, k, N, seed=0), args.stress, log)
        faulthandler.cancel_dump_traceback_later()
        return 0

    cfg = QUICK if args.quick else FULL
    if args.structured_only:
        import jaxlib

        report = "\n".join(
            [
                f"jax {jax.__version__}, jaxlib {jaxlib.__version__}; {machine_info()}",
                "",
                *section_structured(cfg, log),
            ]
        )
    else:
        report = run_all(cfg, log)
    print(report)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(report)
        log(f"wrote {args.out}")
    faulthandler.cancel_dump_traceback_later()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

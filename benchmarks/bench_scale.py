"""Benchmark: scale-out throughput (chunked from disk, sharded over host devices) and memory.

Measures on CPU, for a realistic problem (F = 150 images, k = 10 DCT vectors):

1. Throughput (point trajectories per second) of :func:`jaxtraj.scale.run_batch` against
   the number of devices (1, 2, 4 forced host devices, each count in its own subprocess
   with ``XLA_FLAGS=--xla_force_host_platform_device_count=D`` set before JAX starts) and
   against the chunk size, in float64 and (one chunk size) float32; next to it the
   in-memory :func:`jaxtraj.scale.reconstruct_sharded` rate on the same tracks.
2. Peak resident memory (``ru_maxrss`` of the worker process) of ``run_batch`` against
   the dataset size, at a fixed chunk size: it should not grow with N.

Usage::

    python benchmarks/bench_scale.py [--quick] [--out benchmarks/results/scale.md]

The dataset is written to disk once, in blocks (never all N tracks in memory), under a
temporary folder (``--workdir``) that is deleted at the end. Float64 is enabled below (a
benchmark script may do so; library code never does).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import faulthandler
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (  # noqa: E402
    add_watchdog_option,
    block,
    machine_info,
    markdown_table,
    start_watchdog,
    stderr_logger,
)

from jaxtraj.basis import dct_basis  # noqa: E402
from jaxtraj.scale import point_mesh, reconstruct_sharded, run_batch, write_dataset  # noqa: E402

SCRIPT = Path(__file__).resolve()


@dataclasses.dataclass(frozen=True)
class Config:
    """Problem sizes of one benchmark run."""

    F: int = 150
    k: int = 10
    n: int = 32768  # points of the throughput dataset (65536 took too long on 2 loaded cores)
    devices: tuple[int, ...] = (1, 2, 4)
    chunks: tuple[int, ...] = (512, 2048, 8192)
    f32_chunk: int | None = 2048  # float32 is also run at this chunk size (None: not run)
    repeats: int = 2  # full passes over the dataset per configuration (median reported)
    in_memory_repeats: int = 2
    memory_ns: tuple[int, ...] = (16384, 65536, 262144)
    memory_chunk: int = 4096
    missing: float = 0.05  # fraction of detections that are NaN (missing)
    noise_px: float = 0.3
    seed: int = 0
    block: int = 4096  # points generated and written at a time
    samples: int = 64  # evenly spaced points compared across configurations
    timeout_s: float = 900.0  # per worker subprocess


FULL = Config()
QUICK = Config(
    F=30,
    k=5,
    n=1024,
    chunks=(256, 1024),
    f32_chunk=1024,
    repeats=1,
    in_memory_repeats=1,
    memory_ns=(1024, 4096),
    memory_chunk=512,
    block=512,
    samples=16,
)


# --------------------------------------------------------------------------- dataset


def camera_path(rng: np.random.Generator, F: int) -> tuple[np.ndarray, np.ndarray]:
    """Random camera path as in ``tests/_scale_worker.many_points``: P (F, 3, 4), times (F,).

    Camera centres are drawn in a 1.2 m cube around (0, 0, 1.5) m, each camera looks at
    the origin (x axis horizontal), intrinsics f = 700 px, principal point (320, 240);
    times are sorted uniform draws over F / 30 s (30 images per second on average).
    """
    times = np.sort(rng.uniform(0.0, F / 30.0, F))
    C = rng.uniform(-1, 1, (F, 3)) * 0.6 + np.array([0.0, 0.0, 1.5])
    K = np.array([[700.0, 0, 320], [0, 700.0, 240], [0, 0, 1]])
    P = []
    for c in C:
        z = -c / np.linalg.norm(c)
        x = np.cross(z, [0, 1.0, 0])
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        P.append(K @ np.c_[R, -R @ c])
    return np.asarray(P), times


def _blocks(cfg: Config, n: int, P: np.ndarray, basis: np.ndarray, rng: np.random.Generator):
    """Yield (tracks (b, F, 2) with NaN for missing, true points (b, F, 3)) blocks."""
    F, k = basis.shape
    for a in range(0, n, cfg.block):
        b = min(n, a + cfg.block)
        X = np.einsum("fk,nkc->nfc", basis, rng.normal(size=(b - a, k, 3)) * 0.1)
        h = np.einsum("fij,nfj->nfi", P[:, :, :3], X) + P[:, :, 3]
        uv = h[..., :2] / h[..., 2:] + rng.normal(0, cfg.noise_px, (b - a, F, 2))
        uv[rng.uniform(size=(b - a, F)) < cfg.missing] = np.nan
        yield uv, X


def make_dataset(folder: Path, n: int, cfg: Config, samples: np.ndarray | None = None) -> dict:
    """Write an N-point dataset (cameras.npz, float64 tracks.npy) block by block.

    Args:
        folder: dataset folder (created).
        n: number of point tracks.
        cfg: sizes, noise, missing fraction and seed.
        samples: optional point indices whose true trajectories are kept (for accuracy).

    Returns:
        ``{"tracks_bytes", "seconds", "truth"}`` with truth (len(samples), F, 3) [m] or None.
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(cfg.seed)
    P, times = camera_path(rng, cfg.F)
    basis = np.asarray(dct_basis(jnp.asarray(times), cfg.k))
    write_dataset(folder, P, times, np.zeros((0, cfg.F, 2)))
    truth = None if samples is None else np.zeros((len(samples), cfg.F, 3))
    path = Path(folder) / "tracks.npy"
    header = {"descr": "<f8", "fortran_order": False, "shape": (n, cfg.F, 2)}
    with open(path, "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, header)
        a = 0
        for uv, X in _blocks(cfg, n, P, basis, rng):
            np.ascontiguousarray(uv, np.float64).tofile(fh)
            if samples is not None:
                inside = (samples >= a) & (samples < a + len(uv))
                truth[inside] = X[samples[inside] - a]
            a += len(uv)
    return {
        "tracks_bytes": path.stat().st_size,
        "seconds": time.perf_counter() - t0,
        "truth": truth,
    }


def sample_indices(n: int, count: int) -> np.ndarray:
    """``count`` evenly spaced point indices in [0, n)."""
    return np.unique(np.linspace(0, n - 1, min(count, n)).round().astype(np.int64))


def output_bytes(n: int, F: int, k: int) -> int:
    """Bytes of run_batch's output files for n points (float64 points/coeffs, ...)."""
    return n * (F * 3 * 8 + k * 3 * 8 + 8 + 8 + 4)


# --------------------------------------------------------------------------- workers


def _peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB


def _throughput_worker(spec: dict) -> dict:
    """In a subprocess with D forced host devices: time run_batch and reconstruct_sharded."""
    ds, work, k = Path(spec["dataset"]), Path(spec["work"]), spec["k"]
    samples = np.asarray(spec["samples"], np.int64)
    D = len(jax.devices())
    mesh = point_mesh() if D > 1 else None
    with open(ds / "tracks.npy", "rb") as fh:
        np.lib.format.read_magic(fh)
        n = np.lib.format.read_array_header_1_0(fh)[0][0]
    runs = []
    for run in spec["runs"]:
        c, name = run["chunk"], run["dtype"]
        dtype = {"float64": jnp.float64, "float32": jnp.float32}[name]
        warm = run_batch(
            ds, work / f"warm-{c}-{name}", k=k, chunk_size=c, mesh=mesh, max_chunks=1, dtype=dtype
        )
        seconds, summary = [], None
        for _ in range(spec["repeats"]):
            summary = run_batch(
                ds, work / f"run-{c}-{name}", k=k, chunk_size=c, mesh=mesh, restart=True,
                dtype=dtype,
            )  # fmt: skip
            seconds.append(summary.seconds)
        points = np.load(work / f"run-{c}-{name}" / "points.npy", mmap_mode="r")
        sample = np.array(points[samples])
        del points
        shutil.rmtree(work / f"warm-{c}-{name}")
        shutil.rmtree(work / f"run-{c}-{name}")
        runs.append(
            {
                "chunk": c,
                "dtype": name,
                "first_chunk_s": warm.seconds,
                "seconds": seconds,
                "chunks": summary.chunks,
                "computed": summary.computed,
                "status_counts": summary.status_counts,
                "sample": sample.tolist(),
            }
        )
    peak_chunked = _peak_mib()
    in_memory = None
    if spec["in_memory_repeats"] > 0:
        raw = np.load(ds / "tracks.npy")
        finite = np.all(np.isfinite(raw), axis=-1)
        uv = np.where(finite[..., None], raw, 0.0)
        del raw
        w = finite.astype(np.float64)
        with np.load(ds / "cameras.npz") as z:
            P, times = z["P"], z["times"]
        basis = dct_basis(jnp.asarray(times), k)
        mesh1 = point_mesh()

        def call():
            return block(reconstruct_sharded(P, uv, basis, w, mesh=mesh1))

        t0 = time.perf_counter()
        res = call()
        first = time.perf_counter() - t0
        seconds = []
        for _ in range(spec["in_memory_repeats"]):
            t0 = time.perf_counter()
            res = call()
            seconds.append(time.perf_counter() - t0)
        status = np.asarray(res.status)
        in_memory = {
            "first_s": first,
            "seconds": seconds,
            "shards": len(res.points.sharding.device_set),
            "ok": int(np.sum(status == 0)),
            "sample": np.asarray(res.points)[samples].tolist(),
        }
    return {
        "devices": D,
        "points": int(n),
        "runs": runs,
        "in_memory": in_memory,
        "peak_chunked_mib": peak_chunked,
        "peak_mib": _peak_mib(),
    }


def _memory_worker(spec: dict) -> dict:
    """In a subprocess: peak RSS of one run_batch pass over the dataset."""
    before = _peak_mib()
    summary = run_batch(spec["dataset"], spec["out"], k=spec["k"], chunk_size=spec["chunk"])
    return {
        "devices": len(jax.devices()),
        "before_mib": before,
        "peak_mib": _peak_mib(),
        "seconds": summary.seconds,
        "computed": summary.computed,
        "points": summary.points,
    }


def run_worker(spec: dict, devices: int = 1, timeout_s: float = 900.0) -> dict:
    """Run ``spec`` in a fresh Python with ``devices`` forced host devices (CPU only).

    Returns the worker's JSON answer plus ``wall_s`` (seconds, JAX start-up included).
    """
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    flag = f"--xla_force_host_platform_device_count={devices}"
    env["XLA_FLAGS"] = " ".join(
        [f for f in env.get("XLA_FLAGS", "").split() if "device_count" not in f] + [flag]
    )
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--worker", json.dumps(spec)],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"worker {spec['mode']} (D={devices}) failed:\n{proc.stderr[-3000:]}")
    answer = json.loads(proc.stdout.strip().splitlines()[-1])
    answer["wall_s"] = time.perf_counter() - t0
    return answer


def _worker_main(spec_json: str) -> None:
    spec = json.loads(spec_json)
    fn = {"throughput": _throughput_worker, "memory": _memory_worker}[spec["mode"]]
    print(json.dumps(fn(spec)))


# --------------------------------------------------------------------------- measurements


def measure(cfg: Config, workdir: Path, log=lambda msg: None) -> dict:
    """Run every measurement; returns the raw numbers (used by :func:`report`)."""
    started = time.perf_counter()
    workdir.mkdir(parents=True, exist_ok=True)
    samples = sample_indices(cfg.n, cfg.samples)
    ds = workdir / "ds-throughput"
    log(f"writing dataset: N = {cfg.n}, F = {cfg.F}")
    gen = make_dataset(ds, cfg.n, cfg, samples)
    runs = [{"chunk": c, "dtype": "float64"} for c in cfg.chunks]
    if cfg.f32_chunk is not None:
        runs.append({"chunk": cfg.f32_chunk, "dtype": "float32"})
    throughput = {}
    for D in cfg.devices:
        log(f"throughput worker, {D} device(s)")
        spec = {
            "mode": "throughput",
            "dataset": str(ds),
            "work": str(workdir / f"work-{D}"),
            "k": cfg.k,
            "runs": [r for r in runs if r["chunk"] % D == 0],
            "repeats": cfg.repeats,
            "in_memory_repeats": cfg.in_memory_repeats,
            "samples": samples.tolist(),
        }
        throughput[D] = run_worker(spec, D, cfg.timeout_s)
        shutil.rmtree(workdir / f"work-{D}", ignore_errors=True)
    shutil.rmtree(ds)
    memory = {}
    for n in cfg.memory_ns:
        log(f"memory worker, N = {n}")
        mds, out = workdir / f"ds-{n}", workdir / f"out-{n}"
        mgen = make_dataset(mds, n, cfg)
        spec = {"mode": "memory", "dataset": str(mds), "out": str(out), "k": cfg.k}
        memory[n] = run_worker({**spec, "chunk": cfg.memory_chunk}, 1, cfg.timeout_s)
        memory[n]["tracks_bytes"] = mgen["tracks_bytes"]
        memory[n]["output_bytes"] = sum(f.stat().st_size for f in out.glob("*.npy"))
        shutil.rmtree(mds)
        shutil.rmtree(out)
    return {
        "config": dataclasses.asdict(cfg),
        "generate": {"tracks_bytes": gen["tracks_bytes"], "seconds": gen["seconds"]},
        "truth": gen["truth"],
        "throughput": throughput,
        "memory": memory,
        "seconds": time.perf_counter() - started,
    }


def _rate(n: int, seconds) -> float:
    return n / float(np.median(seconds))


def _max_diff(sample, reference) -> float:
    return float(np.max(np.abs(np.asarray(sample) - np.asarray(reference))))


def summarise(raw: dict) -> dict:
    """Derived numbers: rates [points/s], differences to the reference run [m], errors."""
    cfg = raw["config"]
    n = cfg["n"]
    ref_d = min(raw["throughput"])
    ref = next(r for r in raw["throughput"][ref_d]["runs"] if r["dtype"] == "float64")
    truth = raw["truth"]
    rows, mem_rows = [], []
    for D, t in sorted(raw["throughput"].items()):
        for r in t["runs"]:
            base = next(
                (
                    b
                    for b in raw["throughput"][ref_d]["runs"]
                    if b["chunk"] == r["chunk"] and b["dtype"] == r["dtype"]
                ),
                None,
            )
            err = np.linalg.norm(np.asarray(r["sample"]) - truth, axis=-1)
            rows.append(
                {
                    "devices": D,
                    "chunk": r["chunk"],
                    "dtype": r["dtype"],
                    "first_chunk_s": r["first_chunk_s"],
                    "rate": _rate(n, r["seconds"]),
                    "rates": [n / s for s in r["seconds"]],
                    "speedup": _rate(n, r["seconds"]) / _rate(n, base["seconds"])
                    if base
                    else float("nan"),
                    "max_diff_m": _max_diff(r["sample"], ref["sample"]),
                    "median_err_mm": 1e3 * float(np.median(err)),
                    "ok": r["status_counts"].get("0", r["status_counts"].get(0, 0)),
                    "chunks": r["chunks"],
                    "computed": r["computed"],
                }
            )
        m = t["in_memory"]
        if m is not None:
            mem_rows.append(
                {
                    "devices": D,
                    "shards": m["shards"],
                    "first_s": m["first_s"],
                    "rate": _rate(n, m["seconds"]),
                    "max_diff_m": _max_diff(m["sample"], ref["sample"]),
                    "ok": m["ok"],
                    "peak_mib": t["peak_mib"],
                    "peak_chunked_mib": t["peak_chunked_mib"],
                }
            )
    return {"throughput": rows, "in_memory": mem_rows}


def report(raw: dict, command: str, machine_start: str, machine_end: str) -> str:
    """The markdown report of one run of :func:`measure`."""
    cfg = raw["config"]
    s = summarise(raw)
    n, F, k = cfg["n"], cfg["F"], cfg["k"]
    lines = [
        "# Benchmark: scale-out throughput and memory (chunked + sharded, CPU)",
        "",
        f"Generated by `{command}` on {datetime.date.today().isoformat()}.",
        "",
        f"Machine at start: {machine_start}. Machine at end: {machine_end}.",
        "",
        f"**The machine has {os.cpu_count()} logical CPU(s) (2 physical cores on the "
        "development machine), shared with other jobs.** Forced host devices "
        "(`XLA_FLAGS=--xla_force_host_platform_device_count=D`) are threads on the same "
        "cores, so no gain is expected beyond 2 devices; 4 devices only show the sharding "
        "overhead. **GPU figures are not measured** (no GPU was available to this run).",
        "",
        f"Problem: F = {F} images, k = {k} DCT vectors, N = {n} points, one random camera "
        "path for all points (centres in a 1.2 m cube around (0, 0, 1.5) m, looking at the "
        f"origin, f = 700 px), random trajectories in the DCT span (0.1 m scale), "
        f"{cfg['noise_px']} px noise, {100 * cfg['missing']:.0f}% missing detections (NaN). "
        f"Tracks: float64 `tracks.npy` of {raw['generate']['tracks_bytes'] / 2**20:.0f} MiB, "
        f"written once in blocks of {cfg['block']} points "
        f"({raw['generate']['seconds']:.1f} s); outputs "
        f"{output_bytes(n, F, k) / 2**20:.0f} MiB per run.",
        "",
        "## Chunked processing (`run_batch`) vs devices and chunk size",
        "",
        "Each device count runs in its own subprocess. Per configuration: one warm-up "
        "`run_batch(..., max_chunks=1)` into a separate folder (trace + compile + one "
        "chunk: the *first chunk* column), then "
        f"{cfg['repeats']} full pass(es) over all N points with `restart=True`; the rate is "
        "N / median `BatchSummary.seconds` (read, solve, write and fsync of every chunk; "
        "no compilation). D = 1 runs without a mesh, D > 1 shards each chunk over "
        "`point_mesh()`. *max diff* is the largest coordinate difference of "
        f"{cfg['samples']} sampled trajectories to the float64 run on "
        f"{min(raw['throughput'])} device(s) with chunk {cfg['chunks'][0]}; *error* is the "
        "median 3D distance of the sampled trajectories to the truth.",
        "",
    ]
    header = [
        "devices",
        "chunk",
        "dtype",
        "first chunk [s]",
        "points/s (median)",
        "us/point",
        "points/s per pass",
        "vs 1 device",
        "max diff [m]",
        "error [mm]",
        "status OK",
    ]
    rows = [
        [
            r["devices"],
            r["chunk"],
            r["dtype"],
            f"{r['first_chunk_s']:.2f}",
            f"{r['rate']:.0f}",
            f"{1e6 / r['rate']:.1f}",
            ", ".join(f"{x:.0f}" for x in r["rates"]),
            f"{r['speedup']:.2f}x",
            f"{r['max_diff_m']:.1e}",
            f"{r['median_err_mm']:.2f}",
            f"{r['ok']}/{n}",
        ]
        for r in s["throughput"]
    ]
    lines += [markdown_table(header, rows), ""]
    if s["in_memory"]:
        lines += [
            "## In-memory `reconstruct_sharded` (same tracks, for comparison)",
            "",
            "All N points in one call (tracks loaded with `np.load`, NaN replaced by weight "
            "0), sharded over all devices of the worker; first call (trace + compile + run; no "
            "compile if a chunk of N points was compiled before) listed separately; rate = "
            "N / median of "
            f"{cfg['in_memory_repeats']} warm call(s). Peak RSS: the worker's `ru_maxrss` "
            "after the chunked runs and after the in-memory calls.",
            "",
        ]
        best = {}
        for r in s["throughput"]:
            if r["dtype"] == "float64":
                best[r["devices"]] = max(best.get(r["devices"], 0.0), r["rate"])
        header = [
            "devices",
            "shards",
            "first call [s]",
            "points/s",
            "us/point",
            "vs best chunked",
            "max diff [m]",
            "status OK",
            "peak RSS chunked [MiB]",
            "peak RSS in-memory [MiB]",
        ]
        rows = [
            [
                m["devices"],
                m["shards"],
                f"{m['first_s']:.2f}",
                f"{m['rate']:.0f}",
                f"{1e6 / m['rate']:.1f}",
                f"{m['rate'] / best[m['devices']]:.2f}x",
                f"{m['max_diff_m']:.1e}",
                f"{m['ok']}/{n}",
                f"{m['peak_chunked_mib']:.0f}",
                f"{m['peak_mib']:.0f}",
            ]
            for m in s["in_memory"]
        ]
        lines += [markdown_table(header, rows), ""]
    lines += [
        f"## Peak memory of `run_batch` vs dataset size (chunk {cfg['memory_chunk']}, "
        "1 device, float64)",
        "",
        "One subprocess per N; `ru_maxrss` of the worker before the run (after JAX start-up) "
        "and after it. Each dataset is written in blocks by the parent process beforehand.",
        "",
    ]
    header = [
        "N",
        "tracks.npy [MiB]",
        "outputs [MiB]",
        "RSS before [MiB]",
        "peak RSS [MiB]",
        "peak - before [MiB]",
        "points/s",
    ]
    rows = [
        [
            nn,
            f"{m['tracks_bytes'] / 2**20:.0f}",
            f"{m['output_bytes'] / 2**20:.0f}",
            f"{m['before_mib']:.0f}",
            f"{m['peak_mib']:.0f}",
            f"{m['peak_mib'] - m['before_mib']:.0f}",
            f"{m['points'] / m['seconds']:.0f}",
        ]
        for nn, m in sorted(raw["memory"].items())
    ]
    peaks = [m["peak_mib"] for m in raw["memory"].values()]
    sizes = [m["tracks_bytes"] + m["output_bytes"] for m in raw["memory"].values()]
    lines += [
        markdown_table(header, rows),
        "",
        f"Peak RSS range {min(peaks):.0f}-{max(peaks):.0f} MiB while the data on disk grows "
        f"from {min(sizes) / 2**20:.0f} to {max(sizes) / 2**20:.0f} MiB "
        "(the rate of these single runs includes the first chunk's compilation).",
        "",
        f"Total benchmark time {raw['seconds']:.0f} s.",
        "",
    ]
    return "\n".join(lines)


def vs_kernel(cfg: Config, workdir: Path, chunks: tuple[int, ...], repeats: int, log) -> dict:
    """``run_batch`` and the ``jaxtraj batch`` command against the in-memory kernel, in one
    process on one dataset, with the time of each stage of a chunk (issue: batch
    throughput within 1.5x of the kernel).

    Per repeat, in turn: the public ``reconstruct_points`` on all N points at once and on
    chunks of each size (inputs already on the device: the kernel alone), ``run_batch``
    per chunk size (read, pad, solve, write, fsync, progress file), and the command
    ``jaxtraj batch`` (in this process, so JAX start-up is not counted; its own rate
    includes the first chunk's compilation only on its first call). Medians over repeats.
    """
    from jaxtraj import reconstruct_points
    from jaxtraj.cli import main as cli_main
    from jaxtraj.scale.chunked import NpyRows, _solve_on_cores  # run_batch's masking, kernel
    from jaxtraj.solve import _per_step

    ds = workdir / "ds-vs-kernel"
    log(f"vs-kernel: writing dataset N = {cfg.n}, F = {cfg.F}")
    make_dataset(ds, cfg.n, cfg)
    raw = np.load(ds / "tracks.npy")
    finite = np.all(np.isfinite(raw), axis=-1)
    uv = jnp.asarray(np.where(finite[..., None], raw, 0.0))
    w = jnp.asarray(finite.astype(np.float64))
    del raw
    with np.load(ds / "cameras.npz") as z:
        P, times = jnp.asarray(z["P"]), jnp.asarray(z["times"])
    basis = dct_basis(times, cfg.k)
    n = cfg.n

    def kernel_all():
        return block(reconstruct_points(P, uv, basis, w))

    def kernel_chunks(c):
        parts = [(uv[a : a + c], w[a : a + c]) for a in range(0, n - n % c, c)]

        def run():
            for u, ww in parts:
                block(reconstruct_points(P, u, basis, ww))

        return run, len(parts) * c

    def batch_run(c):
        return run_batch(ds, workdir / f"vk-{c}", k=cfg.k, chunk_size=c, restart=True).seconds

    def cli_run(c):
        t0 = time.perf_counter()
        rc = cli_main(
            ["batch", str(ds), str(workdir / f"cli-{c}"), "--k", str(cfg.k),
             "--chunk-size", str(c), "--restart"]
        )  # fmt: skip
        if rc != 0:
            raise RuntimeError(f"jaxtraj batch exited {rc}")
        return time.perf_counter() - t0

    t0 = time.perf_counter()
    kernel_all()
    first_all = time.perf_counter() - t0
    timings = {"all": []}
    runners = {}
    for c in chunks:
        runners[c] = kernel_chunks(c)
        runners[c][0]()  # compile this shape
        batch_run(c)  # warm: run_batch's program is the same kernel, compiled once
        cli_run(c)
        timings |= {("kernel", c): [], ("batch", c): [], ("cli", c): []}
    for r in range(repeats):
        t0 = time.perf_counter()
        kernel_all()
        timings["all"].append(n / (time.perf_counter() - t0))
        for c in chunks:
            run, m = runners[c]
            t0 = time.perf_counter()
            run()
            timings[("kernel", c)].append(m / (time.perf_counter() - t0))
            timings[("batch", c)].append(n / batch_run(c))
            timings[("cli", c)].append(n / cli_run(c))
        log(f"vs-kernel repeat {r + 1}/{repeats} done")

    # Stage times of one serial pass (no overlap), per point, at the largest chunk size.
    c = max(chunks)
    per_step = _per_step(P)
    tracks = NpyRows(ds / "tracks.npy")
    stages = dict.fromkeys(("read", "pad", "mask and solve", "copy to host", "write", "fsync"), 0.0)
    outs = {name: NpyRows(workdir / f"vk-{c}" / f"{name}.npy", "r+b")
            for name in ("points", "coeffs", "rms_px", "gain", "status")}  # fmt: skip
    try:
        for a in range(0, n, c):
            b = min(n, a + c)
            t = [time.perf_counter()]
            chunk = tracks.read(a, b)
            t.append(time.perf_counter())
            ok = np.ones((b - a, cfg.F), chunk.dtype)  # the dataset has no weights file
            if b - a < c:
                chunk = np.concatenate([chunk, np.zeros((c - (b - a), cfg.F, 2), chunk.dtype)])
                ok = np.concatenate([ok, np.zeros((c - (b - a), cfg.F), ok.dtype)])
            t.append(time.perf_counter())
            res = block(_solve_on_cores(P, basis, chunk, ok, jnp.dtype(jnp.float64), per_step))
            t.append(time.perf_counter())
            res = jax.device_get(res)
            t.append(time.perf_counter())
            for name, f in outs.items():
                f.write(a, getattr(res, name)[: b - a])
            t.append(time.perf_counter())
            for f in outs.values():
                f.flush()
            t.append(time.perf_counter())
            for key, t1, t2 in zip(stages, t[:-1], t[1:], strict=True):
                stages[key] += t2 - t1
    finally:
        for f in (tracks, *outs.values()):
            f.close()
    med = {key: float(np.median(v)) for key, v in timings.items()}
    return {
        "n": n,
        "F": cfg.F,
        "k": cfg.k,
        "chunks": list(chunks),
        "repeats": repeats,
        "first_all_s": first_all,
        "rates": {str(key): v for key, v in med.items()},
        "rates_all": {str(key): v for key, v in timings.items()},
        "stage_chunk": c,
        "stages_us": {key: v / n * 1e6 for key, v in stages.items()},
    }


def vs_kernel_report(raw: dict, command: str, machine_start: str, machine_end: str) -> str:
    rates = raw["rates"]
    best = max([rates["all"]] + [rates[str(("kernel", c))] for c in raw["chunks"]])
    rows = [["kernel, all N points in one call", "-", f"{rates['all']:.0f}",
             f"{1e6 / rates['all']:.1f}", f"{rates['all'] / best:.2f}"]]  # fmt: skip
    for c in raw["chunks"]:
        for key, label in (("kernel", "kernel, chunks in memory"), ("batch", "`run_batch`"),
                           ("cli", "`jaxtraj batch` (in process)")):  # fmt: skip
            v = rates[str((key, c))]
            rows.append([label, c, f"{v:.0f}", f"{1e6 / v:.1f}", f"{v / best:.2f}"])
    stage_rows = [[k, f"{v:.2f}"] for k, v in raw["stages_us"].items()]
    return "\n".join(
        [
            "# Benchmark: `jaxtraj batch` against the in-memory kernel",
            "",
            f"Generated by `{command}` on {datetime.date.today().isoformat()}.",
            "",
            f"Machine at start: {machine_start}. Machine at end: {machine_end}.",
            "",
            f"One process, one device, float64; N = {raw['n']} points, F = {raw['F']}, "
            f"k = {raw['k']}; dataset as in `bench_scale.py` (random camera path, 0.3 px, 5 % "
            f"missing). Rates are medians of {raw['repeats']} repeats, taken in turn so that "
            "load changes hit every row alike; compilation is excluded everywhere (first "
            f"call of the whole-N kernel: {raw['first_all_s']:.1f} s). The kernel is the "
            "public `reconstruct_points` with status on inputs already in memory; "
            "`run_batch` reads the tracks from disk, pads the last chunk, solves, writes the "
            "five output files, fsyncs them and records the chunk, with the next chunk's "
            "solve started (in a second thread) before the previous chunk is written. On a "
            "CPU both split each call's points over the cores (one thread per core).",
            "",
            markdown_table(["path", "chunk", "points/s", "us/point", "vs best kernel"], rows),
            "",
            f"Stages of one serial pass (no overlap) at chunk {raw['stage_chunk']}, "
            "microseconds per point:",
            "",
            markdown_table(["stage", "us/point"], stage_rows),
            "",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes: a smoke run")
    parser.add_argument("--out", type=Path, default=None, help="write the markdown report here")
    parser.add_argument("--workdir", type=Path, default=None, help="scratch folder (deleted)")
    parser.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    parser.add_argument(
        "--vs-kernel",
        action="store_true",
        help="only run_batch and `jaxtraj batch` against the in-memory kernel (one process)",
    )
    parser.add_argument("--repeats", type=int, default=5, help="repeats of --vs-kernel")
    add_watchdog_option(parser)
    args = parser.parse_args(argv)
    if args.worker is not None:
        _worker_main(args.worker)
        return 0
    start_watchdog(args.watchdog)
    log = stderr_logger("bench_scale")

    command = "python benchmarks/bench_scale.py" + (" --quick" if args.quick else "")
    if args.out is not None:
        command += f" --out {args.out}"
    start = machine_info()
    workdir = Path(tempfile.mkdtemp(prefix="bench_scale-", dir=args.workdir))
    try:
        if args.vs_kernel:
            base = QUICK if args.quick else FULL
            cfg = dataclasses.replace(base, n=base.n if args.quick else 16384)
            chunks = (256,) if args.quick else (512, 2048)
            command += f" --vs-kernel --repeats {args.repeats}"
            raw = vs_kernel(cfg, workdir, chunks, args.repeats, log)
        else:
            raw = measure(QUICK if args.quick else FULL, workdir, log)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    if args.vs_kernel:
        text = vs_kernel_report(raw, command, start, machine_info())
    else:
        text = report(raw, command, start, machine_info())
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
        log(f"wrote {args.out}")
    faulthandler.cancel_dump_traceback_later()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

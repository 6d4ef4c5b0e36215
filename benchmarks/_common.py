"""Shared helpers for the benchmarks: timing, a random robot-cell-like scene, a dense baseline.

Nothing here is part of the library. The scene generator is self-contained (it uses only
:mod:`jaxtraj.camera` and :mod:`jaxtraj.basis`) so that benchmarks do not depend on the
simulation package. Generate scenes with float64 enabled
(``jax.config.update("jax_enable_x64", True)`` in the benchmark script); the arrays come
back as NumPy float64 and a float32 run casts them.
"""

from __future__ import annotations

import argparse
import dataclasses
import faulthandler
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxtraj.basis import dct_basis
from jaxtraj.camera import look_at, project, projection_matrix

__all__ = [
    "DenseRun",
    "Scene",
    "Timing",
    "block",
    "compiled_memory",
    "dense_Q",
    "dense_breakdown",
    "dense_lstsq",
    "fmt_mib",
    "fmt_ms",
    "fmt_times",
    "fmt_us",
    "machine_info",
    "make_scene",
    "markdown_table",
    "pinhole_K",
    "relative_difference",
    "run_dense",
    "time_call",
]


# --------------------------------------------------------------------------- timing


@dataclasses.dataclass(frozen=True)
class Timing:
    """Wall-clock times of repeated calls [s]; ``first`` includes any compilation."""

    first: float
    runs: tuple[float, ...]

    @property
    def median(self) -> float:
        return statistics.median(self.runs)

    @property
    def spread(self) -> tuple[float, float]:
        """(min, max) of the warm runs."""
        return min(self.runs), max(self.runs)


def add_watchdog_option(parser: argparse.ArgumentParser, default: float = 1800.0) -> None:
    """``--watchdog SECONDS``: see :func:`start_watchdog`."""
    parser.add_argument(
        "--watchdog",
        type=float,
        default=default,
        help="abort with Python stack traces after this many seconds (0 disables)",
    )


def start_watchdog(seconds: float) -> None:
    """Stop a hung run with Python tracebacks after ``seconds`` (0: never); a benchmark
    cancels it with ``faulthandler.cancel_dump_traceback_later()`` when it is done."""
    if seconds > 0:
        faulthandler.dump_traceback_later(seconds, exit=True)


def stderr_logger(name: str) -> Callable[[str], None]:
    """A progress logger that prints ``[name] message`` to stderr at once."""

    def log(msg: str) -> None:
        print(f"[{name}] {msg}", file=sys.stderr, flush=True)

    return log


def block(x):
    """``block_until_ready`` on every JAX array leaf of ``x``; returns ``x``."""
    for leaf in jax.tree_util.tree_leaves(x):
        if hasattr(leaf, "block_until_ready"):
            leaf.block_until_ready()
    return x


def time_call(fn: Callable[[], object], repeats: int = 5, warmup: int = 1) -> Timing:
    """Time ``fn()`` (blocking on JAX results): the first call, then ``repeats`` warm calls.

    ``warmup`` counts the calls made before the timed ones, the first of which is reported
    as ``Timing.first`` (for a jitted function: trace + compile + one run).
    """
    t0 = time.perf_counter()
    block(fn())
    first = time.perf_counter() - t0
    for _ in range(max(warmup - 1, 0)):
        block(fn())
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        block(fn())
        runs.append(time.perf_counter() - t0)
    return Timing(first=first, runs=tuple(runs))


def machine_info() -> str:
    """One line describing the host, the CPU count and the library versions."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            names = [ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    try:
        load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        load = "n/a"
    return (
        f"{cpu}, {os.cpu_count()} logical CPUs, load average {load}; "
        f"Python {platform.python_version()}, jax {jax.__version__} "
        f"({jax.default_backend()}), numpy {np.__version__}"
    )


def compiled_memory(fn, *args) -> dict[str, float]:
    """Compile a ``jax.jit`` function for ``args`` (arrays or ShapeDtypeStructs).

    Returns XLA's ``memory_analysis()`` sizes in bytes (``argument``, ``output``, ``temp``)
    and the compile time ``compile_s`` [s].
    """
    t0 = time.perf_counter()
    compiled = fn.lower(*args).compile()
    seconds = time.perf_counter() - t0
    mem = compiled.memory_analysis()
    out = {"compile_s": seconds}
    for key in ("argument", "output", "temp"):
        out[key] = float(getattr(mem, f"{key}_size_in_bytes", 0) or 0)
    return out


def fmt_us(seconds: float) -> str:
    return f"{seconds * 1e6:.1f}"


def fmt_ms(seconds: float) -> str:
    return f"{seconds * 1e3:.2f}"


def fmt_mib(nbytes: float) -> str:
    return f"{nbytes / 2**20:.2f}"


def fmt_times(ratio: float) -> str:
    """A speed-up factor: one decimal below 10x."""
    return f"{ratio:.1f}x" if ratio < 10 else f"{ratio:.0f}x"


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A GitHub markdown table; floats are printed as given (format them beforehand)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


# --------------------------------------------------------------------------- scene


def pinhole_K(width: int = 640, height: int = 480, focal_px: float = 525.0) -> np.ndarray:
    """Intrinsics of an ideal camera with the principal point at the image centre."""
    return np.array(
        [[focal_px, 0.0, (width - 1) / 2], [0.0, focal_px, (height - 1) / 2], [0.0, 0.0, 1.0]]
    )


@dataclasses.dataclass(frozen=True)
class Scene:
    """A random scene: N points seen by F cameras (NumPy float64 arrays).

    Attributes:
        P: (F, 3, 4) projection matrices.
        uv: (N, F, 2) noisy pixels [px].
        basis: (F, k) orthonormal DCT basis at the frame times.
        times: (F,) frame times [s].
        points: (N, F, 3) true point trajectories [m].
        centres: (F, 3) camera centres [m].
        K: (3, 3) intrinsics.
    """

    P: np.ndarray
    uv: np.ndarray
    basis: np.ndarray
    times: np.ndarray
    points: np.ndarray
    centres: np.ndarray
    K: np.ndarray


def _rot_z(a):
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2
    )


def _rot_x(a):
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack(
        [np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2
    )


def _cloud_trajectory(rng, N: int, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre (F, 3) and points (N, F, 3) of a cloud moving on a smooth path.

    ``s`` in [0, 1] is normalised time, so the motion has the same shape for every F. The
    cloud (radius 0.1 m) translates about 0.3 m, turns about 30 degrees about z and 6 about
    x, and each point wobbles by a few millimetres on its own (non-rigid part).
    """
    centre = np.stack(
        [0.3 * (s - 0.5), 0.05 * np.sin(2 * np.pi * s), 0.03 * np.sin(np.pi * s)], axis=-1
    )
    R = _rot_z(0.5 * s) @ _rot_x(0.1 * np.sin(np.pi * s))  # (F, 3, 3)
    offsets = rng.normal(size=(N, 3))
    offsets *= 0.1 * rng.uniform(size=(N, 1)) ** (1 / 3) / np.linalg.norm(offsets, axis=1)[:, None]
    freq = rng.uniform(0.5, 1.5, size=(N, 1))
    phase = rng.uniform(0, 2 * np.pi, size=(N, 1))
    direction = rng.normal(size=(N, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    wobble = 0.003 * np.sin(2 * np.pi * freq * s[None, :] + phase)  # (N, F)
    local = offsets[:, None, :] + wobble[..., None] * direction[:, None, :]
    points = np.einsum("fij,nfj->nfi", R, local) + centre[None]
    return centre, points


def make_scene(
    F: int,
    k: int,
    N: int,
    *,
    seed: int = 0,
    noise_px: float = 0.3,
    fps: float = 30.0,
    standoff: tuple[float, float] = (0.5, 1.5),
) -> Scene:
    """A random but realistic scene for timing the solver.

    N points on a moving cloud about 1 m in front of F cameras; each camera has a random
    pose at ``standoff`` metres from the cloud centre (above the cloud, 10-60 degrees
    elevation, any azimuth), looking at the centre (plus 2 cm jitter) through a 640x480
    pinhole camera; pixels carry ``noise_px`` Gaussian noise.
    """
    if not jax.config.jax_enable_x64:
        raise RuntimeError("make_scene: enable float64 first (jax_enable_x64)")
    rng = np.random.default_rng(seed)
    times = np.arange(F) / fps
    s = (np.arange(F) + 0.5) / F
    centre, points = _cloud_trajectory(rng, N, s)

    azim = rng.uniform(0, 2 * np.pi, F)
    elev = np.deg2rad(rng.uniform(10, 60, F))
    dist = rng.uniform(*standoff, F)
    view = np.stack([np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)], -1)
    position = centre + dist[:, None] * view
    target = centre + 0.02 * rng.normal(size=(F, 3))

    K = pinhole_K()
    R_c_w, t_c_w = jax.vmap(look_at, in_axes=(0, 0, None))(
        jnp.asarray(position), jnp.asarray(target), jnp.array([0.0, 0.0, 1.0])
    )
    P = jax.vmap(projection_matrix, in_axes=(None, 0, 0))(jnp.asarray(K), R_c_w, t_c_w)
    uv = jax.vmap(project, in_axes=(None, 0, 0, 1), out_axes=1)(
        jnp.asarray(K), R_c_w, t_c_w, jnp.asarray(points)
    )
    uv = np.asarray(uv) + noise_px * rng.normal(size=(N, F, 2))
    basis = np.asarray(dct_basis(jnp.asarray(times), k))
    return Scene(
        P=np.asarray(P),
        uv=uv,
        basis=basis,
        times=times,
        points=points,
        centres=position,
        K=K,
    )


# --------------------------------------------------------------------------- dense baseline


def dense_Q(P: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The dense block-diagonal ``Q`` (2F, 3F) and ``q`` (2F,) of eq. 5, in NumPy."""
    F = P.shape[0]
    p3 = P[:, 2, :]
    rows = P[:, :2, :] - uv[:, :, None] * p3[:, None, :]  # (F, 2, 4)
    Q = np.zeros((F, 2, F, 3), dtype=P.dtype)
    idx = np.arange(F)
    Q[idx, :, idx, :] = rows[:, :, :3]
    return Q.reshape(2 * F, 3 * F), -rows[:, :, 3].reshape(2 * F)


def dense_lstsq(
    P: np.ndarray, uv: np.ndarray, theta: np.ndarray, weights: np.ndarray | None = None
) -> np.ndarray:
    """Coefficients (k, 3) of one point by the textbook method: dense ``lstsq(Q Theta, q)``.

    Args:
        P: (F, 3, 4) projection matrices.
        uv: (F, 2) pixels of one point.
        theta: (3F, 3k) ``kron(basis, I_3)``; it depends only on the basis and may be
            shared by all points.
        weights: optional (F,) weights on the squared residuals (rows scaled by sqrt).
    """
    Q, q = dense_Q(P, uv)
    A = Q @ theta
    if weights is not None:
        sw = np.repeat(np.sqrt(weights), 2)
        A, q = A * sw[:, None], q * sw
    beta = np.linalg.lstsq(A, q, rcond=None)[0]
    return beta.reshape(-1, 3)


@dataclasses.dataclass(frozen=True)
class DenseRun:
    """Timing of the dense baseline on a subset of the points."""

    indices: np.ndarray
    times_s: np.ndarray  # per point
    coeffs: np.ndarray  # (n, k, 3)
    skipped: bool = False

    @property
    def per_point_s(self) -> float:
        return float(np.median(self.times_s))


def run_dense(
    scene: Scene, max_points: int, budget_s: float, cap_s: float = np.inf, min_points: int = 3
) -> DenseRun:
    """Time the dense baseline per point on an evenly spaced subset of the points.

    The subset size is chosen from the time of the first point so that the run takes about
    ``budget_s``; when that first point takes longer than ``cap_s`` the baseline is skipped.
    ``Theta`` is built once outside the timed region (it depends only on the basis).
    """
    theta = np.kron(scene.basis, np.eye(3))
    N = scene.uv.shape[0]

    def one(j):
        t0 = time.perf_counter()
        beta = dense_lstsq(scene.P, scene.uv[j], theta)
        return time.perf_counter() - t0, beta

    t_first, beta0 = one(0)
    if t_first > cap_s:
        return DenseRun(np.array([0]), np.array([t_first]), beta0[None], skipped=True)
    n = int(np.clip(budget_s / max(t_first, 1e-6), min_points, max_points))
    n = min(n, N)
    idx = np.unique(np.linspace(0, N - 1, n).round().astype(int))
    times, coeffs = [], []
    for j in idx:
        t, beta = one(j)
        times.append(t)
        coeffs.append(beta)
    return DenseRun(idx, np.array(times), np.stack(coeffs))


def dense_breakdown(scene: Scene, n_points: int = 50) -> dict[str, float]:
    """Median per-point seconds of the baseline's parts: build Q/q, Q @ Theta, lstsq."""
    theta = np.kron(scene.basis, np.eye(3))
    parts = {"build Q, q": [], "A = Q @ Theta": [], "lstsq(A, q)": []}
    for j in range(min(n_points, scene.uv.shape[0])):
        t0 = time.perf_counter()
        Q, q = dense_Q(scene.P, scene.uv[j])
        t1 = time.perf_counter()
        A = Q @ theta
        t2 = time.perf_counter()
        np.linalg.lstsq(A, q, rcond=None)
        t3 = time.perf_counter()
        parts["build Q, q"].append(t1 - t0)
        parts["A = Q @ Theta"].append(t2 - t1)
        parts["lstsq(A, q)"].append(t3 - t2)
    return {name: float(np.median(v)) for name, v in parts.items()}


def relative_difference(coeffs: np.ndarray, reference: np.ndarray) -> float:
    """max over points of ``||beta - beta_ref|| / ||beta_ref||`` (coefficients (n, k, 3))."""
    n = reference.shape[0]
    diff = np.linalg.norm((coeffs - reference).reshape(n, -1), axis=1)
    return float(np.max(diff / np.linalg.norm(reference.reshape(n, -1), axis=1)))

"""How the batched drivers step through their points, chosen per backend.

The drivers over many points seen by the same cameras (:func:`jaxtraj.reconstruct_points`,
:func:`jaxtraj.estimators.select_k_points`,
:func:`jaxtraj.estimators.reconstruct_regularised_points`, :func:`jaxtraj.estimate_points`
and the chunked batch runner) do a small amount of dense work per point: factorisations of
30x30 to 180x180 systems, short smoother passes. How the points are grouped decides the
speed, and the best grouping differs by backend:

* on a CPU, a loop (``lax.map``) over small groups keeps each group's matrices in cache,
  and XLA:CPU compiles the loop body into one native function (see :mod:`jaxtraj._xla`);
  one ``vmap`` over all points streams every step's arrays through memory instead;
* on a GPU, each loop step launches a sequence of small kernels and waits for them, so a
  loop over small groups leaves the device nearly idle; there the points go in large
  groups, as large as memory allows.

Each driver names both sizes (``MAP_BATCH`` for the CPU and ``MAP_BATCH_ACCELERATOR``);
:func:`points_per_step` picks one from the platform of the input data (a committed
``jax.Array``'s device; under tracing, or for NumPy inputs, JAX's default backend). The
results are the same up to rounding whichever size is used.

**Every core of a CPU.** XLA:CPU runs such a loop on one core: it does not run the steps,
or two loops over halves of the points in one program, side by side. Called eagerly on a
CPU, the drivers whose kernels make no batched LAPACK call (:func:`jaxtraj.reconstruct_points`,
:func:`jaxtraj.estimate_points`, :func:`jaxtraj.estimators.select_k_points`,
:func:`jaxtraj.estimators.reconstruct_regularised_points` - its per-track choice, whose
LAPACK calls are unbatched, one track per loop step, and its fits - and the chunked batch
runner) therefore go through :func:`on_cores`: the points are split into one chunk per
core and the same compiled kernel runs on each chunk from its own thread (JAX releases the
interpreter lock while a program runs). Each point's result is the same as in one call,
up to rounding where its loop group changes (the last, padded group). Under ``jit``,
``vmap`` or ``grad`` (traced inputs), on an accelerator, or with too few points, the
kernel runs once as before; ``JAXTRAJ_CPU_THREADS=1`` turns the split off. Kernels with
batched LAPACK calls are not split: two of them running at once on jaxlib 0.10.2
(``refine_points``, whose Levenberg-Marquardt steps call batched QR) were seen to stop
for good with every XLA worker idle; the regularised DCT's split choice did not (300
split calls of its 5-fold choice on 2 cores, jaxlib 0.10.2).

**One BLAS thread for LAPACK.** JAX's CPU LAPACK calls go to SciPy's OpenBLAS, which by
default runs every call on a thread per core. On jaxtraj's small systems (3x3 to
180x180) that costs more than it gains: with one OpenBLAS thread the regularised DCT's
5-fold choice took 6.4 instead of 9.3 ms per point in one call and ``refine_points`` 2.8
instead of 4.7 ms (2-core Intel Xeon, F = 150), and only with one thread each can the
two cores each run a chunk of tracks. The drivers that call LAPACK therefore run their
programs through :func:`with_one_blas_thread`.
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp

__all__ = [
    "carried",
    "cpu_cores",
    "in_threads",
    "map_points",
    "on_cores",
    "one_blas_thread",
    "platform_of",
    "points_per_step",
    "with_one_blas_thread",
]

#: fewest points per chunk for which :func:`on_cores` splits a batch over the cores
MIN_POINTS_PER_CORE = 64
#: chunk sizes are multiples of this (the CPU group size of every driver divides it), so
#: that a point falls in the same group of its loop as in one call over all points
ALIGN = 8


def platform_of(x=None) -> str:
    """``"cpu"``, ``"gpu"``, ``"tpu"``...: where an array lives, else the default backend."""
    if isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer):
        try:
            return next(iter(x.devices())).platform
        except (AttributeError, StopIteration, RuntimeError):  # deleted or abstract arrays
            pass
    return jax.default_backend()


def points_per_step(cpu: int, accelerator: int, like=None) -> int:
    """The group size for the platform of ``like`` (see the module docstring); 0 = all."""
    return cpu if platform_of(like) == "cpu" else accelerator


def map_points(fn: Callable, xs, per_step: int):
    """``fn`` over the leading axis of ``xs``: ``lax.map`` in groups of ``per_step`` points
    (one point per step, unbatched, when it is 1), or one ``vmap`` over all of them when
    ``per_step`` is 0."""
    if per_step <= 0:
        return jax.vmap(fn)(xs)
    if per_step == 1:  # one point per step, not a vmap of one (no batched LAPACK call)
        return jax.lax.map(fn, xs)
    return jax.lax.map(fn, xs, batch_size=per_step)


def cpu_cores() -> int:
    """CPU cores this process may use, or ``JAXTRAJ_CPU_THREADS`` when set (>= 1)."""
    env = os.environ.get("JAXTRAJ_CPU_THREADS", "").strip()
    if env:
        if not env.isdigit() or int(env) < 1:
            raise ValueError(f"JAXTRAJ_CPU_THREADS: expected an integer >= 1, got {env!r}")
        return int(env)
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def carried(fn: Callable) -> Callable:
    """``fn`` made to run, in any thread, with the calling thread's ``jax.enable_x64`` and
    ``jax.default_device`` settings (a new thread starts with JAX's global settings, not
    the caller's context managers)."""
    x64, device = jax.config.jax_enable_x64, jax.config.jax_default_device

    def run(*args):
        with jax.enable_x64(x64), jax.default_device(device):
            return fn(*args)

    return run


def in_threads(fn: Callable, args: list, workers: int) -> list:
    """``[fn(a) for a in args]`` on a pool of ``workers`` threads, in order, each with the
    caller's JAX settings (:func:`carried`)."""
    with ThreadPoolExecutor(max_workers=max(1, min(workers, len(args)))) as pool:
        return list(pool.map(carried(fn), args))


def on_cores(
    kernel: Callable,
    points,
    others=(),
    min_per_core: int = MIN_POINTS_PER_CORE,
    align: int = ALIGN,
):
    """``kernel(points)`` with the leading axis of the pytree ``points`` split over the CPU
    cores (module notes): one chunk per core, all of one size (the last padded with copies
    of the last point, so one compilation serves every chunk), each run from its own
    thread, the results concatenated. ``others``: the kernel's other array arguments,
    only checked for tracers. Runs ``kernel(points)`` once when any input is traced, the
    data are not on a CPU, there is one core, or a chunk would hold fewer than
    ``min_per_core`` points. Chunk sizes are multiples of ``align`` (the kernel's loop
    group size; 1 for a loop over single points)."""
    leaves = jax.tree_util.tree_leaves(points)
    n = leaves[0].shape[0]
    cores = cpu_cores()
    traced = any(
        isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves((points, others))
    )
    chunks = min(cores, n // max(min_per_core, 1))
    if traced or chunks < 2 or platform_of(leaves[0]) != "cpu":
        return kernel(points)
    size = -(-n // chunks)
    size += -size % align  # chunks start on a group boundary of the drivers' CPU loops
    parts = _split(points, chunks, size)
    results = in_threads(lambda p: jax.block_until_ready(kernel(p)), parts, chunks)
    return _join(results, n)


@functools.partial(jax.jit, static_argnums=(1, 2))
def _split(points, chunks: int, size: int):
    """``chunks`` chunks of ``size`` points, the last padded with copies of the last point."""
    n = jax.tree_util.tree_leaves(points)[0].shape[0]
    pad = size * chunks - n

    def padded(x):
        return jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]) if pad else x

    full = jax.tree_util.tree_map(padded, points)
    return [
        jax.tree_util.tree_map(lambda x, a=a: x[a : a + size], full)
        for a in range(0, size * chunks, size)
    ]


@functools.partial(jax.jit, static_argnums=1)
def _join(results, n: int):
    """The chunks' results concatenated in order, without the padding."""
    return jax.tree_util.tree_map(lambda *r: jnp.concatenate(r)[:n], *results)


_blas_lock = threading.Lock()
_blas_users = 0
_blas_limit = None
_blas_controller = None


def _controller():
    """threadpoolctl's view of the loaded BLAS libraries, made once, after loading the one
    JAX's CPU LAPACK calls use (SciPy's, loaded by JAX only when it first compiles one)."""
    global _blas_controller
    if _blas_controller is None:
        from threadpoolctl import ThreadpoolController

        try:
            import scipy.linalg.cython_lapack  # noqa: F401
        except ImportError:  # no SciPy: nothing of JAX's to limit
            pass
        _blas_controller = ThreadpoolController()
    return _blas_controller


@contextlib.contextmanager
def one_blas_thread() -> Iterator[None]:
    """Run the body with one thread in every BLAS library of the process (module notes).

    Process-wide while any thread is inside (the limit is set by the first to enter and
    lifted by the last to leave, so threads that overlap cannot leave it set); under
    tracing it only affects the trace. ``JAXTRAJ_ONE_BLAS_THREAD=0`` turns it off."""
    global _blas_users, _blas_limit
    if os.environ.get("JAXTRAJ_ONE_BLAS_THREAD", "1").strip() == "0":
        yield
        return
    with _blas_lock:
        if _blas_users == 0:
            _blas_limit = _controller().limit(limits=1, user_api="blas")
        _blas_users += 1
    try:
        yield
    finally:
        with _blas_lock:
            _blas_users -= 1
            if _blas_users == 0:
                _blas_limit.restore_original_limits()
                _blas_limit = None


def with_one_blas_thread(fn: Callable, *args):
    """``fn(*args)`` inside :func:`one_blas_thread`, returned once its programs have run
    (JAX dispatches them asynchronously, so leaving the context sooner would lift the limit
    while they run)."""
    with one_blas_thread():
        return jax.block_until_ready(fn(*args))

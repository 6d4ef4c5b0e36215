"""Reconstruct point sets larger than memory: stream tracks from disk in fixed chunks.

On-disk layout of a batch (NumPy ``.npy`` files, readable from any language)::

    dataset/
      cameras.npz     P: (F, 3, 4) projection matrices of undistorted pixels,
                      times: (F,) image times [s]  (one camera path for all points)
      tracks.npy      (N, F, 2) pixels, float32 or float64; NaN where not detected
      weights.npy     optional (N, F) weights; default 1 where the pixel is finite

    out/
      points.npy      (N, F, 3) float64 reconstructed trajectories [m]
      coeffs.npy      (N, k, 3) DCT coefficients
      rms_px.npy, gain.npy (N,) float64;  status.npy (N,) int32 (jaxtraj.Status)
      progress-P.json the finished chunks of process P (see below)

Each chunk of ``chunk_size`` points is read with plain file reads (no memory map, so the
resident memory stays flat), padded to the fixed size (one compilation), masked (a pixel
that is not finite is a missing detection) and solved in one program on the device with
the batched kernel (sharded over the devices of ``mesh`` when given), and written into its
rows of the output files, which are flushed to disk before the chunk is recorded as done
in ``progress-P.json`` (written atomically). The next chunk is read and its solve
dispatched (JAX runs it asynchronously) before the previous chunk's rows are written, so
disk reads, writes and fsync overlap the compute. An interrupted run resumes from the
progress file; a chunk that was computed or written but not recorded (at most the last
two) is simply computed again, with identical results. With several processes
(``jax.distributed.initialize``), process P of Q does the chunks ``i % Q == P`` and keeps
its own progress file; all write disjoint rows of the same output files on a shared file
system.
"""

from __future__ import annotations

import functools
import json
import os
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .._batching import carried, on_cores
from ..basis import dct_basis
from ..solve import _per_step, _reconstruct_points

__all__ = ["BatchSummary", "NpyRows", "run_batch", "write_dataset"]

FORMAT = "jaxtraj-batch"


@functools.partial(jax.jit, static_argnames=("dtype", "per_step"))
def _solve_chunk(P, basis, raw, weights, dtype, per_step):
    """One chunk's masking and solve in one program on the device: a pixel that is not
    finite is a missing detection (weight 0, pixel 0). Masking here rather than with NumPy
    on the host keeps the host to reading and writing (the host's masking cost 4-5 us per
    point, against a solve of 2 us on a GPU)."""
    finite = jnp.all(jnp.isfinite(raw), axis=-1)
    uv = jnp.where(finite[..., None], raw, 0.0).astype(dtype)
    w = jnp.where(finite, weights, 0.0).astype(dtype)
    return _reconstruct_points(P, uv, basis, w, 20.0, 1, True, None, per_step)


def _solve_on_cores(P, basis, raw, weights, dtype, per_step):
    """:func:`_solve_chunk` with the chunk split over the CPU cores, one part per core,
    each solved from its own thread (:func:`jaxtraj._batching.on_cores`; one call on an
    accelerator or for a small chunk)."""
    return on_cores(
        lambda a: _solve_chunk(P, basis, a[0], a[1], dtype, per_step),
        (jnp.asarray(raw), jnp.asarray(weights)),
        (P, basis),
    )


class NpyRows:
    """Row-wise reads and writes of a ``.npy`` file with plain file I/O (no memory map)."""

    def __init__(self, path: str | Path, mode: str = "rb"):
        self.path = Path(path)
        self.file = open(self.path, mode)
        version = np.lib.format.read_magic(self.file)
        read_header = (
            np.lib.format.read_array_header_1_0
            if version == (1, 0)
            else np.lib.format.read_array_header_2_0
        )
        self.shape, fortran, self.dtype = read_header(self.file)
        if fortran:
            raise ValueError(f"{self.path}: Fortran-ordered arrays are not supported")
        self.offset = self.file.tell()
        self.row_items = int(np.prod(self.shape[1:], dtype=np.int64))
        self.row_bytes = self.row_items * self.dtype.itemsize

    def read(self, start: int, stop: int) -> np.ndarray:
        self.file.seek(self.offset + start * self.row_bytes)
        data = np.fromfile(self.file, self.dtype, (stop - start) * self.row_items)
        return data.reshape((stop - start, *tuple(self.shape[1:])))

    def write(self, start: int, rows: np.ndarray) -> None:
        self.file.seek(self.offset + start * self.row_bytes)
        np.ascontiguousarray(rows, self.dtype).tofile(self.file)

    def flush(self) -> None:
        self.file.flush()
        os.fsync(self.file.fileno())

    def close(self) -> None:
        self.file.close()


@dataclass(frozen=True)
class BatchSummary:
    """Outcome of :func:`run_batch`: points, chunks, chunks computed now / skipped (done
    before), points per status code, the wall time of the computed chunks [s] (the first
    chunk's compilation included) and the number of points in the computed chunks."""

    points: int
    chunks: int
    computed: int
    skipped: int
    status_counts: dict
    seconds: float
    computed_points: int = 0


def write_dataset(folder: str | Path, P, times, tracks, weights=None) -> Path:
    """Write a batch dataset (see the module docstring) from arrays in memory."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    np.savez(folder / "cameras.npz", P=np.asarray(P, np.float64), times=np.asarray(times))
    np.save(folder / "tracks.npy", np.asarray(tracks))
    if weights is not None:
        np.save(folder / "weights.npy", np.asarray(weights))
    return folder


def _load_cameras(dataset: Path):
    path = dataset / "cameras.npz"
    if not path.is_file():
        raise ValueError(f"{path}: no such file (a batch dataset needs cameras.npz)")
    with np.load(path) as z:
        missing = {"P", "times"} - set(z.files)
        if missing:
            raise ValueError(f"{path}: missing array(s) {sorted(missing)}; found {z.files}")
        P, times = z["P"].astype(np.float64), z["times"].astype(np.float64)
    if P.ndim != 3 or P.shape[1:] != (3, 4) or times.shape != (P.shape[0],):
        raise ValueError(
            f"{path}: expected P (F, 3, 4) and times (F,), got {P.shape}, {times.shape}"
        )
    return P, times


def _create_once(path: Path, shape: tuple, dtype) -> None:
    """Create an output ``.npy`` (zeros) unless it exists; safe when several processes try
    at once (the file is made under a private name and hard-linked into place)."""
    if path.exists():
        return
    tmp = path.with_name(f".{path.name}.{os.getpid()}.part")
    np.lib.format.open_memmap(tmp, mode="w+", dtype=dtype, shape=shape).flush()
    try:
        os.link(tmp, path)
    except FileExistsError:
        pass  # another process was first
    finally:
        tmp.unlink()


def _outputs(out: Path, n: int, F: int, k: int, restart: bool) -> dict[str, NpyRows]:
    specs = {
        "points": ((n, F, 3), np.float64),
        "coeffs": ((n, k, 3), np.float64),
        "rms_px": ((n,), np.float64),
        "gain": ((n,), np.float64),
        "status": ((n,), np.int32),
    }
    files = {}
    for name, (shape, dtype) in specs.items():
        path = out / f"{name}.npy"
        if restart:
            path.unlink(missing_ok=True)
        _create_once(path, shape, dtype)
        files[name] = NpyRows(path, "r+b")
        if tuple(files[name].shape) != shape or files[name].dtype != np.dtype(dtype):
            raise ValueError(
                f"{path}: holds {files[name].dtype} {files[name].shape}, this run needs "
                f"{np.dtype(dtype)} {shape}; use a new output folder or --restart"
            )
    return files


def _read_progress(path: Path, meta: dict) -> set[int]:
    if not path.exists():
        return set()
    data = json.loads(path.read_text())
    if {k: data.get(k) for k in meta} != meta:
        raise ValueError(
            f"{path}: belongs to another run ({ {k: data.get(k) for k in meta} }); "
            "use a new output folder or --restart"
        )
    return set(data["done"])


def _write_progress(path: Path, meta: dict, done: set[int]) -> None:
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps({**meta, "done": sorted(done)}) + "\n")
    os.replace(tmp, path)


def run_batch(
    dataset: str | Path,
    out: str | Path,
    *,
    k: int,
    chunk_size: int = 4096,
    mesh=None,
    restart: bool = False,
    max_chunks: int | None = None,
    process: tuple[int, int] | None = None,
    progress: Callable[[Iterable, str, int], Iterable] | None = None,
    dtype=jnp.float64,
) -> BatchSummary:
    """Reconstruct every track of ``dataset`` with the DCT basis of ``k`` vectors.

    Args:
        dataset: the dataset folder; out: the output folder (created).
        k: DCT basis vectors.
        chunk_size: points per chunk (a multiple of the mesh size when ``mesh`` is given).
        mesh: a ``jax.sharding.Mesh`` with axis ``"points"`` to shard each chunk over.
        restart: discard earlier progress and outputs in ``out`` and start again (one
            process only; for a multi-host restart, delete ``out`` instead).
        max_chunks: stop after computing this many chunks (for tests of resumption).
        process: ``(index, count)``; default ``(jax.process_index(), jax.process_count())``.
        progress: ``progress(iterable, description, total)`` wrapper (tqdm) or None.
        dtype: computation dtype (outputs are float64 files either way).

    Returns:
        a :class:`BatchSummary`.
    """
    import time

    dataset, out = Path(dataset), Path(out)
    P, times = _load_cameras(dataset)
    tracks = NpyRows(dataset / "tracks.npy") if (dataset / "tracks.npy").is_file() else None
    if tracks is None:
        raise ValueError(f"{dataset / 'tracks.npy'}: no such file")
    n, F = int(tracks.shape[0]), P.shape[0]
    if tuple(tracks.shape[1:]) != (F, 2):
        raise ValueError(f"{tracks.path}: expected shape (N, {F}, 2), got {tracks.shape}")
    weights = NpyRows(dataset / "weights.npy") if (dataset / "weights.npy").is_file() else None
    if weights is not None and tuple(weights.shape) != (n, F):
        raise ValueError(f"{weights.path}: expected shape ({n}, {F}), got {weights.shape}")
    if not isinstance(k, int) or k < 1 or 2 * F < 3 * k:
        raise ValueError(f"k: expected 1 <= k <= 2F/3 = {2 * F // 3}, got {k}")
    devices = 1 if mesh is None else mesh.devices.size
    if chunk_size < 1 or chunk_size % devices:
        raise ValueError(f"chunk_size: expected a positive multiple of {devices}, got {chunk_size}")
    index, count = process or (jax.process_index(), jax.process_count())
    out.mkdir(parents=True, exist_ok=True)
    meta = {
        "format": FORMAT,
        "version": 1,
        "points": n,
        "frames": F,
        "k": k,
        "chunk_size": chunk_size,
    }
    prog_path = out / f"progress-{index}.json"
    if restart:
        prog_path.unlink(missing_ok=True)
    done = _read_progress(prog_path, meta)
    done_before = set(done)
    files = _outputs(out, n, F, k, restart)

    basis = jnp.asarray(dct_basis(times, k), dtype)
    P_d = jnp.asarray(P, dtype)
    if mesh is not None:
        from jax.sharding import NamedSharding
        from jax.sharding import PartitionSpec as Pspec

        split, same = NamedSharding(mesh, Pspec("points")), NamedSharding(mesh, Pspec())
        P_d, basis = jax.device_put(P_d, same), jax.device_put(basis, same)

    per_step = _per_step(P_d)

    def solve(raw, w):
        if mesh is not None:
            raw, w = jax.device_put(raw, split), jax.device_put(w, split)
            return _solve_chunk(P_d, basis, raw, w, jnp.dtype(dtype), per_step)
        return _solve_on_cores(P_d, basis, raw, w, jnp.dtype(dtype), per_step)

    chunks = [i for i in range(-(-n // chunk_size)) if i % count == index]
    todo = [i for i in chunks if i not in done]
    if max_chunks is not None:
        todo = todo[:max_chunks]
    steps = todo if progress is None else progress(todo, "batch chunks", len(todo))

    def load(i):
        """Chunk i's pixels and weights as stored, padded to the chunk size (one compiled
        shape); :func:`_solve_chunk` masks them."""
        a, b = i * chunk_size, min(n, (i + 1) * chunk_size)
        raw = tracks.read(a, b)
        w = np.ones((b - a, F), raw.dtype) if weights is None else weights.read(a, b)
        if b - a < chunk_size:
            raw = np.concatenate([raw, np.zeros((chunk_size - (b - a), F, 2), raw.dtype)])
            w = np.concatenate([w, np.zeros((chunk_size - (b - a), F), w.dtype)])
        return raw, w

    def store(i, res):
        """Write chunk i's rows, flush them to disk, then record the chunk as done."""
        a, b = i * chunk_size, min(n, (i + 1) * chunk_size)
        res = jax.device_get(res)
        for name in files:
            files[name].write(a, getattr(res, name)[: b - a])
        for f in files.values():
            f.flush()
        done.add(i)
        _write_progress(prog_path, meta, done)

    # Chunk i + 1 is read and its solve started (in a second thread: on a CPU the solve
    # runs from threads of its own and returns when done) before the rows of chunk i are
    # written and flushed, so reading and writing overlap the compute.
    t0 = time.perf_counter()
    pending = None
    try:
        with ThreadPoolExecutor(max_workers=1) as solver:
            for i in steps:
                result = solver.submit(carried(solve), *load(i))
                if pending is not None:
                    store(*pending)
                pending = (i, result.result())
        if pending is not None:
            store(*pending)
    finally:
        for f in (*files.values(), tracks, *(() if weights is None else (weights,))):
            f.close()
    seconds = time.perf_counter() - t0
    status = np.load(out / "status.npy", mmap_mode="r")
    mine = np.concatenate(
        [np.arange(i * chunk_size, min(n, (i + 1) * chunk_size)) for i in sorted(done)]
        or [np.zeros(0, int)]
    )
    values, counts = np.unique(np.asarray(status[mine]), return_counts=True)
    return BatchSummary(
        points=n,
        chunks=len(chunks),
        computed=len(todo),
        skipped=len(set(chunks) & done_before),
        status_counts={int(v): int(c) for v, c in zip(values, counts, strict=True)},
        seconds=seconds,
        computed_points=sum(min(n, (i + 1) * chunk_size) - i * chunk_size for i in todo),
    )

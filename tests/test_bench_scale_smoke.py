"""Smoke tests of benchmarks/bench_scale.py at tiny sizes, so that the benchmark cannot rot.

Key checks: the block-written dataset follows its camera model (0.3 px noise, 5% missing),
every worker subprocess really has the device count it was started with (the XLA flag is
set before JAX starts), and every device count and chunk size gives the same trajectories.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np

from jaxtraj.scale.chunked import NpyRows

BENCH_DIR = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCH_DIR))

import bench_scale  # noqa: E402

TINY = bench_scale.Config(
    F=20,
    k=3,
    n=200,  # 4 chunks of 64, the last one padded
    devices=(1, 2),
    chunks=(64,),
    f32_chunk=None,
    repeats=1,
    in_memory_repeats=1,
    memory_ns=(256,),  # one memory worker: flatness is tested in tests/test_scale.py
    memory_chunk=64,
    block=96,  # not a divisor of n: blocks straddle chunk boundaries
    samples=8,
    timeout_s=120.0,
)


def test_dataset_is_written_in_blocks_and_follows_the_camera_model(tmp_path):
    cfg = dataclasses.replace(TINY, n=250)
    samples = bench_scale.sample_indices(250, 10)
    gen = bench_scale.make_dataset(tmp_path / "a", 250, cfg, samples)
    rows = NpyRows(tmp_path / "a" / "tracks.npy")
    try:
        assert tuple(rows.shape) == (250, 20, 2) and rows.dtype == np.float64
        assert gen["tracks_bytes"] == rows.offset + 250 * 20 * 2 * 8
        tracks = rows.read(0, 250)
    finally:
        rows.close()
    nan = np.isnan(tracks)
    assert np.array_equal(nan[..., 0], nan[..., 1])  # a detection is missing as a whole
    assert 0.03 < nan[..., 0].mean() < 0.07  # 5% missing
    with np.load(tmp_path / "a" / "cameras.npz") as z:
        P, times = z["P"], z["times"]
    assert P.shape == (20, 3, 4) and np.all(np.diff(times) >= 0)
    # the kept truth reprojects onto the sampled tracks up to the 0.3 px noise
    h = np.einsum("fij,nfj->nfi", P[:, :, :3], gen["truth"]) + P[:, :, 3]
    assert np.all(h[..., 2] > 0.5)  # in front of every camera
    resid = tracks[samples] - h[..., :2] / h[..., 2:]
    resid = resid[np.isfinite(resid)]
    assert 0.25 < np.std(resid) < 0.35 and abs(np.mean(resid)) < 0.05
    # seeded: a second write is byte-identical
    bench_scale.make_dataset(tmp_path / "b", 250, cfg)
    a, b = ((tmp_path / d / "tracks.npy").read_bytes() for d in "ab")
    assert a == b


def test_tiny_benchmark_agrees_across_devices_and_chunks(tmp_path):
    raw = bench_scale.measure(TINY, tmp_path / "work")
    assert not any((tmp_path / "work").iterdir())  # datasets and outputs deleted
    for D in TINY.devices:
        t = raw["throughput"][D]
        assert t["devices"] == D and t["points"] == 200
        assert t["in_memory"]["shards"] == D
    s = bench_scale.summarise(raw)
    assert [(r["devices"], r["chunk"]) for r in s["throughput"]] == [(1, 64), (2, 64)]
    for r in s["throughput"]:
        assert (r["chunks"], r["computed"], r["ok"]) == (4, 4, 200)
        assert r["max_diff_m"] < 1e-12  # same trajectories on 1 and 2 devices
        assert r["median_err_mm"] < 3.0  # and close to the truth
        assert r["rate"] > 0 and r["first_chunk_s"] > 0
    for m in s["in_memory"]:
        assert m["max_diff_m"] < 1e-12 and m["ok"] == 200
        assert m["peak_mib"] >= m["peak_chunked_mib"] > 0
    for n, m in raw["memory"].items():
        assert m["computed"] == -(-n // 64) and m["peak_mib"] >= m["before_mib"] > 0
        assert m["tracks_bytes"] == 128 + n * 20 * 2 * 8
        extra = m["output_bytes"] - bench_scale.output_bytes(n, 20, 3)
        assert 0 < extra <= 5 * 256  # five .npy headers
    text = bench_scale.report(raw, "bench_scale.py (test)", "start", "end")
    assert "GPU figures are not measured" in text
    table = [ln for ln in text.splitlines() if ln.startswith("| 1 | 64 | float64 |")]
    assert len(table) == 1 and "| 200/200 |" in table[0]
    assert "## Peak memory of `run_batch` vs dataset size" in text


def test_batch_against_the_kernel_section(tmp_path):
    """bench_scale.py --vs-kernel: every path measured on the same data; the command's own
    outputs equal the kernel's trajectories."""
    cfg = dataclasses.replace(TINY, n=150)
    raw = bench_scale.vs_kernel(cfg, tmp_path, (64,), 1, lambda msg: None)
    assert set(raw["rates"]) == {"all", "('kernel', 64)", "('batch', 64)", "('cli', 64)"}
    assert all(v > 0 for v in raw["rates"].values())
    assert set(raw["stages_us"]) == {"read", "pad", "mask and solve", "copy to host", "write",
                                     "fsync"}  # fmt: skip
    # what `jaxtraj batch` wrote is what the kernel computes on the same tracks
    from jaxtraj import dct_basis, reconstruct_points

    tracks = np.load(tmp_path / "ds-vs-kernel" / "tracks.npy")
    with np.load(tmp_path / "ds-vs-kernel" / "cameras.npz") as z:
        P, times = z["P"], z["times"]
    ok = np.all(np.isfinite(tracks), axis=-1)
    ref = reconstruct_points(P, np.nan_to_num(tracks), dct_basis(times, 3), ok * 1.0)
    for folder in ("cli-64", "vk-64"):
        got = np.load(tmp_path / folder / "points.npy")
        np.testing.assert_allclose(got, ref.points, rtol=0, atol=1e-12)
    text = bench_scale.vs_kernel_report(raw, "bench (test)", "start", "end")
    rows = [ln for ln in text.splitlines() if ln.startswith("| `jaxtraj batch`")]
    assert len(rows) == 1 and "| 64 |" in rows[0]

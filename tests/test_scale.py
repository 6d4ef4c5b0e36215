"""Scale-out: sharding over devices, chunked processing from disk, resumption, memory."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxtraj import dct_basis, reconstruct_points
from jaxtraj.cli import EXIT_OK, EXIT_USAGE, main
from jaxtraj.scale import chunked, run_batch, write_dataset

sys.path.insert(0, str(Path(__file__).parent))
from _scale_worker import many_points

WORKER = Path(__file__).parent / "_scale_worker.py"
OUTPUTS = ("points", "coeffs", "rms_px", "gain", "status")


def _worker(*args, devices=None):
    env = dict(os.environ)
    if devices:
        flags = f"{env.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={devices}"
        env["XLA_FLAGS"] = flags.strip()  # keeps the session's flags (conftest.py)
    proc = subprocess.run(
        [sys.executable, str(WORKER), *map(str, args)],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]


@pytest.fixture
def dataset(tmp_path):
    rng = np.random.default_rng(3)
    P, times, uv, _ = many_points(rng, 70)
    uv[5, 3] = np.nan  # a missing detection
    w = (rng.uniform(size=uv.shape[:2]) > 0.1).astype(float)
    return write_dataset(tmp_path / "ds", P, times, uv, w), P, times, uv, w


def _outputs(folder):
    return {name: np.load(folder / f"{name}.npy") for name in OUTPUTS}


def test_sharded_over_four_devices_equals_one_device(tmp_path):
    _worker("shard", tmp_path / "r.json", devices=4)
    r = json.loads((tmp_path / "r.json").read_text())
    assert r["devices"] == 4 and r["shards"] == 4
    assert r["sharded_vs_single"] < 1e-12 and r["status_equal"]
    assert r["chunked_sharded_vs_single"] < 1e-12
    assert r["recordings_vs_loop"] < 1e-12
    assert r["design_vs_single"] < 1e-9


def test_chunked_equals_one_shot(dataset, tmp_path):
    ds, P, times, uv, w = dataset
    summary = run_batch(ds, tmp_path / "out", k=5, chunk_size=16)
    assert (summary.points, summary.chunks, summary.computed) == (70, 5, 5)
    assert summary.computed_points == 70  # the padded rows of the last chunk do not count
    w = np.where(np.all(np.isfinite(uv), axis=-1), w, 0.0)
    ref = reconstruct_points(P, np.nan_to_num(uv), dct_basis(times, 5), w)
    got = _outputs(tmp_path / "out")
    np.testing.assert_allclose(got["points"], ref.points, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got["coeffs"], ref.coeffs, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got["rms_px"], ref.rms_px, rtol=1e-9)
    np.testing.assert_array_equal(got["status"], ref.status)
    assert sum(summary.status_counts.values()) == 70


def test_interrupted_run_resumes_with_identical_output(dataset, tmp_path, monkeypatch):
    ds = dataset[0]
    run_batch(ds, tmp_path / "once", k=5, chunk_size=16)
    # stopped after two chunks ...
    first = run_batch(ds, tmp_path / "twice", k=5, chunk_size=16, max_chunks=2)
    assert first.computed == 2
    # ... then killed while recording the fourth chunk as done
    real = chunked._write_progress
    calls = []

    def dying(*args):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        real(*args)

    monkeypatch.setattr(chunked, "_write_progress", dying)
    with pytest.raises(KeyboardInterrupt):
        run_batch(ds, tmp_path / "twice", k=5, chunk_size=16)
    monkeypatch.setattr(chunked, "_write_progress", real)
    done = json.loads((tmp_path / "twice" / "progress-0.json").read_text())["done"]
    assert done == [0, 1, 2]
    last = run_batch(ds, tmp_path / "twice", k=5, chunk_size=16)
    assert (last.computed, last.skipped) == (2, 3)
    assert last.computed_points == 16 + 6  # chunks 3 and 4 (the last one holds 6 points)
    for name in OUTPUTS:
        a = (tmp_path / "once" / f"{name}.npy").read_bytes()
        b = (tmp_path / "twice" / f"{name}.npy").read_bytes()
        assert a == b, name


def test_progress_of_another_run_is_refused(dataset, tmp_path):
    ds = dataset[0]
    run_batch(ds, tmp_path / "out", k=5, chunk_size=16, max_chunks=1)
    with pytest.raises(ValueError, match="belongs to another run"):
        run_batch(ds, tmp_path / "out", k=4, chunk_size=16)
    s = run_batch(ds, tmp_path / "out", k=4, chunk_size=16, restart=True)
    assert s.computed == 5 and s.skipped == 0


def test_peak_memory_does_not_grow_with_the_number_of_points(tmp_path):
    peaks = {}
    for n in (16384, 65536):
        out = tmp_path / f"m{n}.json"
        _worker("make", n, tmp_path / f"ds{n}")
        _worker("memory", tmp_path / f"ds{n}", tmp_path / f"out{n}", out)
        peaks[n] = json.loads(out.read_text())["peak_kib"]
    data_kib = 65536 * 60 * (2 + 3) * 8 / 1024  # tracks + points of the big run: 150 MiB
    growth = peaks[65536] - peaks[16384]  # allocator noise, not proportional to N
    assert growth < 0.25 * data_kib, (peaks, data_kib)


def test_batch_command(dataset, tmp_path, capsys):
    ds = dataset[0]
    out = tmp_path / "out"
    assert (
        main(["--quiet", "batch", str(ds), str(out), "--k", "5", "--chunk-size", "32"]) == EXIT_OK
    )
    assert "70 points in 3 chunks" in capsys.readouterr().out
    assert np.load(out / "points.npy").shape == (70, 30, 3)
    (ds / "cameras.npz").unlink()
    assert main(["--quiet", "batch", str(ds), str(tmp_path / "o2"), "--k", "5"]) == EXIT_USAGE
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cameras.npz: no such file" in err[0]


def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("localhost", 0))
        return sock.getsockname()[1]


def test_two_processes_with_jax_distributed_split_the_chunks(dataset, tmp_path):
    """Two processes on this host, coordinated by jax.distributed, as on two hosts."""
    ds = dataset[0]
    port = _free_port()
    cmd = [sys.executable, "-m", "jaxtraj", "--quiet", "batch", str(ds), str(tmp_path / "out")]
    cmd += ["--k", "5", "--chunk-size", "16", "--coordinator", f"localhost:{port}"]
    cmd += ["--num-processes", "2", "--process-id"]
    procs = [
        subprocess.Popen([*cmd, str(i)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for i in (0, 1)
    ]
    outs = [p.communicate(timeout=240) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [o[1][-1500:] for o in outs]
    done = [
        json.loads((tmp_path / "out" / f"progress-{i}.json").read_text())["done"] for i in (0, 1)
    ]
    assert done == [[0, 2, 4], [1, 3]]
    run_batch(ds, tmp_path / "one", k=5, chunk_size=16)
    for name in OUTPUTS:
        assert (tmp_path / "out" / f"{name}.npy").read_bytes() == (
            tmp_path / "one" / f"{name}.npy"
        ).read_bytes(), name

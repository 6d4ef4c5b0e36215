"""Smoke test of benchmarks/bench_drivers.py (the per-point cost of the batched drivers),
so that the script cannot rot: one cheap driver at a tiny size, table row printed."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_drivers


def test_prints_a_row_per_selected_driver(capsys):
    assert (
        bench_drivers.main(["--points", "4", "--only", "reconstruct_points", "--repeats", "1"]) == 0
    )
    rows = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("| reconstruct")]
    assert len(rows) == 1
    cost = float(rows[0].strip("| ").split("|")[-1])
    assert cost > 0


def test_device_benchmark_reports_the_solver_rows(tmp_path):
    import bench_device

    out = tmp_path / "device.md"
    args = ["--points", "8", "--skip", "gain,drivers,sweep", "--repeats", "1", "--out", str(out)]
    assert bench_device.main(args) == 0
    rows = [ln for ln in out.read_text().splitlines() if ln.startswith("| 8 |")]
    assert [r.split("|")[2].strip() for r in rows] == ["float64", "float32"]
    assert all(r.split("|")[-2].strip() == "8/8" for r in rows)  # status OK on every point
    assert all(float(r.split("|")[4]) > 0 for r in rows)  # us per point

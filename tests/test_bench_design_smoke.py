"""Smoke test of benchmarks/bench_design.py at tiny sizes, so that the benchmark cannot rot.

One design compilation dominates the time (about 20-30 s on 2 cores), so the test runs
the simulated scene only, with few images, draws and optimiser steps.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCH_DIR))

import bench_design  # noqa: E402

TINY = dataclasses.replace(
    bench_design.QUICK,
    frames=20,
    basis_k=6,
    camera_k=12,
    draws=4,
    max_steps=20,
    perturbed=1,
    mocap=False,
)


def _cells(report: str, path: str) -> list[str]:
    line = next(ln for ln in report.splitlines() if ln.startswith(f"| {path} |"))
    return [c.strip() for c in line.strip("|").split("|")]


def test_design_benchmark_table():
    report, results = bench_design.run_all(TINY)
    assert [r.name for r in results] == ["simulated cell"]
    res = results[0]
    assert [r.name for r in res.rows] == list(bench_design.PATHS)
    header = "| " + " | ".join(bench_design.HEADER) + " |"
    assert header in report
    for name in bench_design.PATHS:
        cells = _cells(report, name)
        assert len(cells) == len(bench_design.HEADER)
        row = res.row(name)
        numbers = [row.eta, row.mc_error, row.peak_velocity, row.peak_acceleration]
        if name != "follower":  # the follower is exactly degenerate: its E may be singular
            numbers += [row.expected_error, row.expected_mean_error]
            assert row.expected_mean_error <= row.expected_error * (1 + 1e-12)  # Jensen
        assert all(math.isfinite(x) and x > 0 for x in numbers), (name, numbers)
    follower, random = res.row("follower"), res.row("random discontinuous")
    optimised = res.row("optimised")
    # the follower is degenerate (eta ~ 1, error of metres) but drivable
    assert follower.eta < 2.0 and follower.mc_error > 0.1 and follower.within_limits
    # the paper's camera is informative but breaks the robot's limits
    assert random.eta > 20 and random.mc_error < 0.1
    assert {"velocity", "acceleration"} <= set(random.violated)
    # even a short design leaves the degenerate case and keeps every limit
    assert optimised.within_limits
    assert optimised.mc_error < 0.1 * follower.mc_error
    assert optimised.peak_velocity <= TINY.max_velocity * 1.01
    assert optimised.peak_acceleration <= TINY.max_acceleration * 1.01
    assert res.design_seconds > 0
    assert "**Verdict (simulated cell): target" in report

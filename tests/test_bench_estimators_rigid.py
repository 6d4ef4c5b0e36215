"""The known-layout rigid fit of benchmarks/bench_estimators.py on a slow-camera scene.

A single point seen from a slow, smooth camera is ambiguous in scale (the README explains
why); markers with a known layout are not. This keeps the benchmark's ``rigid_points``
from rotting and checks the claim at a small size; and its tables reprint the committed
results.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

import jaxtraj as jt
from tests.test_estimators_scenes import project_np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_estimators


def test_known_layout_resolves_the_slow_camera_scale_ambiguity():
    rng = np.random.default_rng(0)
    F, M, noise = 60, 6, 0.4
    times, X, P = bench_estimators.scene(rng, F, "slow", noise, "sim")
    Xs = bench_estimators.points_around(rng, X, M)
    uv = np.stack([project_np(P, x) for x in Xs]) + noise * rng.normal(size=(M, F, 2))
    # per point: every scale along the rays fits the pixels; the solver flags it
    lin = jt.reconstruct_points(P, uv, jt.dct_basis(times, 8))
    assert np.all(np.asarray(lin.status) == jt.Status.DEGENERATE)
    assert bench_estimators.err_mm(lin.points, Xs) > 100.0
    # the markers' layout fixes the scale: millimetres
    rigid = bench_estimators.rigid_points(P, uv, Xs[:, 0] - X[0], times, k=20)
    assert rigid.shape == Xs.shape
    assert bench_estimators.err_mm(rigid, Xs) < 10.0


def test_markdown_reprints_the_committed_results():
    """``--markdown`` on the committed JSON: one row per cell, the best fixed k per row."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "estimators.json"
    results = json.loads(path.read_text())
    table = bench_estimators.markdown(results).split("\n\n")[0].splitlines()
    header = [c.strip() for c in table[0].strip("|").split("|")]
    assert header == ["scene / camera", *bench_estimators.ESTIMATOR_COLUMNS]
    assert len(table) == 2 + len(results)
    for line, row in zip(table[2:], results, strict=True):
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert cells[0] == f"{bench_estimators.LABEL[row['source']]}, {row['mode']}"
        best = min(row[f"dct_k{k}"]["err_mm"] for k in bench_estimators.FIXED_K)
        assert float(cells[1]) == pytest.approx(best, rel=5e-3)


def test_markdown_table_layout():
    table = bench_estimators.markdown_table(["a", "b"], [["1", "2"], ["3", "4"]])
    assert table.splitlines() == ["| a | b |", "|---|---|", "| 1 | 2 |", "| 3 | 4 |"]

"""Smoke tests of benchmarks/bench_solve.py at tiny sizes, so that the benchmark cannot rot.

The key check: the dense NumPy ``lstsq`` port of the method and jaxtraj's structured solver
give the same coefficients (1e-9 relative, float64) on the benchmark's own scenes.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxtraj.constraints import block_diagonal_Q, ray_constraints
from jaxtraj.solve import reconstruct_points

BENCH_DIR = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCH_DIR))

import _common  # noqa: E402
import bench_solve  # noqa: E402

TINY = bench_solve.Config(
    main=(24, 4, 12),
    trials=1,
    repeats=1,
    dense_max_points=12,
    dense_budget_s=5.0,
    # the scaling sections rerun the main case: every new (F, k, N) is one more compilation
    # of the solver (about 5 s each at -O0), and the smoke test checks that they run and agree
    Fs=(24,),
    ks=(4,),
    Ns=(12,),
)


def test_dense_Q_matches_library_block_form(rng):
    scene = _common.make_scene(7, 3, 2, seed=3)
    Q, q = _common.dense_Q(scene.P, scene.uv[1])
    Qb, qb = ray_constraints(scene.P, scene.uv[1])
    np.testing.assert_allclose(Q, np.asarray(block_diagonal_Q(Qb)), rtol=0, atol=1e-12)
    np.testing.assert_allclose(q, np.asarray(qb).reshape(-1), rtol=0, atol=1e-12)


def test_dense_baseline_agrees_with_jaxtraj():
    c = bench_solve.compare(24, 4, 12, TINY)
    assert c.dense.indices.size == 12  # the budget covers every point
    assert not c.dense.skipped
    assert c.rel_diff < 1e-9
    assert np.all(np.asarray(c.jax.result.status) == 0)
    assert np.isfinite(c.ratio) and c.ratio > 0
    assert c.jax.per_point_s > 0 and c.dense.per_point_s > 0


def test_weighted_dense_baseline_agrees_with_jaxtraj(rng):
    scene = _common.make_scene(30, 5, 3, seed=1)
    theta = np.kron(scene.basis, np.eye(3))
    weights = rng.uniform(0.2, 2.0, 30)
    weights[[2, 11, 17]] = 0.0  # missing detections
    dense = np.stack([_common.dense_lstsq(scene.P, uv, theta, weights) for uv in scene.uv])
    ours = reconstruct_points(scene.P, scene.uv, scene.basis, np.tile(weights, (3, 1)))
    assert _common.relative_difference(np.asarray(ours.coeffs), dense) < 1e-9


def test_scene_is_realistic():
    F, N = 40, 25
    noisy = _common.make_scene(F, 5, N, seed=4, noise_px=0.3)
    clean = _common.make_scene(F, 5, N, seed=4, noise_px=0.0)
    np.testing.assert_array_equal(noisy.P, clean.P)  # the noise is drawn last
    noise = (noisy.uv - clean.uv).reshape(-1)
    assert 0.27 < np.std(noise) < 0.33
    # every point in front of every camera, 0.35-1.7 m away
    homog = np.concatenate([noisy.points, np.ones((N, F, 1))], axis=-1)
    depth = np.einsum("fj,nfj->nf", noisy.P[:, 2, :], homog)
    assert depth.min() > 0.35 and depth.max() < 1.7
    # camera stand-off 0.5-1.5 m from the cloud centre, pixels mostly inside 640x480
    centre = noisy.points.mean(axis=0)
    standoff = np.linalg.norm(noisy.centres - centre, axis=1)
    assert standoff.min() > 0.45 and standoff.max() < 1.55
    inside = (clean.uv[..., 0] > 0) & (clean.uv[..., 0] < 640) & (clean.uv[..., 1] > 0)
    assert np.mean(inside & (clean.uv[..., 1] < 480)) > 0.95
    # orthonormal basis at uniform times
    np.testing.assert_allclose(noisy.basis.T @ noisy.basis, np.eye(5), atol=1e-12)


def test_kernel_memory_is_linear_in_F():
    k, N = 4, 8
    small = bench_solve.kernel_memory(40, k, N)
    large = bench_solve.kernel_memory(160, k, N)
    # arguments are exactly P, uv, basis and weights in float64
    for F, mem in ((40, small), (160, large)):
        assert mem["argument"] == 8 * (12 * F + 2 * N * F + F * k + N * F)
    # 4x the frames: at most ~4x the scratch memory, far below the 16x of a dense (2F, 3F) Q
    assert large["temp"] < 6 * small["temp"]


def test_markdown_table():
    table = _common.markdown_table(["a", "b"], [[1, "x"], [2.5, "y"]])
    assert table == "| a | b |\n|---|---|\n| 1 | x |\n| 2.5 | y |"


@pytest.mark.slow
def test_report_runs_and_solvers_agree():
    report = bench_solve.run_all(TINY)
    assert "**Speed-up per point:" in report
    for title in ("Scaling with F", "Scaling with k", "Scaling with N", "float32", "Memory"):
        assert title in report
    # every comparison row: the dense and structured coefficients agree
    rows = [ln for ln in report.splitlines() if re.match(r"\| \d+ \| \d+ \| \d+ \|", ln)]
    assert len(rows) == len(TINY.Fs) + len(TINY.ks) + len(TINY.Ns)
    col = bench_solve.ROW_HEADER.index("max rel. diff of coeffs")
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert float(cells[col]) < 1e-9
    # float32 agrees with float64 to a few float32 ulps relative
    rel = re.search(r"relative difference median ([0-9.e+-]+), max ([0-9.e+-]+)", report)
    assert rel is not None and float(rel.group(2)) < 100 * np.finfo(np.float32).eps
    # the vectorised-NumPy structured baseline solves the same equations
    row = re.search(r"^\| float64 \| .*\| (\d+)/(\d+) \| ([0-9.e+-]+) \|$", report, re.M)
    assert row is not None and float(row.group(3)) < 1e-9
    assert "the gain costs" in report


def _trust_row(cell, camera, ep_err, flagged):
    stats = dict(
        trajectories=4,
        err_mm=ep_err,
        flagged=flagged,
        ok_err_mm=ep_err,
        ok_max_mm=2 * ep_err,
        ok_nees=3.0,
        over_5sd=0,
        over_5sd_flagged=float("nan"),
        has_cov=True,
        ms_per_point=1.0,
    )
    other = dict(stats, err_mm=10.0)
    row = dict(cell=cell, source="sim", camera=camera, noise_px=0.5, pixel_sigma=0.5)
    row |= dict(scenes=1, seen=1.0, best_k=8, cv_k=[8])
    import bench_estimators

    return row | {key: dict(other) for key in bench_estimators.TRUST_ROWS} | {"ep": stats}


def test_trust_scenes_follow_the_protocol():
    """--trust (issue 20): orbits of radius 3 m at the stated speed, a follower at a fixed
    offset, noise-free pixels that reproject; the summary marks missed targets."""
    import bench_estimators as be

    assert len(be.trust_cells({"cmu131_01": None, "cmu131_03": None}, None)) == 57
    assert len(be.trust_cells({}, "sim/orbit1/*,*/random/*")) == 3
    rng, noise_rng = np.random.default_rng(0), np.random.default_rng(1)
    _, Xs, P, uv, w = be.trust_scene(rng, noise_rng, "sim", "orbit5", 0.0, 3, {})
    assert Xs.shape == (3, 150, 3) and uv.shape == (3, 150, 2) and np.all(w == 1)
    C = np.array([-np.linalg.solve(p[:, :3], p[:, 3]) for p in P])
    mean = Xs.mean(axis=(0, 1))
    np.testing.assert_allclose(np.linalg.norm(C - mean, axis=1), 3.0, rtol=1e-9)
    flat = C[:, :2] - mean[:2]
    step = np.degrees(np.arccos(np.sum(flat[1:] * flat[:-1], 1) / np.sum(flat[1:] ** 2, 1)))
    np.testing.assert_allclose(step, 5.0, rtol=1e-6)
    h = np.einsum("fij,nfj->nfi", P[:, :, :3], Xs) + P[None, :, :, 3]
    np.testing.assert_allclose(uv, h[..., :2] / h[..., 2:], atol=1e-9)
    _, Xs, P, _, _ = be.trust_scene(rng, noise_rng, "sim", "follow", 0.5, 3, {})
    C = np.array([-np.linalg.solve(p[:, :3], p[:, 3]) for p in P])
    offset = C - Xs.mean(axis=0)
    np.testing.assert_allclose(offset, np.broadcast_to(offset[0], offset.shape), atol=1e-9)
    rows = [_trust_row("sim/random/0.5px", "random", 20.0, 0.5)]
    rows.append(_trust_row("sim/orbit1/clean", "orbit1", 11.0, 0.0))
    text = be.trust_markdown(rows)
    assert "| sim/orbit1/clean | 1.10 (" in text  # sorted: orbits first; within 1.25x
    assert "| **2.00 (" in text and "**50 %** (missed)" in text
    assert "ratio to best other: 1 of 2 cells" in text

"""Benchmark: per-point cost of the batched estimator drivers over points sharing cameras.

The scene of ``bench_solve.py`` (F = 150 random camera poses around a moving point cloud,
0.3 px), N points; each driver is called once to compile, then timed warm (best of 3).

Usage::

    python benchmarks/bench_drivers.py [--points 64] [--only select_k,regularised]

The regularised DCT's per-point 5-fold penalty choice is the slowest (see the README); it
runs on ``--regularised-points`` points (default: all N; 16 before 2026-12-07, when it
cost 4x more and ran on one core). With a shared weight it cross-validates 16 tracks and
solves all N, so its per-point cost falls with N (the issue's size: N = 2000). The
per-point choices by leave-one-frame-out cross-validation (``folds=F``) and generalised
cross-validation (``criterion="gcv"``) run on all N.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine_info, make_scene  # noqa: E402

from jaxtraj import dct_basis, estimate_points, reconstruct_points  # noqa: E402
from jaxtraj.estimators import (  # noqa: E402
    reconstruct_regularised_points,
    refine_points,
    select_k_points,
)


def cases(n: int, n_reg: int) -> dict:
    sc = make_scene(150, 10, n)
    P, uv, t = sc.P, sc.uv, sc.times
    basis = dct_basis(jnp.asarray(t), 10)
    lin = reconstruct_points(P, uv, basis)
    few = uv[:n_reg]
    return {
        "reconstruct_points (k = 10)": (n, lambda: reconstruct_points(P, uv, basis)),
        "select_k_points (k = 3..20)": (n, lambda: select_k_points(P, uv, t)),
        "reconstruct_regularised_points (k = 60, CV per point)": (
            n_reg,
            lambda: reconstruct_regularised_points(P, few, t, k=60),
        ),
        "reconstruct_regularised_points (k = 60, leave-one-frame-out CV per point)": (
            n,
            lambda: reconstruct_regularised_points(P, uv, t, k=60, folds=len(t)),
        ),
        "reconstruct_regularised_points (k = 60, GCV per point)": (
            n,
            lambda: reconstruct_regularised_points(P, uv, t, k=60, criterion="gcv"),
        ),
        "reconstruct_regularised_points (k = 60, shared weight, CV on 16 tracks)": (
            n,
            lambda: reconstruct_regularised_points(P, uv, t, k=60, shared=True, cv_points=16),
        ),
        "reconstruct_regularised_points (k = 60, weight given)": (
            n,
            lambda: reconstruct_regularised_points(P, uv, t, k=60, lam=1.0),
        ),
        "refine_points (k = 10)": (
            n,
            lambda: refine_points(P, uv, basis, lin.coeffs, status=lin.status),
        ),
        "estimate_points": (n, lambda: estimate_points(P, uv, t, pixel_sigma=0.3)),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=64)
    parser.add_argument("--regularised-points", type=int, default=None, help="default: --points")
    parser.add_argument("--only", default=None, help="comma-separated name fragments")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    print(machine_info())
    print("| driver | points | first call [s] | warm [ms/point] |")
    print("|---|---|---|---|")
    only = None if args.only is None else args.only.split(",")
    n_reg = args.points if args.regularised_points is None else args.regularised_points
    for name, (n, fn) in cases(args.points, n_reg).items():
        if only and not any(o in name for o in only):
            continue
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        first = time.perf_counter() - t0
        runs = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            runs.append(time.perf_counter() - t0)
        print(f"| {name} | {n} | {first:.1f} | {min(runs) / n * 1e3:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

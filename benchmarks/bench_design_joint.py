"""Benchmark: joint-space camera-path design on the built-in cell (issue 21).

Designs the KR 16-2's joint path for the simulated cell of ``jaxtraj design --example``
(workpiece carried by a KR 60-3 along a smooth 3D curve) and reports: the design time
with compilation (first call), a warm re-plan (same shapes, the prediction moved by
5 mm, started from the design), convergence per start (largest violation, KKT
stationarity), the expected mean error and the constraints on a grid 10x finer.

Usage::

    python benchmarks/bench_design_joint.py [--frames 60] [--starts 8] [--inner-steps 500]
        [--estimator dct|smoother1|smoother2] [--out OUT/]

Float64 is enabled below (a benchmark script may do so; library code never does).
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxtraj.design.joint_optimise import design_joint_path  # noqa: E402
from jaxtraj.design_command import design_cell, example_cell, write_design  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--starts", type=int, default=8)
    parser.add_argument("--inner-steps", type=int, default=500)
    parser.add_argument(
        "--estimator",
        choices=("dct", "smoother1", "smoother2"),
        default="dct",
        help="the estimator whose expected error is minimised",
    )
    parser.add_argument("--out", default=None, help="also write the design's files here")
    args = parser.parse_args(argv)
    spec = example_cell(frames=args.frames, starts=args.starts)
    if args.estimator != "dct":
        spec.method, spec.order = "smoother", int(args.estimator[-1])
    res = design_cell(spec, inner_steps=args.inner_steps)
    best, designs = res["best"], res["designs"]
    print(f"design with compilation: {res['seconds']:.1f} s")
    print(
        f"best: expected mean error {1000 * float(best.expected_mean_error):.2f} mm, "
        f"max violation {float(best.max_violation):.1e}, stationarity "
        f"{float(best.stationarity):.1e}, converged {bool(best.converged)}"
    )
    print("per start: converged", np.asarray(designs.converged).tolist())
    print("  stationarity", np.asarray(designs.stationarity).round(5).tolist())
    print("  max violation", np.asarray(designs.max_violation).round(5).tolist())
    print("  mean error [mm]", (1000 * np.asarray(designs.expected_mean_error)).round(2).tolist())
    print("10x finer grid, largest value per constraint:", res["fine_violation"])
    if args.out:
        write_design(args.out, spec, res)
    inits = jnp.stack([best.theta] * args.starts)
    t0 = time.perf_counter()
    warm, _ = design_joint_path(
        res["model"],
        res["cell"],
        spec.predicted + 0.005,
        res["samples"] + 0.005,
        res["basis"],
        inits,
        objective=spec.objective,
        estimator=args.estimator,
        inner_steps=args.inner_steps,
    )
    warm.theta.block_until_ready()
    print(
        f"warm re-plan: {time.perf_counter() - t0:.2f} s, expected mean error "
        f"{1000 * float(warm.expected_mean_error):.2f} mm, stationarity "
        f"{float(warm.stationarity):.1e}, converged {bool(warm.converged)}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Benchmark: the batched solver and estimator drivers on JAX's default device (a GPU if any).

One script for the figures the README gives per accelerator, sized so that the whole run
fits in a few minutes on a lent GPU:

1. ``reconstruct_points`` with its status (the public call, host-side input checks
   included) and the jitted batched kernel alone, float64 and float32, F = 150, k = 10,
   for several N; the vectorised-NumPy structured baseline of ``bench_solve.py`` runs on
   the host CPU in the same process at the smallest N (same data), so the ratio is taken
   in one run;
2. the cost of the conditioning-gain bound (``diagnostics=True`` against ``False``);
3. the batched estimator drivers of ``bench_drivers.py`` at N = 2000, with this platform's
   group sizes (``jaxtraj._batching``);
4. each driver's group size swept (points per step of its loop over points), to check the
   sizes chosen for CPUs and accelerators.

Usage::

    python benchmarks/bench_device.py [--points 2000,16384,131072] [--out FILE]
    python benchmarks/bench_device.py --quick          # small sizes: a smoke run on a CPU

Float64 is enabled below (a benchmark script may do so; library code never does).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

if __name__ == "__main__":
    # One BLAS thread for the NumPy baseline, as in bench_solve.py. Set before NumPy loads.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import fmt_times, fmt_us, machine_info, make_scene, markdown_table, time_call  # noqa: E402
from bench_drivers import cases as driver_cases  # noqa: E402
from bench_solve import _inputs, run_jaxtraj, time_numpy_structured  # noqa: E402


def kernel_per_point(scene, dtype, repeats: int) -> float:
    """Warm seconds per point of the batched kernel that ``reconstruct_points`` calls
    (``jaxtraj.solve._reconstruct_points``, this platform's group size), without the
    host-side input checks."""
    from jaxtraj.solve import _per_step, _reconstruct_points

    P, uv, basis = _inputs(scene, dtype)
    w = jnp.ones(uv.shape[:2], dtype)
    gain = jnp.asarray(20.0, dtype)
    per_step = _per_step(uv)

    def run():
        return _reconstruct_points(P, uv, basis, w, gain, 1, True, None, per_step)

    return time_call(run, repeats=repeats).median / uv.shape[0]


def device_line() -> str:
    devs = jax.devices()
    kinds = sorted({d.device_kind for d in devs})
    return f"jax {jax.__version__}, backend {jax.default_backend()}, {len(devs)} x {kinds}"


def solver_section(sizes: list[int], repeats: int, log) -> list[str]:
    rows = []
    numpy_per_point = None
    for n in sizes:
        scene = make_scene(150, 10, n, seed=0)
        if numpy_per_point is None:
            numpy_per_point = time_numpy_structured(scene, repeats=repeats)
            log(f"NumPy structured baseline (host), N={n}: {fmt_us(numpy_per_point)} us/pt")
        for name, dtype in (("float64", jnp.float64), ("float32", jnp.float32)):
            public = run_jaxtraj(scene, dtype, repeats=repeats)
            kernel = kernel_per_point(scene, dtype, repeats)
            ok = int(np.sum(np.asarray(public.result.status) == 0))
            ratio = numpy_per_point / public.per_point_s
            rows.append(
                [
                    str(n),
                    name,
                    f"{public.first_s:.1f}",
                    fmt_us(public.per_point_s),
                    fmt_us(kernel),
                    f"{1 / public.per_point_s:,.0f}",
                    fmt_times(ratio) if n == sizes[0] else "-",
                    f"{ok}/{n}",
                ]
            )
            log(" | ".join(rows[-1]))
    header = [
        "N",
        "dtype",
        "first call [s]",
        "reconstruct_points [us/point]",
        "kernel alone [us/point]",
        "points/s",
        "vs NumPy structured (host)",
        "status OK",
    ]
    return [
        "## reconstruct_points with status (F = 150, k = 10)",
        "",
        markdown_table(header, rows),
        "",
        f"NumPy structured baseline on the host CPU at N = {sizes[0]}: "
        f"{fmt_us(numpy_per_point)} us per point (float64).",
        "",
    ]


def gain_section(n: int, repeats: int, log) -> list[str]:
    from jaxtraj import reconstruct_points

    scene = make_scene(150, 10, n, seed=0)
    P, uv, basis = (jnp.asarray(x) for x in (scene.P, scene.uv, scene.basis))
    out = {}
    for diag in (True, False):
        t = time_call(lambda d=diag: reconstruct_points(P, uv, basis, diagnostics=d), repeats)
        out[diag] = t.median / n
    log(f"gain: {fmt_us(out[True])} vs {fmt_us(out[False])} us/pt")
    return [
        f"Conditioning-gain bound at N = {n}, float64: {fmt_us(out[True])} us per point with it, "
        f"{fmt_us(out[False])} without ({100 * (out[True] / out[False] - 1):.0f} % extra).",
        "",
    ]


def drivers_section(n: int, n_reg: int, repeats: int, log) -> list[str]:
    rows = []
    for name, (count, fn) in driver_cases(n, n_reg).items():
        t = time_call(fn, repeats)
        rows.append([name, str(count), f"{t.first:.1f}", f"{min(t.runs) / count * 1e3:.3f}"])
        log(" | ".join(rows[-1]))
    header = ["driver", "points", "first call [s]", "warm [ms/point]"]
    return [
        "## Batched estimator drivers (F = 150, best of the warm calls)",
        "",
        markdown_table(header, rows),
        "",
    ]


#: driver -> (module, group-size attributes, sizes to try)
SWEEP = {
    "reconstruct_points (k = 10)": ("jaxtraj.solve", ("MAP_BATCH",), (8, 256, 0)),
    "select_k_points (k = 3..20)": ("jaxtraj.estimators.select_k", ("MAP_BATCH",), (8, 256, 0)),
    "reconstruct_regularised_points (k = 60, CV per point)": (
        "jaxtraj.estimators.regularised",
        ("CV_BATCH",),
        (4, 16, 64),
    ),
    "estimate_points": ("jaxtraj.estimators.estimate", ("MAP_BATCH",), (8, 256, 0)),
}


def sweep_section(n: int, n_reg: int, repeats: int, log) -> list[str]:
    """Each driver with its loop's group size set to each candidate (the platform's own
    attribute is patched: ``X`` on a CPU, ``X_ACCELERATOR`` elsewhere)."""
    import importlib

    from jaxtraj._batching import platform_of

    suffix = "" if platform_of() == "cpu" else "_ACCELERATOR"
    rows = []
    all_cases = driver_cases(n, n_reg)
    for name, (module_name, attrs, sizes) in SWEEP.items():
        module = importlib.import_module(module_name)
        count, fn = all_cases[name]
        saved = {a: getattr(module, a + suffix) for a in attrs}
        try:
            for size in sizes:
                for a in attrs:
                    setattr(module, a + suffix, size)
                t = time_call(fn, repeats)
                label = "all" if size == 0 else str(size)
                rows.append(
                    [name, label, str(count), f"{t.first:.1f}", f"{min(t.runs) / count * 1e3:.3f}"]
                )
                log(" | ".join(rows[-1]))
        finally:
            for a, v in saved.items():
                setattr(module, a + suffix, v)
    header = ["driver", "points per step", "points", "first call [s]", "warm [ms/point]"]
    return ["## Group size of each driver's loop over points", "", markdown_table(header, rows), ""]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", default="2000,16384,131072", help="comma-separated N")
    parser.add_argument("--driver-points", type=int, default=2000)
    parser.add_argument("--regularised-points", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--skip", default="", help="comma-separated: solver, gain, drivers, sweep")
    parser.add_argument("--quick", action="store_true", help="small sizes: a smoke run")
    parser.add_argument("--out", type=Path, default=None, help="write the markdown report here")
    args = parser.parse_args(argv)
    if args.quick:
        args.points, args.driver_points, args.regularised_points, args.repeats = "64", 32, 4, 2
    sizes = [int(s) for s in args.points.split(",")]
    skip = set(filter(None, args.skip.split(",")))

    def log(msg: str) -> None:
        print(f"[bench_device] {msg}", file=sys.stderr, flush=True)

    lines = ["# Solver and drivers on the default JAX device", "", device_line(), ""]
    lines += [f"Host: {machine_info()}.", ""]
    log(lines[2])
    sections = (
        ("solver", lambda: solver_section(sizes, args.repeats, log)),
        ("gain", lambda: gain_section(sizes[0], args.repeats, log)),
        (
            "drivers",
            lambda: drivers_section(
                args.driver_points, args.regularised_points, min(args.repeats, 3), log
            ),
        ),
        ("sweep", lambda: sweep_section(args.driver_points, args.regularised_points, 2, log)),
    )
    for name, section in sections:
        if name in skip:
            continue
        lines += section()
        report = "\n".join(lines)
        if args.out is not None:  # after every section: a run cut short keeps what it did
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(report)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The ``jaxtraj`` command.

Sub-commands:
    demo    simulate the paper's experiment (section 5) in a robot cell, reconstruct the
            workpiece trajectory, print the errors and save the Fig. 3/4 plots.

Exit codes: 0 success, 1 the run finished but its result failed a check (e.g. a
degenerate reconstruction), 2 bad usage or input.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


class UsageError(Exception):
    """Bad input or options: reported as one line, exit code 2."""


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return value


def _nonneg_float(text: str) -> float:
    value = float(text)
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"expected a non-negative number, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxtraj",
        description="Trajectory and 6-DoF pose of a moving workpiece from a robot-carried "
        "monocular camera.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    demo = sub.add_parser(
        "demo",
        help="simulate the paper's experiment, reconstruct, print errors, save plots",
        description="Simulate the paper's experiment (section 5): a workpiece point moved along "
        "an arbitrary smooth 3D curve, images at irregular times from a camera on a second "
        "robot that moves randomly and discontinuously (0.5-1.5 m stand-off, 640x480), "
        "pixel noise; reconstruct the trajectory with the DCT basis and report the "
        "mean/max Euclidean error. Writes fig3_trajectory.png, fig4_errors.png and "
        "summary.json to --out.",
    )
    demo.add_argument(
        "--out",
        type=Path,
        default=Path("jaxtraj-demo"),
        help="output folder (default: ./jaxtraj-demo)",
    )
    demo.add_argument(
        "--frames",
        type=_positive_int,
        default=150,
        help="number of images (default 150, as in the paper)",
    )
    demo.add_argument(
        "--k",
        type=_positive_int,
        default=None,
        help="number of DCT basis vectors for --method dct (default 20)",
    )
    demo.add_argument(
        "--method",
        choices=("dct", "regularised", "smoother"),
        default="dct",
        help="estimator: 'dct' is the paper's plain DCT with a fixed k; 'regularised' a DCT "
        "with a cross-validated roughness penalty (no k to choose); 'smoother' a smoothness "
        "prior without any basis (default: dct)",
    )
    demo.add_argument(
        "--noise",
        type=_nonneg_float,
        default=0.3,
        help="pixel detection noise, standard deviation in px (default 0.3)",
    )
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    demo.add_argument(
        "--float32", action="store_true", help="compute in float32 instead of float64"
    )
    demo.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jaxtraj`` console script; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.command == "demo":
            from .demo import run_demo

            return run_demo(args)
    except UsageError as err:
        print(f"jaxtraj {args.command}: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("jaxtraj: interrupted", file=sys.stderr)
        return 130
    parser.error(f"unknown command {args.command}")  # pragma: no cover
    return EXIT_USAGE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

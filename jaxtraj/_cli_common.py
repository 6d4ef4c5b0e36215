"""What the ``jaxtraj`` command's modules share: exit codes, accuracy targets, UsageError.

:mod:`jaxtraj.cli` (the argument parser), :mod:`jaxtraj.commands` (the sub-commands) and
:mod:`jaxtraj.demo` (``demo --paper``) import these from here, so none of them imports
another's module; :mod:`jaxtraj.cli` re-exports them for user code and the tests.

Exit codes: 0 success; 1 the run finished but its result failed a check (a degenerate
reconstruction, accuracy targets missed); 2 bad usage or input (one line on stderr naming
the file, line and problem); 130 interrupted.
"""

from __future__ import annotations

__all__ = [
    "EXIT_FAILED",
    "EXIT_OK",
    "EXIT_USAGE",
    "SIMULATE_DURATION",
    "SIMULATE_FRAMES",
    "TARGET_ORIENTATION_DEG",
    "TARGET_POSITION_MM",
    "UsageError",
]

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2

#: Accuracy the simulated cell must reach (issue "pipeline"): assembly point, orientation.
TARGET_POSITION_MM, TARGET_ORIENTATION_DEG = 1.0, 0.1

#: ``jaxtraj simulate``'s defaults: images (as in the paper) and recording length [s].
SIMULATE_FRAMES, SIMULATE_DURATION = 150, 10.0


class UsageError(Exception):
    """Bad input or options: reported as one line, exit code 2."""

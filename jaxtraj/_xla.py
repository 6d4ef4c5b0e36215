"""XLA:CPU configuration applied when jaxtraj is imported: small loops as one kernel.

XLA:CPU runs a compiled program as a sequence of "thunks", one per fused kernel. Inside a
``lax.scan`` / ``lax.while_loop`` every iteration pays that dispatch for each of its
kernels. For the camera-pose filter (:func:`jaxtraj.fusion.eskf`: ~40 small kernels per
event, 15x15 matrices) the dispatch costs more than the arithmetic. XLA can instead compile
a loop whose *per-iteration* memory traffic is small into a single native function; the
bound is the backend option ``xla_cpu_small_while_loop_byte_threshold`` (1 KiB by default).

jaxtraj raises that bound to :data:`SMALL_LOOP_BYTES` (1 MiB) by appending it to
``XLA_FLAGS`` at import. Effects, measured by ``benchmarks/bench_fusion.py``:

* the single-stream filter scan (~55 kB per iteration) runs 3-7x faster (552-557k
  against 77-164k IMU samples/s), and filter + RTS smoother went from 56k to 83-86k
  samples/s once the smoother's 15x15 Cholesky solve stopped calling LAPACK
  (:mod:`jaxtraj._linalg`; its scan moves between 256 KiB and 1 MiB per iteration);
* results are unchanged up to rounding (1e-16 m in the filtered positions);
* loops with large per-iteration traffic (batched solves, 64 vmapped streams) and loops
  that call LAPACK or other custom calls keep the usual runtime.

XLA reads ``XLA_FLAGS`` once, when it first compiles. So the option takes effect only if
jaxtraj is imported before the first JAX computation of the process (importing ``jax``
itself is fine). It is not applied when ``XLA_FLAGS`` already sets backend extra options
(the user's choice wins) or when ``JAXTRAJ_XLA_SMALL_LOOPS=0``.
"""

from __future__ import annotations

import os

#: per-iteration bytes below which XLA:CPU compiles a while loop into one kernel
SMALL_LOOP_BYTES = 1_048_576

_OPTION = "xla_cpu_small_while_loop_byte_threshold"
_EXTRA = "--xla_backend_extra_options"


def with_small_loop_flag(xla_flags: str, threshold: int = SMALL_LOOP_BYTES) -> str:
    """``xla_flags`` with the small-loop threshold added, or unchanged if the flags
    already set backend extra options (which a second ``--xla_backend_extra_options``
    would override)."""
    if _EXTRA in xla_flags:
        return xla_flags
    return f"{xla_flags} {_EXTRA}={_OPTION}={int(threshold)}".strip()


def configure_small_loops() -> bool:
    """Append the small-loop option to ``XLA_FLAGS`` (see the module docstring).

    Returns:
        whether ``XLA_FLAGS`` now requests it (it still has no effect if XLA has already
        compiled something in this process).
    """
    if os.environ.get("JAXTRAJ_XLA_SMALL_LOOPS", "1").strip().lower() in ("0", "false", "no"):
        return False
    flags = os.environ.get("XLA_FLAGS", "")
    new = with_small_loop_flag(flags)
    if new != flags:
        os.environ["XLA_FLAGS"] = new
    return _OPTION in new


configure_small_loops()

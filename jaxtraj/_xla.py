"""XLA:CPU configuration applied when jaxtraj is imported: small loops as one kernel, no
YNNPACK fusions.

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

**No YNNPACK fusions.** From jaxlib 0.10, XLA:CPU hands element-wise, reduction and dot
sub-graphs to YNNPACK ("``__ynn_fusion``" custom calls). jaxtraj's programs are made of
many tiny operations (3x3 frame blocks, 30x30 normal equations, per-point loops) and for
them each such call costs more than it saves: on jaxlib 0.10.2 the batched solver compiled
41 of them and ran 2-3x slower than on 0.9.2, which compiles none, and a call inside a loop
body keeps XLA from compiling that loop into one kernel (the RTS smoother). jaxlib 0.10.2
also has reported YNN-fusion bugs: wrong sums after a vmapped matrix-vector product
(jax-ml/jax#39103), crashes and hangs in rank-7/8 reductions (jax-ml/jax#39257, #40412).
So jaxtraj also sets ``--xla_cpu_experimental_ynn_fusion_type=`` (an empty list: no YNN
fusions) at import, on the jaxlib versions it was checked on (:data:`YNN_CHECKED`: the flag
exists there; XLA aborts the process on an unknown flag, so untested versions are left
alone). Not applied when ``XLA_FLAGS`` already names that option or when
``JAXTRAJ_XLA_YNN_FUSIONS=1``.
"""

from __future__ import annotations

import os
from importlib import metadata

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


#: jaxlib versions (major, minor) whose XLA knows the YNN option and was measured with it
YNN_CHECKED = ((0, 9), (0, 10))
_YNN_OPTION = "xla_cpu_experimental_ynn_fusion_type"


def _jaxlib_minor() -> tuple[int, int] | None:
    try:
        major, minor = metadata.version("jaxlib").split(".")[:2]
        return int(major), int(minor)
    except (metadata.PackageNotFoundError, ValueError):
        return None


def with_no_ynn_flag(xla_flags: str) -> str:
    """``xla_flags`` with YNNPACK fusions turned off, or unchanged if the flags already
    name the option (the user's choice wins)."""
    if _YNN_OPTION in xla_flags:
        return xla_flags
    return f"{xla_flags} --{_YNN_OPTION}=".strip()


def configure_no_ynn_fusions() -> bool:
    """Turn YNNPACK fusions off in ``XLA_FLAGS`` (see the module docstring).

    Returns:
        whether ``XLA_FLAGS`` now turns them off (by jaxtraj or by the user).
    """
    if os.environ.get("JAXTRAJ_XLA_YNN_FUSIONS", "0").strip().lower() in ("1", "true", "yes"):
        return False
    flags = os.environ.get("XLA_FLAGS", "")
    if _YNN_OPTION in flags:
        return f"--{_YNN_OPTION}= " in f"{flags} "
    if _jaxlib_minor() not in YNN_CHECKED:
        return False
    os.environ["XLA_FLAGS"] = with_no_ynn_flag(flags)
    return True


configure_small_loops()
configure_no_ynn_fusions()

"""How the batched drivers step through their points, chosen per backend.

The drivers over many points seen by the same cameras (:func:`jaxtraj.reconstruct_points`,
:func:`jaxtraj.estimators.select_k_points`,
:func:`jaxtraj.estimators.reconstruct_regularised_points`, :func:`jaxtraj.estimate_points`
and the chunked batch runner) do a small amount of dense work per point: factorisations of
30x30 to 180x180 systems, short smoother passes. How the points are grouped decides the
speed, and the best grouping differs by backend:

* on a CPU, a loop (``lax.map``) over small groups keeps each group's matrices in cache,
  and XLA:CPU compiles the loop body into one native function (see :mod:`jaxtraj._xla`);
  one ``vmap`` over all points streams every step's arrays through memory instead;
* on a GPU, each loop step launches a sequence of small kernels and waits for them, so a
  loop over small groups leaves the device nearly idle; there the points go in large
  groups, as large as memory allows.

Each driver names both sizes (``MAP_BATCH`` for the CPU and ``MAP_BATCH_ACCELERATOR``);
:func:`points_per_step` picks one from the platform of the input data (a committed
``jax.Array``'s device; under tracing, or for NumPy inputs, JAX's default backend). The
results are the same up to rounding whichever size is used.
"""

from __future__ import annotations

from collections.abc import Callable

import jax

__all__ = ["map_points", "platform_of", "points_per_step"]


def platform_of(x=None) -> str:
    """``"cpu"``, ``"gpu"``, ``"tpu"``...: where an array lives, else the default backend."""
    if isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer):
        try:
            return next(iter(x.devices())).platform
        except (AttributeError, StopIteration, RuntimeError):  # deleted or abstract arrays
            pass
    return jax.default_backend()


def points_per_step(cpu: int, accelerator: int, like=None) -> int:
    """The group size for the platform of ``like`` (see the module docstring); 0 = all."""
    return cpu if platform_of(like) == "cpu" else accelerator


def map_points(fn: Callable, xs, per_step: int):
    """``fn`` over the leading axis of ``xs``: ``lax.map`` in groups of ``per_step`` points
    (one point per step, unbatched, when it is 1), or one ``vmap`` over all of them when
    ``per_step`` is 0."""
    if per_step <= 0:
        return jax.vmap(fn)(xs)
    if per_step == 1:  # one point per step, not a vmap of one (no batched LAPACK call)
        return jax.lax.map(fn, xs)
    return jax.lax.map(fn, xs, batch_size=per_step)

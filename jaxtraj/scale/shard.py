"""Batch axes spread over devices with ``jax.sharding``.

The points of a batch are independent, so the point axis is split over a 1-D device mesh
(``NamedSharding(mesh, PartitionSpec("points"))``) and the jit-compiled batched solver
runs on every device on its slice; cameras and basis are replicated. The same code runs
on one CPU, several GPUs or TPU cores, and, after ``jax.distributed.initialize``, on the
devices of several hosts (``jax.devices()`` then lists all of them). For tests and
benchmarks on one CPU, ``XLA_FLAGS=--xla_force_host_platform_device_count=4`` (set before
JAX is imported) makes four host devices.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as Pspec
from jaxtyping import ArrayLike, Float

from ..solve import Reconstruction, _per_step, _reconstruct_points, _validate

__all__ = ["point_mesh", "reconstruct_recordings_sharded", "reconstruct_sharded", "shard_leading"]


def point_mesh(devices=None) -> Mesh:
    """A 1-D mesh with axis ``"points"`` over ``devices`` (default: all of ``jax.devices()``)."""
    devices = jax.devices() if devices is None else list(devices)
    return Mesh(np.asarray(devices), ("points",))


def shard_leading(x, mesh: Mesh, pad_value=0.0):
    """Put an array on ``mesh`` split along its leading axis (padded with ``pad_value``
    rows to a multiple of the mesh size); returns ``(sharded, original_length)``."""
    x = np.asarray(x)
    n, d = x.shape[0], mesh.devices.size
    pad = (-n) % d
    if pad:
        x = np.concatenate([x, np.full((pad, *x.shape[1:]), pad_value, x.dtype)])
    return jax.device_put(x, NamedSharding(mesh, Pspec(mesh.axis_names[0]))), n


def reconstruct_recordings_sharded(
    P: Float[ArrayLike, "R F 3 4"],
    uv: Float[ArrayLike, "R N F 2"],
    basis: Float[ArrayLike, "F k"],
    weights: Float[ArrayLike, "R N F"] | None = None,
    *,
    mesh: Mesh | None = None,
    max_gain: float = 20.0,
) -> Reconstruction:
    """Many recordings (each its own cameras, same frame count) with the recording axis
    sharded over ``mesh``; fields gain leading axes (R, N). Padded recordings (zero
    weights) are dropped. Equals a loop of :func:`jaxtraj.reconstruct_points`."""
    mesh = point_mesh() if mesh is None else mesh
    P = np.asarray(P)
    if P.ndim != 4 or P.shape[2:] != (3, 4):
        raise ValueError(f"P: expected shape (R, F, 3, 4), got {P.shape}")
    R, F = P.shape[:2]
    uv = np.asarray(uv)
    if uv.ndim != 4 or uv.shape[0] != R or uv.shape[2:] != (F, 2):
        raise ValueError(f"uv: expected shape ({R}, N, {F}, 2), got {uv.shape}")
    dtype = jnp.result_type(P.dtype, jnp.float32)
    w = np.ones(uv.shape[:3], dtype) if weights is None else np.asarray(weights, dtype)
    for r in range(R):
        _validate(P[r], uv[r], basis, w[r], batch=(uv.shape[1],))
    P_s, _ = shard_leading(P.astype(dtype), mesh, pad_value=1.0)
    uv_s, _ = shard_leading(uv.astype(dtype), mesh)
    w_s, _ = shard_leading(w, mesh)
    B = jax.device_put(jnp.asarray(basis, dtype), NamedSharding(mesh, Pspec()))
    res = _recordings(P_s, uv_s, B, w_s, max_gain, _per_step(uv_s))
    return jax.tree_util.tree_map(lambda a: a[:R], res)


@functools.partial(jax.jit, static_argnames="per_step")
def _recordings(P, uv, basis, w, max_gain, per_step):
    def one(p, u, ww):
        return _reconstruct_points(p, u, basis, ww, max_gain, 1, True, None, per_step)

    return jax.vmap(one)(P, uv, w)


def reconstruct_sharded(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "N F 2"],
    basis: Float[ArrayLike, "F k"],
    weights: Float[ArrayLike, "N F"] | None = None,
    *,
    mesh: Mesh | None = None,
    max_gain: float = 20.0,
    refine: int = 1,
    diagnostics: bool = True,
) -> Reconstruction:
    """:func:`jaxtraj.reconstruct_points` with the point axis sharded over ``mesh``.

    N is padded to a multiple of the mesh size (padded points have weight 0 and are
    dropped); results equal the single-device call. Outputs stay sharded on the devices
    (``jax.device_get`` gathers them).
    """
    mesh = point_mesh() if mesh is None else mesh
    batch = (np.shape(uv)[0],)
    _validate(P, uv, basis, weights, batch=batch)
    dtype = jnp.result_type(jnp.asarray(P).dtype, jnp.float32)
    n = np.shape(uv)[0]
    d = mesh.devices.size
    pad = (-n) % d
    uv = np.asarray(uv, dtype)
    w = np.ones(uv.shape[:2], dtype) if weights is None else np.asarray(weights, dtype)
    if pad:
        uv = np.concatenate([uv, np.zeros((pad, *uv.shape[1:]), dtype)])
        w = np.concatenate([w, np.zeros((pad, w.shape[1]), dtype)])
    split = NamedSharding(mesh, Pspec("points"))
    same = NamedSharding(mesh, Pspec())
    uv_s, w_s = jax.device_put(uv, split), jax.device_put(w, split)
    P_r = jax.device_put(jnp.asarray(P, dtype), same)
    B_r = jax.device_put(jnp.asarray(basis, dtype), same)
    per_step = _per_step(uv_s)
    res = _reconstruct_points(P_r, uv_s, B_r, w_s, max_gain, refine, diagnostics, None, per_step)
    return jax.tree_util.tree_map(lambda a: a[:n], res) if pad else res

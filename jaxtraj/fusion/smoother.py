"""Error-state Rauch-Tung-Striebel smoother over a filtered event stream.

Backward from the last event, with ``F``, ``Q`` and the predicted nominal state
recomputed from the stored filtered state and the rates that propagated it::

    x^-_{k+1} = f(x_k, u_{k+1}),  P^-_{k+1} = F P_k F^T + Q
    C_k = P_k F^T (P^-_{k+1})^-1
    x_{k|N} = x_k (+) C_k (x_{k+1|N} (-) x^-_{k+1})
    P_{k|N} = P_k + C_k (P_{k+1|N} - P^-_{k+1}) C_k^T

Differences and injections use the local orientation error, so in the linear limit
(orientation frozen) this is exactly the textbook RTS smoother. Error components with
exactly zero predicted variance (e.g. a frozen orientation) are left out of the inverse
and get no correction. The 15x15 Cholesky solve is unrolled (:mod:`jaxtraj._linalg`), so
XLA:CPU compiles the backward scan into one kernel.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import ArrayLike, Float

from .._linalg import cholesky_small, solve_triangular_small
from .eskf import FusionResult
from .imu import (
    ImuNoise,
    apply_transition,
    boxminus,
    boxplus,
    process_noise_diag,
    propagate,
    propagate_covariance,
)

__all__ = ["rts_smoother"]


def _gain(FP, P_pred):
    """``C = P F^T P_pred^-1`` by an equilibrated Cholesky solve (zero variances skipped)."""
    d = jnp.diagonal(P_pred)
    zero = d <= 0
    s = jnp.where(zero, 1.0, jnp.sqrt(jnp.where(zero, 1.0, d)))
    Pn = P_pred / (s[:, None] * s[None, :]) + jnp.diag(zero.astype(FP.dtype))
    Pn = 0.5 * (Pn + Pn.T)
    rhs = FP / s[:, None]
    L = cholesky_small(Pn)
    Ct = solve_triangular_small(L, solve_triangular_small(L, rhs), trans=1) / s[:, None]
    return Ct.T


@jax.jit
def rts_smoother(
    result: FusionResult,
    noise: ImuNoise,
    gravity_w: Float[ArrayLike, " 3"] = (0.0, 0.0, -9.81),
) -> FusionResult:
    """Smooth a filtered stream (filter run with ``reset="full"`` and ``store="full"``).

    Args:
        result: output of :func:`~jaxtraj.fusion.eskf` for one stream (E events).
        noise: the IMU noise the filter used.
        gravity_w: (3,) gravity in the world [m/s^2], as in the filter.

    Returns:
        a :class:`FusionResult` with smoothed states and covariances (``nis``/``nll``
        are the filter's).
    """
    if result.P.ndim != result.t.ndim + 2:
        raise ValueError("result: the smoother needs full covariances (filter store='full')")
    if result.t.ndim != 1:
        raise ValueError(f"result: expected one stream (E,), got t of shape {result.t.shape}")
    dtype = result.t.dtype
    g = jnp.asarray(gravity_w, dtype)

    def step(carry, inp):
        xs_next, Ps_next = carry
        x, P, u, dt = inp
        x_pred, imu_step = propagate(x, u[:3], u[3:], dt, g)
        FP = apply_transition(imu_step, P)
        P_pred = propagate_covariance(P, imu_step, process_noise_diag(noise, dt, dtype))
        C = _gain(FP, P_pred)
        xs = boxplus(x, C @ boxminus(xs_next, x_pred))
        Ps = P + C @ (Ps_next - P_pred) @ C.T
        Ps = 0.5 * (Ps + Ps.T)
        return (xs, Ps), (xs, Ps)

    last = jax.tree_util.tree_map(lambda a: a[-1], result.x)
    head = jax.tree_util.tree_map(lambda a: a[:-1], result.x)
    _, (xs, Ps) = jax.lax.scan(
        step,
        (last, result.P[-1]),
        (head, result.P[:-1], result.u[1:], result.dt[1:]),
        reverse=True,
    )
    x_all = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b[None]]), xs, last)
    return FusionResult(
        t=result.t,
        kind=result.kind,
        index=result.index,
        x=x_all,
        P=jnp.concatenate([Ps, result.P[-1:]]),
        u=result.u,
        dt=result.dt,
        nis=result.nis,
        nll=result.nll,
        updated=result.updated,
    )

"""On-line (recursive) DCT trajectory estimation over a sliding window of frames.

Frames arrive one at a time at robot rate. The state keeps the information form
``(N, b)`` of the coefficients (the normal equations of :func:`jaxtraj.normal_equations`)
and a ring buffer of the last ``window`` frames' ray-constraint blocks ``Q^T Q`` (3x3),
``Q^T q`` (3) and times. Each update adds the new frame's term
``(phi phi^T) (x) Q^T Q`` and, once the window is full, subtracts the oldest frame's: O(k^2)
per frame, independent of the window length. The basis is a :class:`jaxtraj.DCTBasis` on
a fixed span; when the window approaches the end of the span, :func:`stream_rebase`
moves the span and rebuilds ``(N, b)`` from the buffer in O(window k^2). The estimate
(position, velocity and a prediction a few tens of milliseconds ahead, which the robot
controller needs to synchronise) costs one (3k)x(3k) Cholesky solve and equals the batch
:func:`jaxtraj.reconstruct` on the window's frames with the same basis.

Everything is a pure function of an :class:`equinox.Module` state, so a whole recording
runs as one ``lax.scan`` (:func:`stream_run`) and many tracks run under ``vmap``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._checks import check_shape
from .._spd import inverse_cholesky, matvec, vecmat
from ..basis import DCTBasis

__all__ = [
    "StreamEstimate",
    "StreamState",
    "stream_estimate",
    "stream_init",
    "stream_rebase",
    "stream_run",
    "stream_update",
]


class StreamState(eqx.Module):
    """Sliding-window information state of one point's DCT coefficients.

    Attributes:
        basis: the :class:`jaxtraj.DCTBasis` (span, k) the information refers to.
        N: (3k, 3k) information matrix; b: (3k,) information vector.
        QtQ: (W, 3, 3), Qtq: (W, 3), times: (W,), valid: (W,) the ring buffer.
        head: index of the slot the next frame overwrites; count: frames seen.
    """

    basis: DCTBasis
    N: Float[Array, "3k 3k"]
    b: Float[Array, " 3k"]
    QtQ: Float[Array, "W 3 3"]
    Qtq: Float[Array, "W 3"]
    times: Float[Array, " W"]
    valid: Bool[Array, " W"]
    head: Int[Array, ""]
    count: Int[Array, ""]


class StreamEstimate(eqx.Module):
    """Current estimate: ``position`` and ``velocity`` at ``time`` [m, m/s],
    ``predicted`` position at ``time + horizon`` [m], ``coeffs`` (k, 3), and ``ok``
    (enough frames in the window, ``2 W' >= 3 k``)."""

    position: Float[Array, " 3"]
    velocity: Float[Array, " 3"]
    predicted: Float[Array, " 3"]
    coeffs: Float[Array, "k 3"]
    ok: Bool[Array, ""]


def stream_init(basis: DCTBasis, window: int) -> StreamState:
    """An empty state for a basis on a fixed span and a window of ``window`` frames."""
    if not isinstance(basis, DCTBasis):
        raise ValueError(f"basis: expected a DCTBasis (fixed span), got {type(basis).__name__}")
    if not isinstance(window, int) or window < 1:
        raise ValueError(f"window: expected a positive int number of frames, got {window!r}")
    dtype = basis.t0.dtype
    n = 3 * basis.k
    return StreamState(
        basis=basis,
        N=jnp.zeros((n, n), dtype),
        b=jnp.zeros(n, dtype),
        QtQ=jnp.zeros((window, 3, 3), dtype),
        Qtq=jnp.zeros((window, 3), dtype),
        times=jnp.zeros(window, dtype),
        valid=jnp.zeros(window, bool),
        head=jnp.asarray(0, jnp.int32),
        count=jnp.asarray(0, jnp.int32),
    )


def _frame_term(basis, t, QtQ, Qtq):
    phi = basis(jnp.reshape(t, (1,)))[0]
    N = jnp.einsum("u,v,ij->uivj", phi, phi, QtQ).reshape(3 * basis.k, 3 * basis.k)
    return N, jnp.outer(phi, Qtq).reshape(-1)


def stream_update(
    state: StreamState,
    P: Float[ArrayLike, "3 4"],
    uv: Float[ArrayLike, " 2"],
    time: float,
    weight: float = 1.0,
) -> StreamState:
    """Add one frame (projection matrix, pixel [px], time [s], weight) in O(k^2).

    A frame with weight 0 (missing detection) occupies a window slot but adds nothing.
    """
    check_shape("P", P, (3, 4), "one projection matrix")
    check_shape("uv", uv, (2,), "one pixel")
    dtype = state.N.dtype
    P = jnp.asarray(P, dtype)
    uv = jnp.asarray(uv, dtype)
    w = jnp.asarray(weight, dtype)
    uv = jnp.where(w > 0, uv, 0.0)
    rows = P[:2, :] - uv[:, None] * P[2:3, :]
    Q, q = rows[:, :3], -rows[:, 3]
    QtQ, Qtq = w * Q.T @ Q, w * Q.T @ q
    i = state.head
    N_old, b_old = _frame_term(state.basis, state.times[i], state.QtQ[i], state.Qtq[i])
    old = state.valid[i]
    N_new, b_new = _frame_term(state.basis, time, QtQ, Qtq)
    N = state.N + N_new - jnp.where(old, N_old, 0.0)
    b = state.b + b_new - jnp.where(old, b_old, 0.0)
    W = state.times.shape[0]
    return StreamState(
        basis=state.basis,
        N=0.5 * (N + N.T),
        b=b,
        QtQ=state.QtQ.at[i].set(QtQ),
        Qtq=state.Qtq.at[i].set(Qtq),
        times=state.times.at[i].set(jnp.asarray(time, dtype)),
        valid=state.valid.at[i].set(w > 0),
        head=(i + 1) % W,
        count=state.count + 1,
    )


def stream_rebase(state: StreamState, basis: DCTBasis) -> StreamState:
    """Rebuild the information for a new basis (e.g. a span moved forward), O(W k^2)."""
    if not isinstance(basis, DCTBasis):
        raise ValueError(f"basis: expected a DCTBasis, got {type(basis).__name__}")
    phi = basis(state.times) * state.valid[:, None]
    k = basis.k
    outer = (phi[:, :, None] * phi[:, None, :]).reshape(-1, k * k)
    N = (outer.T @ state.QtQ.reshape(-1, 9)).reshape(k, k, 3, 3).transpose(0, 2, 1, 3)
    b = (phi.T @ state.Qtq).reshape(-1)
    return eqx.tree_at(lambda s: (s.basis, s.N, s.b), state, (basis, N.reshape(3 * k, 3 * k), b))


def stream_estimate(
    state: StreamState, time: float | None = None, horizon: float = 0.0
) -> StreamEstimate:
    """Solve the window's normal equations; position/velocity at ``time`` (default: the
    latest frame's time) and the position ``horizon`` seconds later."""
    dtype = state.N.dtype
    k = state.basis.k
    N, b = state.N, state.b
    d = jax.lax.rsqrt(jnp.maximum(jnp.diag(N), jnp.finfo(dtype).tiny))
    # A ridge of sqrt(eps) on the unit-diagonal system: a window much shorter than the
    # basis span leaves directions of the coefficients it cannot see (the DCT functions are
    # nearly collinear on a short interval); without it, rounding alone would move the
    # solution along them by centimetres. One refinement step with the exact N removes
    # the ridge's bias from every well-determined direction (error factor (ridge/lambda)^2).
    ridge = jnp.sqrt(jnp.finfo(dtype).eps)
    Ns = N * d[:, None] * d[None, :] + ridge * jnp.eye(3 * k, dtype=dtype)
    W = inverse_cholesky(Ns)  # no LAPACK: many tracks run under vmap (see jaxtraj._spd)

    def solve(rhs):
        return d * vecmat(matvec(W, d * rhs), W)

    beta = solve(b)
    beta = beta + solve(b - N @ beta)  # refinement
    coeffs = beta.reshape(k, 3)
    latest = state.times[(state.head - 1) % state.times.shape[0]]
    t = latest if time is None else jnp.asarray(time, dtype)
    ts = jnp.stack([t, t + horizon])
    pos = state.basis(ts) @ coeffs
    vel = state.basis(ts[:1], derivative=1)[0] @ coeffs
    ok = 2 * jnp.sum(state.valid) >= 3 * k
    return StreamEstimate(position=pos[0], velocity=vel, predicted=pos[1], coeffs=coeffs, ok=ok)


@eqx.filter_jit
def stream_run(
    state: StreamState,
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "F 2"],
    times: Float[ArrayLike, " F"],
    weights: Float[ArrayLike, " F"] | None = None,
    horizon: float = 0.0,
) -> tuple[StreamState, StreamEstimate]:
    """Feed F frames in order (one ``lax.scan``); returns the final state and the
    estimate after every frame (fields with a leading axis F)."""
    check_shape("P", P, (None, 3, 4), "one projection matrix per frame")
    F = P.shape[0]
    check_shape("uv", uv, (F, 2), "one pixel per frame")
    check_shape("times", times, (F,), "one time per frame")
    dtype = state.N.dtype
    w = jnp.ones(F, dtype) if weights is None else jnp.asarray(weights, dtype)

    def step(s, frame):
        P_i, uv_i, t_i, w_i = frame
        s = stream_update(s, P_i, uv_i, t_i, w_i)
        return s, stream_estimate(s, horizon=horizon)

    return jax.lax.scan(
        step, state, (jnp.asarray(P, dtype), jnp.asarray(uv, dtype), jnp.asarray(times, dtype), w)
    )

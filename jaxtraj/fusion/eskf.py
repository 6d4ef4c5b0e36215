"""Error-state Kalman filter over one event stream, as a jit-compiled ``lax.scan``.

At every event the filter first propagates from the previous event time with the IMU
rates linearly interpolated at the interval's midpoint (:mod:`.imu`), then

* IMU event: takes the new sample (and the next one) as the current segment;
* pose event: updates with the IMU pose ``T_w_i`` measured through the hand-eye and
  IMU-camera transforms (residual ``[z_p - p; Log(R^T R_z)]``, ``H = [I 0 0 0 0; 0 0 I 0
  0]``), Joseph form, injection into the nominal state and the reset ``P <- G P G^T``;
* image event: nothing; the stored state is the estimate at the image time.

Written for one recording; batch recordings with ``jax.vmap`` (same event count) or
:func:`eskf_batch` (faster when the streams share one event layout). The dtype of the
result follows the inputs (float64 or float32). Small matrix products are written as
fusible multiply-sums and the 6x6 innovation covariance is inverted in closed form
(3x3 blocks), which on CPU is several times faster than dot/LAPACK calls per event.
"""

from __future__ import annotations

import functools
import math
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._linalg import cholesky_small, solve_triangular_small
from .events import IMU, POSE, EventStream
from .imu import (
    ImuNoise,
    NominalState,
    _mm,
    apply_transition,
    boxminus,
    boxplus,
    process_noise_diag,
    propagate,
    propagate_covariance,
    right_jacobian,
)

__all__ = ["FusionResult", "eskf", "eskf_batch", "initial_covariance", "initial_state", "nees"]


class FusionResult(eqx.Module):
    """Filtered (or smoothed) states at every event (one stream; ``vmap`` adds axes).

    Attributes:
        t, kind, index: (E,) event times [s], kinds and input indices (as in the stream).
        x: nominal states after each event (fields with a leading (E,) axis).
        P: (E, 15, 15) error covariance after each event, or (E, 15) variances when
            the filter ran with ``store="diag"``.
        u: (E, 6) rates (gyro, accel) that propagated into each event.
        dt: (E,) length of that propagation [s].
        nis: (E,) normalised innovation squared of pose updates (0 elsewhere).
        nll: (E,) negative log-likelihood of each pose update (0 elsewhere).
        updated: (E,) whether the event updated the filter.
    """

    t: Float[Array, " E"]
    kind: Int[Array, " E"]
    index: Int[Array, " E"]
    x: NominalState
    P: Float[Array, "E 15 15"] | Float[Array, "E 15"]
    u: Float[Array, "E 6"]
    dt: Float[Array, " E"]
    nis: Float[Array, " E"]
    nll: Float[Array, " E"]
    updated: Bool[Array, " E"]

    @property
    def variances(self) -> Array:
        """(E, 15) error variances (diagonal of ``P``)."""
        return self.P if self.P.ndim == self.t.ndim + 1 else jnp.diagonal(self.P, 0, -2, -1)

    @property
    def ok(self) -> Array:
        """Whether every stored state and covariance is finite (jit-safe flag)."""
        leaves = [*jax.tree_util.tree_leaves(self.x), self.P]
        return jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in leaves]))


def initial_covariance(
    position: float,
    velocity: float,
    orientation: float,
    accel_bias: float,
    gyro_bias: float,
    dtype=jnp.float64,
) -> Float[Array, "15 15"]:
    """Diagonal (15, 15) prior from standard deviations [m, m/s, rad, m/s^2, rad/s]."""
    s = jnp.repeat(jnp.asarray([position, velocity, orientation, accel_bias, gyro_bias]), 3)
    return jnp.diag(jnp.square(s)).astype(dtype)


def initial_state(events: EventStream) -> NominalState:
    """A starting state at the first IMU time from the first two active pose events:
    orientation of the first, velocity from their difference, position extrapolated
    back to the start, zero biases. Put the uncertainty of this guess into ``P0``."""
    n = events.t.shape[0]
    ar = jnp.arange(n)
    i0 = jnp.argmax(events.active)
    i1 = jnp.argmax(events.active & (ar > i0))
    t0 = jnp.min(jnp.where(events.kind == IMU, events.t, jnp.inf))
    v = (events.z_p[i1] - events.z_p[i0]) / (events.t[i1] - events.t[i0])
    p = events.z_p[i0] - v * (events.t[i0] - t0)
    return NominalState.create(p, events.z_q[i0], v=v)


class _Carry(eqx.Module):
    x: NominalState
    P: Array
    dx: Array
    t: Array
    seg_t0: Array
    seg_t1: Array
    seg_u0: Array
    seg_u1: Array


def _inv3(A: Array) -> tuple[Array, Array]:
    """Inverse and determinant of a 3x3 matrix by cofactors (fusible elementwise ops)."""
    c0 = jnp.cross(A[1], A[2])
    c1 = jnp.cross(A[2], A[0])
    c2 = jnp.cross(A[0], A[1])
    det = jnp.dot(A[0], c0)
    return jnp.stack([c0, c1, c2], axis=1) / det, det


def _inv_spd6(S: Array) -> tuple[Array, Array]:
    """Inverse and log-determinant of a 6x6 SPD matrix: equilibration, then 3x3 blocks
    and their Schur complement (cheaper than a LAPACK call for one small matrix)."""
    d = jnp.sqrt(jnp.diagonal(S))
    Sn = S / (d[:, None] * d[None, :])
    A, B, D = Sn[:3, :3], Sn[:3, 3:], Sn[3:, 3:]
    Ai, detA = _inv3(A)
    AiB = _mm(Ai, B)
    Sc = D - _mm(B.T, AiB)
    Sci, detS = _inv3(0.5 * (Sc + Sc.T))
    top_right = -_mm(AiB, Sci)
    top_left = Ai - _mm(top_right, AiB.T)
    inv = jnp.concatenate(
        [jnp.concatenate([top_left, top_right], 1), jnp.concatenate([top_right.T, Sci], 1)]
    )
    inv = inv / (d[:, None] * d[None, :])
    return 0.5 * (inv + inv.T), 2.0 * jnp.sum(jnp.log(d)) + jnp.log(detA) + jnp.log(detS)


def _select(M: Array) -> Array:
    """Rows 0:3 and 6:9 (position and orientation) of M: ``H @ M``."""
    return jnp.concatenate([M[0:3], M[6:9]])


def _update(x: NominalState, P, dx, z_p, z_q, Rm, reset: str):
    """One pose update (Joseph form); returns the new (x, P, dx, nis, nll)."""
    r = jnp.concatenate([z_p - x.p, (jaxlie.SO3(x.q).inverse() @ jaxlie.SO3(z_q)).log()])
    if reset == "none":  # error mean is carried, not injected
        r = r - _select(dx)
    PHt = _select(P).T
    S = _select(PHt) + Rm
    Sinv, logdet = _inv_spd6(0.5 * (S + S.T))
    K = _mm(PHt, Sinv)
    nis = r @ Sinv @ r
    nll = 0.5 * (nis + logdet + 6.0 * math.log(2.0 * math.pi))
    A = P - _mm(K, PHt.T)  # (I - K H) P
    P = A - _mm(_select(A.T).T, K.T) + _mm(_mm(K, Rm), K.T)
    d = K @ r
    if reset == "none":
        dx = dx + d
    else:
        x = boxplus(x, d)
        if reset == "full":  # P <- G P G^T, G = blockdiag(I, J_r(dtheta), I)
            G = right_jacobian(d[6:9])
            P = P.at[6:9].set(_mm(G, P[6:9]))
            P = P.at[:, 6:9].set(_mm(P[:, 6:9], G.T))
    return x, 0.5 * (P + P.T), dx, nis, nll


@functools.partial(jax.jit, static_argnames=("reset", "store", "unroll"))
def eskf(
    events: EventStream,
    x0: NominalState,
    P0: Float[ArrayLike, "15 15"],
    noise: ImuNoise,
    gravity_w: Float[ArrayLike, " 3"] = (0.0, 0.0, -9.81),
    *,
    reset: Literal["full", "no_jacobian", "none"] = "full",
    store: Literal["full", "diag"] = "full",
    unroll: int = 1,
) -> FusionResult:
    """Run the error-state Kalman filter over an event stream.

    Args:
        events: from :func:`~jaxtraj.fusion.build_events` (E events).
        x0: nominal state at the first IMU time.
        P0: (15, 15) covariance of its error.
        noise: IMU noise densities and bias random walks.
        gravity_w: (3,) gravity in the world frame [m/s^2].
        reset: ``"full"`` (inject and apply the reset Jacobian; the correct filter),
            ``"no_jacobian"`` (inject, ``G = I``) or ``"none"`` (never inject: the error
            mean is propagated and the nominal state runs open loop). The last two are for
            studying the reset: ``"none"`` fails the NEES test; ``"no_jacobian"`` differs
            from ``"full"`` only at second order in the correction, which is invisible
            at the correction sizes of a robot cell.
        store: ``"full"`` keeps (E, 15, 15) covariances (needed by the smoother and
            NEES), ``"diag"`` only their diagonals (less memory for long or many streams).
        unroll: ``lax.scan`` unroll factor.

    Returns:
        a :class:`FusionResult` with the state after every event.
    """
    if reset not in ("full", "no_jacobian", "none"):
        raise ValueError(f"reset: expected 'full', 'no_jacobian' or 'none', got {reset!r}")
    if store not in ("full", "diag"):
        raise ValueError(f"store: expected 'full' or 'diag', got {store!r}")
    dtype = events.t.dtype
    x0 = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), x0)
    P0 = jnp.asarray(P0, dtype)
    if P0.shape != (15, 15):
        raise ValueError(f"P0: expected shape (15, 15), got {P0.shape}")
    g = jnp.asarray(gravity_w, dtype)
    first = jnp.argmax(events.kind == IMU)
    carry = _Carry(
        x=x0,
        P=P0,
        dx=jnp.zeros(15, dtype),
        t=events.t[first],
        seg_t0=events.t[first],
        seg_t1=events.t1[first],
        seg_u0=events.u0[first],
        seg_u1=events.u1[first],
    )
    # one packed row per event and per output: fewer slices per scan step
    # the layout flags stay a separate (possibly unbatched, see eskf_batch) input
    flags = jnp.stack([events.kind == IMU, (events.kind == POSE) & events.active], axis=1)
    rows = jnp.concatenate(
        [
            events.t[:, None],
            events.t1[:, None],
            events.u0,
            events.u1,
            events.z_p,
            events.z_q,
            events.R.reshape(-1, 36),
        ],
        axis=1,
    )

    def step(c: _Carry, inp):
        row, (imu_ev, do_update) = inp
        t_ev, t1 = row[0], row[1]
        u0, u1, z_p, z_q = row[2:8], row[8:14], row[14:17], row[17:21]
        t = jnp.maximum(t_ev, c.t)
        dt = t - c.t
        span = jnp.where(c.seg_t1 > c.seg_t0, c.seg_t1 - c.seg_t0, 1.0)
        w = jnp.clip((c.t + 0.5 * dt - c.seg_t0) / span, 0.0, 1.0)
        u = c.seg_u0 + w * (c.seg_u1 - c.seg_u0)
        x, imu_step = propagate(c.x, u[:3], u[3:], dt, g)
        P = propagate_covariance(c.P, imu_step, process_noise_diag(noise, dt, dtype))
        dx = apply_transition(imu_step, c.dx[:, None])[:, 0] if reset == "none" else c.dx
        x, P, dx, nis, nll = jax.lax.cond(
            do_update,
            lambda a: _update(*a, z_p, z_q, row[21:57].reshape(6, 6), reset),
            lambda a: (*a, jnp.zeros((), dtype), jnp.zeros((), dtype)),
            (x, P, dx),
        )
        c = _Carry(
            x=x,
            P=P,
            dx=dx,
            t=t,
            seg_t0=jnp.where(imu_ev, t_ev, c.seg_t0),
            seg_t1=jnp.where(imu_ev, t1, c.seg_t1),
            seg_u0=jnp.where(imu_ev, u0, c.seg_u0),
            seg_u1=jnp.where(imu_ev, u1, c.seg_u1),
        )
        x_out = boxplus(x, dx) if reset == "none" else x
        P_out = P.reshape(-1) if store == "full" else jnp.diagonal(P)
        flag = do_update.astype(dtype)[None]
        out = jnp.concatenate(
            [*jax.tree_util.tree_leaves(x_out), u, dt[None], nis[None], nll[None], flag, P_out]
        )
        return c, out

    _, out = jax.lax.scan(step, carry, (rows, flags), unroll=unroll)
    x_out = NominalState(
        p=out[:, 0:3], v=out[:, 3:6], q=out[:, 6:10], b_a=out[:, 10:13], b_g=out[:, 13:16]
    )
    P_out = out[:, 26:].reshape(-1, 15, 15) if store == "full" else out[:, 26:]
    return FusionResult(
        t=events.t,
        kind=events.kind,
        index=events.index,
        x=x_out,
        P=P_out,
        u=out[:, 16:22],
        dt=out[:, 22],
        nis=out[:, 23],
        nll=out[:, 24],
        updated=out[:, 25] > 0,
    )


def eskf_batch(
    events: EventStream,
    x0: NominalState,
    P0: Float[ArrayLike, "15 15"],
    noise: ImuNoise,
    gravity_w: Float[ArrayLike, " 3"] = (0.0, 0.0, -9.81),
    **options,
) -> FusionResult:
    """:func:`eskf` over a batch of recordings (leading axis B on ``events`` and ``x0``).

    Under a plain ``vmap`` a pose update that happens in one stream is computed (and
    discarded) at every event of every stream. When all streams share one event layout
    (the same kinds and active flags in the same order: Monte-Carlo runs, recordings on
    a common clock) this passes the layout unbatched, so the update remains a real
    branch. Otherwise it falls back to a plain ``vmap``. Options as for :func:`eskf`.
    """
    kind, active = events.kind, events.active
    if kind.ndim != 2:
        raise ValueError(
            f"events: expected a batch (B, E) of streams, got kind of shape {kind.shape}"
        )
    shared = (
        not isinstance(kind, jax.core.Tracer)
        and not isinstance(active, jax.core.Tracer)
        and bool(jnp.all(kind == kind[0]))
        and bool(jnp.all(active == active[0]))
    )
    run = functools.partial(eskf, P0=P0, noise=noise, gravity_w=gravity_w, **options)
    if not shared:
        return jax.vmap(lambda e, x: run(e, x0=x))(events, x0)
    axes = EventStream(t=0, kind=None, active=None, index=0, u0=0, u1=0, t1=0, z_p=0, z_q=0, R=0)
    layout = EventStream(
        t=events.t,
        kind=kind[0],
        active=active[0],
        index=events.index,
        u0=events.u0,
        u1=events.u1,
        t1=events.t1,
        z_p=events.z_p,
        z_q=events.z_q,
        R=events.R,
    )
    return jax.vmap(lambda e, x: run(e, x0=x), in_axes=(axes, 0))(layout, x0)


def nees(result: FusionResult, truth: NominalState) -> Float[Array, " E"]:
    """Normalised estimation error squared ``e^T P^-1 e`` with ``e = truth (-) estimate``
    at every event (15 degrees of freedom). ``truth`` has the same (E,) leading axis."""
    if result.P.ndim != result.t.ndim + 2:
        raise ValueError("result: NEES needs full covariances; run the filter with store='full'")

    def one(x_est, x_true, P):
        e = boxminus(x_true, x_est)
        # by a written-out Cholesky factor: vmapped over events, jnp.linalg.solve would be
        # a batched LAPACK call (deadlocked on 2 cores with jaxlib 0.10, see jaxtraj._spd)
        y = solve_triangular_small(cholesky_small(0.5 * (P + P.T)), e)
        return y @ y

    return jax.vmap(one)(result.x, truth, result.P)

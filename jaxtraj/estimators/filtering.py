"""Recursive Bayesian tracking of one point from a known start: a sigma-point (or
extended) Kalman filter and Rauch-Tung-Striebel smoother on the pixels, as ``lax.scan``s.

This is the estimator to use when the state at the first frame is roughly known (a
hand-over from the robot, the end of an earlier track, a CAD pose) and the camera moves
slowly or smoothly. There the pixels fix the point only up to a depth that changes along
the rays, and :func:`jaxtraj.estimators.smooth_trajectory`, which finds the exact
posterior mode of the same model, follows that ambiguity: under a white-noise prior a
trajectory shrunk towards the camera projects to the same pixels with less acceleration,
so the mode is drawn towards the camera (measured: 0.4-0.8 m off on slow robot-cell
scenes with a 5 cm start prior). A filter linearises each frame's projection once, at
the state predicted from the frames before, and so carries the depth of its start
forward; on those scenes it stays about 10 cm off, as a sigma-point smoother of the
same model from the tracking literature does. Where the camera moves enough to
fix the depth (fast or random paths), both agree and the posterior-mode smoother needs no
start at all.

Model (the same as :mod:`.smoothness`): the state ``s_i`` (position, velocity, ...) of
the point at frame time ``t_i`` follows the integrated Wiener process of ``order`` with
noise density ``q`` (``order=2``: white-noise acceleration, constant velocity), exactly
discretised at the real frame times; the pixel of frame ``i`` is ``pi(P_i p_i)`` plus
white noise of ``pixel_sigma / sqrt(w_i)`` px. The measurement update is either the
third-degree spherical-radial cubature rule (``"cubature"``: 2 n sigma points of equal,
positive weight, so every covariance stays positive definite; the unscented transform
with ``alpha = 1, beta = 0, kappa = 0``) or a first-order linearisation at the predicted
mean (``"extended"``). The dynamics are linear, so prediction and smoothing are exact.

Which rule: the cubature rule's pixel covariance carries the projection's curvature
across the predicted spread, so it updates more cautiously; that pays where the start is
rough and the camera fast (10-15 % closer than the first-order rule with a start drawn
from its prior), while the first-order rule is 3-7 % closer with an exact start on random
cameras and with the motion-capture slow and smooth cameras, but 4-5 % behind with the
simulated slow ones (measured point by point in ``benchmarks/bench_estimators.py
--paired``).
Two alternatives were measured on the same scenes and not adopted: iterating each
frame's update at its updated state (the iterated extended / posterior-linearisation
update) converges to each frame's posterior mode and inherits the mode's drift towards
the camera, 2-6x worse with slow and smooth cameras; the first-order mean with the
cubature covariances matches the better rule in some cases but is 4-7 % behind it in
others (slow simulated cameras, random cameras with an exact start).

Frames with weight 0 are skipped; an optional innovation gate skips frames whose squared
Mahalanobis distance exceeds ``gate`` (outlier detections), and those are not counted in
``num_observed``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from .._checks import check_shape
from .._linalg import cholesky_small, solve_spd_small
from ..solve import Status
from ._common import as_float, check_positive, linearise, normalise_cameras, validate_track
from .smoothness import (
    Smoothed,
    _q_scale,
    _q_unit,
    _transition,
    _validate_batch,
    _validate_start,
)

__all__ = ["filter_points", "filter_trajectory"]

RULES = ("cubature", "extended")


def _process(dt, order: int, q):
    """Transition ``A`` (.., s, s) and process covariance ``Q`` (.., s, s) on (order, 3)
    states flattened position first, for noise density ``q``."""
    A, _ = _transition(dt, order)
    Qbar, _ = _q_unit(order)
    d = _q_scale(dt, order)
    Qs = q * jnp.asarray(Qbar, dt.dtype) * d[..., :, None] * d[..., None, :]
    eye3 = jnp.eye(3, dtype=dt.dtype)
    kron = jax.vmap(lambda a: jnp.kron(a, eye3))
    return kron(A), kron(Qs)


def _symmetric(C):
    return 0.5 * (C + jnp.swapaxes(C, -1, -2))


def _inv2(S):
    """Inverse of a 2x2 matrix in closed form."""
    det = S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0]
    return jnp.array([[S[1, 1], -S[0, 1]], [-S[1, 0], S[0, 0]]], S.dtype) / det


def _project(P, X):
    """Pixels ``pi(P X)`` (.., 2) of positions X (.., 3) for one camera P (3, 4)."""
    h = X @ P[:, :3].T + P[:, 3]
    tiny = jnp.finfo(P.dtype).eps
    z = jnp.where(jnp.abs(h[..., 2]) > tiny, h[..., 2], tiny)
    return h[..., :2] / z[..., None]


def _moments_cubature(P, mean, cov):
    """Predicted pixel mean (2,), covariance (2, 2) and state-pixel cross-covariance (s, 2)
    by the spherical-radial cubature rule."""
    s = mean.shape[0]
    jitter = jnp.finfo(cov.dtype).eps * (jnp.trace(cov) / s + jnp.finfo(cov.dtype).tiny)
    L = cholesky_small(cov + jitter * jnp.eye(s, dtype=cov.dtype))
    offsets = jnp.sqrt(float(s)) * jnp.concatenate([L.T, -L.T])  # (2 s, s)
    Z = _project(P, mean[:3] + offsets[:, :3])
    z = jnp.mean(Z, axis=0)
    dZ = Z - z
    return z, dZ.T @ dZ / (2 * s), offsets.T @ dZ / (2 * s)


def _moments_extended(P, mean, cov):
    """As :func:`_moments_cubature`, linearised at the mean."""
    e, J, _ = linearise(P[None], jnp.zeros((1, 2), P.dtype), mean[None, :3])
    H = jnp.zeros((2, mean.shape[0]), P.dtype).at[:, :3].set(J[0])
    C = cov @ H.T
    return e[0], H @ C, C


def kalman_smoother(moments, frames, z, w, A, Q, m0, C0, sigma2, gate, smoother):
    """Kalman filter (and RTS smoother) of a linear-Gaussian motion and a 2-D measurement.

    ``moments(frame, mean, cov)`` returns the predicted measurement mean (2,), covariance
    (2, 2) and state-measurement cross-covariance (s, 2) for one frame's data ``frame``
    (any pytree with a leading axis F). Step ``i`` predicts frame ``i`` with ``A[i], Q[i]``
    (identity and zero for the first frame, whose prior is ``m0, C0``) and updates it with
    ``z[i]`` of noise ``sigma2 / w[i]`` unless ``w[i] = 0`` or the squared Mahalanobis
    distance of the innovation exceeds ``gate``. Returns means (F, s), covariances
    (F, s, s) and which frames were used (F,).
    """
    eye2 = jnp.eye(2, dtype=m0.dtype)

    def step(carry, inputs):
        m, C = carry
        frame, zi, wi, Ai, Qi = inputs
        m_pred = Ai @ m
        C_pred = _symmetric(Ai @ C @ Ai.T + Qi)
        zhat, S, Cxz = moments(frame, m_pred, C_pred)
        S = _symmetric(S) + (sigma2 / jnp.where(wi > 0, wi, 1.0)) * eye2
        S_inv = _inv2(S)
        K = Cxz @ S_inv
        r = zi - zhat
        use = (wi > 0) & (r @ S_inv @ r <= gate)
        m_new = jnp.where(use, m_pred + K @ r, m_pred)
        C_new = jnp.where(use, _symmetric(C_pred - K @ S @ K.T), C_pred)
        return (m_new, C_new), (m_new, C_new, m_pred, C_pred, use)

    _, (mf, Cf, mp, Cp, used) = jax.lax.scan(step, (m0, C0), (frames, z, w, A, Q))
    if not smoother:
        return mf, Cf, used

    def back(carry, inputs):
        m_next, C_next = carry
        m, C, m_pred_next, C_pred_next, A_next = inputs
        # C A^T C_pred^-1, without LAPACK: under vmap over points a LAPACK solve becomes a
        # batched call (deadlocked on 2 cores with jaxlib 0.10, see jaxtraj._spd)
        G = solve_spd_small(C_pred_next, A_next @ C).T
        m_s = m + G @ (m_next - m_pred_next)
        C_s = _symmetric(C + G @ (C_next - C_pred_next) @ G.T)
        return (m_s, C_s), (m_s, C_s)

    _, (ms, Cs) = jax.lax.scan(
        back, (mf[-1], Cf[-1]), (mf[:-1], Cf[:-1], mp[1:], Cp[1:], A[1:]), reverse=True
    )
    return jnp.concatenate([ms, mf[-1:]]), jnp.concatenate([Cs, Cf[-1:]]), used


def _run(
    P,
    uv,
    times,
    weights,
    *,
    order,
    process_psd,
    pixel_sigma,
    start_mean,
    start_cov,
    rule,
    gate,
    smoother,
):
    """The traced body of :func:`filter_trajectory` (inputs already validated)."""
    dtype = P.dtype
    F = P.shape[0]
    s = 3 * order
    w = jnp.ones(F, dtype) if weights is None else weights
    observed = w > 0
    finite_in = jnp.all(jnp.isfinite(uv) | ~observed[:, None]) & jnp.all(jnp.isfinite(P))
    uv = jnp.where(observed[:, None], uv, 0.0)
    Pn = normalise_cameras(P)
    A, Q = _process(jnp.diff(times), order, process_psd)
    A = jnp.concatenate([jnp.eye(s, dtype=dtype)[None], A])
    Q = jnp.concatenate([jnp.zeros((1, s, s), dtype), Q])
    moments = _moments_cubature if rule == "cubature" else _moments_extended
    m, C, used = kalman_smoother(
        moments, Pn, uv, w, A, Q, start_mean.reshape(s), start_cov, pixel_sigma**2, gate, smoother
    )

    states = m.reshape(F, order, 3)
    e = linearise(Pn, uv, states[:, 0])[0]
    n_used = jnp.sum(used)
    rms = jnp.sqrt(jnp.sum(jnp.where(used, jnp.sum(e * e, axis=1), 0.0)) / jnp.maximum(n_used, 1))
    ok = finite_in & jnp.all(jnp.isfinite(states)) & jnp.all(jnp.isfinite(C))
    return Smoothed(
        states=states,
        state_cov=C,
        times=times,
        process_psd=jnp.asarray(process_psd, dtype),
        pixel_sigma=jnp.asarray(pixel_sigma, dtype),
        rms_px=rms,
        edf=jnp.asarray(jnp.nan, dtype),
        num_observed=n_used.astype(jnp.int32),
        status=jnp.where(ok, Status.OK, Status.NONFINITE).astype(jnp.int32),
    )


_run_jit = eqx.filter_jit(_run)


def _validate_options(order, process_psd, pixel_sigma, rule, gate) -> None:
    if order not in (1, 2, 3):
        raise ValueError(f"order: expected 1, 2 or 3, got {order!r}")
    if process_psd is None:
        raise ValueError(
            "process_psd: a filter needs the noise density q (choose it with "
            "jaxtraj.estimators.select_process_psd or tune it on recorded data)"
        )
    check_positive("process_psd", process_psd, "a noise density")
    check_positive("pixel_sigma", pixel_sigma, "a pixel standard deviation")
    if rule not in RULES:
        raise ValueError(f"rule: expected one of {RULES}, got {rule!r}")
    if gate is not None:
        check_positive("gate", gate, "a squared Mahalanobis distance (e.g. 16)")


def filter_trajectory(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "F 2"],
    times: Float[ArrayLike, " F"],
    weights: Float[ArrayLike, " F"] | None = None,
    *,
    start_mean: Float[ArrayLike, "order 3"],
    start_cov: Float[ArrayLike, "s s"],
    process_psd: float,
    pixel_sigma: float = 1.0,
    order: int = 2,
    rule: str = "cubature",
    gate: float | None = None,
    smoother: bool = True,
) -> Smoothed:
    """Track one point from a known start with a Kalman filter (and RTS smoother).

    jit-, vmap- and grad-compatible (see :func:`filter_points` for a batched driver).

    Args:
        P, uv, times, weights: cameras, pixels [px], frame times [s] and weights (0: a
            missing detection), as in :func:`.smooth_trajectory`.
        start_mean: (order, 3) state at ``times[0]`` before its pixel is used: position
            [m], velocity [m/s], ...
        start_cov: (3 order, 3 order) its covariance, in the order of ``Smoothed.states``
            flattened (position first).
        process_psd: noise density ``q`` of the ``order``-th derivative
            [m^2 / s^(2 order - 1)] (as in :func:`.smooth_trajectory`).
        pixel_sigma: pixel noise standard deviation [px].
        order: 1, 2 (white-noise acceleration, the default) or 3.
        rule: ``"cubature"`` (sigma points) or ``"extended"`` (first-order) update.
        gate: skip frames whose innovation's squared Mahalanobis distance exceeds this
            (2 degrees of freedom: 13.8 rejects 0.1 % of inliers); ``None``: no gate.
        smoother: ``True``: RTS-smoothed states (every frame uses all frames);
            ``False``: filtered states (each frame uses the frames up to it, for on-line
            use). The last state is the same either way.

    Returns:
        A :class:`.Smoothed` (``edf`` is NaN; ``num_observed`` counts the frames used;
        :func:`.predict` extrapolates its last state).
    """
    validate_track(P, uv, times, weights)
    _validate_options(order, process_psd, pixel_sigma, rule, gate)
    _validate_start(start_mean, start_cov, order)
    P, uv, times, weights = as_float(P, uv, times, weights)
    if weights is None:  # one compiled program with and without weights
        weights = jnp.ones(uv.shape[0], P.dtype)
    opts = _traced_options(
        P.dtype, order, process_psd, pixel_sigma, start_cov, rule, gate, smoother
    )
    return _run_jit(P, uv, times, weights, start_mean=jnp.asarray(start_mean, P.dtype), **opts)


def _traced_options(dtype, order, process_psd, pixel_sigma, start_cov, rule, gate, smoother):
    """Keyword arguments of :func:`_run`: numbers as arrays, so that a new value does not
    compile again; ``order``, ``rule`` and ``smoother`` stay static."""
    return dict(
        order=order,
        process_psd=jnp.asarray(process_psd, dtype),
        pixel_sigma=jnp.asarray(pixel_sigma, dtype),
        start_cov=jnp.asarray(start_cov, dtype),
        rule=rule,
        gate=jnp.asarray(jnp.inf if gate is None else gate, dtype),
        smoother=smoother,
    )


def filter_points(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "N F 2"],
    times: Float[ArrayLike, " F"],
    weights: Float[ArrayLike, "N F"] | None = None,
    *,
    start_mean: Float[ArrayLike, "N order 3"],
    start_cov: Float[ArrayLike, "s s"],
    process_psd: float,
    **kwargs,
) -> Smoothed:
    """:func:`filter_trajectory` for N points seen by the same cameras (jit + vmap).

    ``start_mean`` is (N, order, 3), one per point, or (order, 3) for all; ``start_cov``,
    ``process_psd`` and the keyword arguments are shared. Fields gain a leading axis N.
    """
    order = kwargs.get("order", 2)
    unknown = set(kwargs) - {"order", "pixel_sigma", "rule", "gate", "smoother"}
    if unknown:
        raise TypeError(f"filter_points: unexpected keyword argument(s) {sorted(unknown)}")
    _validate_batch(P, uv, times, weights)
    N = np.shape(uv)[0]
    if np.ndim(start_mean) == 3:
        check_shape("start_mean", start_mean, (N, order, 3), "(N, order, 3), one per point")
        _validate_start(start_mean[0], start_cov, order)
    else:
        _validate_start(start_mean, start_cov, order)
    pixel_sigma, rule, gate = (
        kwargs.get("pixel_sigma", 1.0),
        kwargs.get("rule", "cubature"),
        kwargs.get("gate"),
    )
    _validate_options(order, process_psd, pixel_sigma, rule, gate)
    P, uv, times, weights = as_float(P, uv, times, weights)
    dtype = P.dtype
    smoother = kwargs.get("smoother", True)
    opts = _traced_options(dtype, order, process_psd, pixel_sigma, start_cov, rule, gate, smoother)
    w = jnp.ones(uv.shape[:2], dtype) if weights is None else weights
    mean = jnp.broadcast_to(jnp.asarray(start_mean, dtype), (N, order, 3))
    return _filter_points(P, uv, times, w, mean, opts)


@eqx.filter_jit
def _filter_points(P, uv, times, weights, start_mean, opts):
    one = lambda u, w, m: _run(P, u, times, w, start_mean=m, **opts)  # noqa: E731
    return jax.vmap(one)(uv, weights, start_mean)

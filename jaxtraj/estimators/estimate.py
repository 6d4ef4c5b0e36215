"""One call for point trajectories from a moving camera: :func:`estimate_points`.

It fits the smoothness prior (:mod:`.smoothness`) of every order in ``orders`` to each
track, with the noise density chosen per track by the marginal likelihood, and then asks
two questions of each fit.

**Is the depth determined by the data?** The pixels fix two of the three coordinates of
each frame; the third, the depth along the viewing ray, comes from the prior alone. The
trajectories ``c + s (x - c)`` (``c`` the camera centres) project to the same pixels for
every ``s``, and when the camera moves slowly or follows the point they are all about as
smooth as ``x``: the prior then decides ``s``, and the smoother's posterior, which trusts
the prior, is 10-1000x overconfident along that family (measured on motion capture under
slow orbits). Which member a prior of order ``m`` picks is governed by the roughness
ratio::

    kappa_m^2 = R_m(x_hat) / R_m(x_hat - c),    R_m(y) = sum_i h_i |D^m y_i|^2

(``D^m``: ``m``-th divided differences in units of the mean frame step, ``h_i`` the span
of each difference): at the estimate the prior is stationary along the family, so its
bias in ``s`` is the alignment of the point's own roughness with the family's, bounded by
``kappa_m`` (Cauchy-Schwarz). ``kappa`` is therefore reported as the relative depth
uncertainty: the error along the rays is up to about ``kappa |x_hat - c|``. It is large
(0.3 to 5) when the camera's motion is not rougher than the point's in the prior's
derivative (slow orbits, a camera that follows the point) and 0.001-0.05 for orbits of
20 deg/frame or more and random cameras. The covariance returned adds
an along-ray term to each frame's posterior covariance (below), and a track
whose smallest ``kappa`` exceeds ``max_depth_uncertainty`` is
:attr:`jaxtraj.Status.DEGENERATE`.

**Which motion model?** Among the orders whose depth is determined
(``kappa <= max_depth_uncertainty``), the one with the largest marginal likelihood of the
pixels, computed at each order's own noise density with the same proper prior on the
start (position within 1 m of the estimate's start, velocity 0 +- 1 m/s, acceleration
0 +- 10 m/s^2) and with every normalising term of the prior, so that it compares across
orders (the diffuse restricted likelihood that chooses the noise density drops terms
that differ between orders). The marginal likelihood judges how well each motion model
explains the pixel tracks, which are blind along the rays; that is why ``kappa``, not
the likelihood, decides whether an order is admissible. On data drawn from an order-1,
2 or 3 prior it picks the generating order (95-100 % of tracks, random and orbiting
cameras); on motion capture it picks order 2 for orbits of 20-90 deg/frame and random
cameras, order 3 on the simulated cell's fast and random cameras. When no order has its
depth determined, the order with the smallest ``kappa`` is returned, flagged: the prior
whose derivative the camera dominates most (order 1, penalised velocity, for slow orbits,
where the camera moves faster than the point but accelerates less).

**The DCT basis as a candidate.** The paper's model, ``x = Theta beta`` with ``k`` DCT
vectors (``dct_ks``, default 4, 6, 9, 12), competes on the same scale: its marginal
likelihood, with the constant coefficient under the smoother's start prior and the others
``N(0, s^2)`` (``s`` by the marginal likelihood), is computed on the same linearised pixels
with the same normalising terms (:mod:`._dct_candidate`). A DCT fit is admissible only
where some smoothness order is (``kappa``, the model-free part of the question, decides
whether the depth is determined). On tracks inside the span of 6 DCT vectors (random
cameras, 4 scenes of 8 tracks) it is chosen for every track, with 0.31-0.41x the
smoothers' error; on the simulated cell and motion capture the smoothers won (see the
README for the cells measured). Its covariance keeps the smallest admissible ``kappa``'s
along-ray bound, which is conservative for tracks inside the span (mean squared error /
trace 0.07-0.17 there; of the DCT posterior alone: 0.86-1.24).

The reported covariance treats ``kappa |x_hat - c|`` as a two-standard-deviation bound of
the along-ray error: the standard deviation along each frame's ray is raised to at least
``kappa |x_hat - c| / 2``. On data drawn from the prior (random cameras) the posterior
is then left as it is and matches Monte-Carlo errors (mean squared error / trace 0.96
for order 1, 1.09 for order 2; 4 scenes of 8 tracks); the noise density is chosen on
half decades for that (evaluated every other decade, then on decades and half decades
about the minimum: the parabola through decades alone was 2x off in q for order 1 on
data drawn from the prior, which made the posterior 2x too wide; half decades: 8 %).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._batching import map_points, on_cores, points_per_step
from .._checks import is_concrete
from ..depth import camera_centres, depth_uncertainty, with_ray_bound
from ..solve import Status
from ._common import as_float, check_loss, check_positive, normalise_cameras
from ._dct_candidate import data_blocks, dct_fit
from .smoothness import (
    _neg2_log_evidence,
    _q_unit,
    _smooth,
    _transition,
    _validate_batch,
    default_psd_grid,
)

__all__ = ["PointEstimate", "depth_uncertainty", "estimate_points"]

ORDERS = (1, 2, 3)
MIN_OBSERVED = 3  # frames with a detection per track (raised outside jit)
DCT_KS = (4, 6, 9, 12)  # candidate DCT sizes (module notes)
START_SD = (1.0, 1.0, 10.0)  # start prior of the evidence: m, m/s, m/s^2 (module notes)
MAP_BATCH = 8  # points per group of the batched driver's loop on a CPU (lax.map)
MAP_BATCH_ACCELERATOR = 0  # the same on an accelerator; 0: all at once (jaxtraj._batching)


class PointEstimate(eqx.Module):
    """Result of :func:`estimate_points` for N points seen by the same F cameras.

    Attributes:
        points: (N, F, 3) positions at the frame times [m].
        cov: (N, F, 3, 3) covariance of each position [m^2]: the smoother's posterior
            with the standard deviation along each ray raised to at least
            ``kappa |x - c| / 2`` (see the module notes).
        posterior_cov: (N, F, 3, 3) the chosen model's posterior alone [m^2].
        order: (N,) order of the smoothness prior chosen per point; 0 where a DCT basis
            was chosen.
        dct_k: (N,) size of the DCT basis chosen per point; 0 where a smoothness prior was.
        depth_uncertainty: (N,) ``kappa`` of the chosen order (where a DCT basis was
            chosen: the smallest ``kappa`` of the admissible orders): the along-ray error
            relative to the distance to the camera.
        kappas: (N, len(orders)) ``kappa`` of every candidate order.
        predicted_rmse: (N, len(orders)) predicted RMS 3D error of every candidate [m].
        process_psd: (N,) noise density of the chosen order [m^2 / s^(2 order - 1)];
            NaN where a DCT basis was chosen.
        rms_px: (N,) reprojection RMS of the chosen fit [px].
        num_observed: (N,) frames with non-zero weight.
        status: (N,) :class:`jaxtraj.Status` codes (int32); ``DEGENERATE`` where the depth
            is not determined by the data.
    """

    points: Float[Array, "N F 3"]
    cov: Float[Array, "N F 3 3"]
    posterior_cov: Float[Array, "N F 3 3"]
    order: Int[Array, " N"]
    dct_k: Int[Array, " N"]
    depth_uncertainty: Float[Array, " N"]
    kappas: Float[Array, "N M"]
    predicted_rmse: Float[Array, "N M"]
    process_psd: Float[Array, " N"]
    rms_px: Float[Array, " N"]
    num_observed: Int[Array, " N"]
    status: Int[Array, " N"]

    @property
    def std(self) -> Float[Array, "N F"]:
        """(N, F) RMS standard deviation of each position, ``sqrt(trace(cov))`` [m]."""
        return jnp.sqrt(jnp.trace(self.cov, axis1=-2, axis2=-1))


def _evidence(P, uv, times, w, sm, order):
    """-2 log marginal likelihood of the linearised model of ``order`` at its chosen
    noise density, with a proper start prior (sd START_SD about the estimated start
    position, zero velocity and acceleration), so that it compares across orders."""
    dtype = P.dtype
    F = P.shape[0]
    m = order
    tau = (times[-1] - times[0]) / (F - 1)
    dt = jnp.diff(times) / tau
    A, Qinv = _transition(dt, m)
    q = sm.process_psd * tau ** (2 * m - 1)
    unit = (tau ** -np.repeat(np.arange(m), 3).astype(float)).astype(dtype)
    x = sm.states.reshape(F, 3 * m) / unit
    uv0 = jnp.where(w[:, None] > 0, uv, 0.0)
    H, g, c = data_blocks(normalise_cameras(P), uv0, w, x[:, :3], sm.pixel_sigma**2)
    var0 = jnp.asarray(np.repeat(np.square(START_SD[:m]), 3), dtype) / unit**2
    m0 = jnp.zeros(3 * m, dtype).at[:3].set(x[0, :3])
    L0 = jnp.diag(1.0 / var0)
    Qbar1, _ = _q_unit(m)
    j = np.arange(m)
    logdet_Q = 3 * (
        (F - 1) * np.log(np.linalg.det(Qbar1)) + 2 * jnp.sum((m - 0.5 - j) * jnp.log(dt)[:, None])
    )
    return (
        _neg2_log_evidence(H, g, c, A, Qinv, q, m, (L0, m0))
        + logdet_Q
        + jnp.sum(jnp.log(var0))
        + m0 @ L0 @ m0
    )


def _one_order(P, C, uv, times, w, order, opts):
    sm = _smooth(
        P,
        uv,
        times,
        w,
        order=order,
        process_psd=None,
        # every other decade, then decades and half decades about the minimum (module notes)
        grid=jnp.asarray(default_psd_grid(order)[::2], P.dtype),
        refine_grid=2,
        covariance=True,
        max_depth_uncertainty=None,  # judged here, across the orders
        **opts,
    )
    x = sm.points
    kappa = depth_uncertainty(x, C, times, order)
    d = x - C
    cov = with_ray_bound(sm.cov, d, 0.5 * kappa)
    mse = jnp.mean(jnp.trace(cov, axis1=-2, axis2=-1))
    return sm, kappa, cov, jnp.sqrt(mse), _evidence(P, uv, times, w, sm, order)


def _estimate_one(P, C, uv, times, w, orders, dct_ks, tau, opts):
    fits = [_one_order(P, C, uv, times, w, m, opts) for m in orders]
    kappa = jnp.stack([f[1] for f in fits])
    rmse = jnp.stack([f[3] for f in fits])
    evidence = jnp.stack([f[4] for f in fits])
    evidence = jnp.where(jnp.isnan(evidence), jnp.inf, evidence)
    ok = jnp.stack([f[0].status == Status.OK for f in fits])
    admissible = ok & (kappa <= tau)
    determined = jnp.any(admissible)
    kappa_det = jnp.min(jnp.where(admissible, kappa, jnp.inf))
    # candidates: the smoothness orders, then the DCT sizes
    score = [jnp.where(admissible, evidence, jnp.inf)]
    points = [f[0].points for f in fits]
    cov = [f[2] for f in fits]
    posterior = [f[0].cov for f in fits]
    order = list(orders)
    size = [0] * len(orders)
    depth = [f[1] for f in fits]
    psd = [f[0].process_psd for f in fits]
    rms = [f[0].rms_px for f in fits]
    status = [f[0].status for f in fits]
    if dct_ks:
        x_lin = jnp.stack(points)[jnp.argmin(jnp.where(ok, evidence, jnp.inf))]
        uv0 = jnp.where(w[:, None] > 0, uv, 0.0)
        sigma2 = opts["pixel_sigma"] ** 2
        Pn = normalise_cameras(P)
        blocks = data_blocks(Pn, uv0, w, x_lin, sigma2)
        for k in dct_ks:
            neg2, x, c, r = dct_fit(Pn, uv0, w, times, sigma2, x_lin, blocks, k, START_SD[0])
            ok_k = determined & jnp.isfinite(neg2) & jnp.all(jnp.isfinite(x))
            score.append(jnp.where(ok_k, neg2, jnp.inf)[None])
            points.append(x)
            cov.append(with_ray_bound(c, x - C, 0.5 * kappa_det))
            posterior.append(c)
            order.append(0)
            size.append(k)
            depth.append(kappa_det)
            psd.append(jnp.full((), jnp.nan, P.dtype))
            rms.append(r)
            status.append(jnp.asarray(Status.OK, jnp.int32))
    score = jnp.concatenate(score)
    fallback = jnp.argmin(jnp.where(ok & jnp.isfinite(kappa), kappa, jnp.inf))
    pick = jnp.where(determined, jnp.argmin(score), fallback)

    def take(values):
        return jnp.stack(values)[pick]

    chosen_status = take(status)
    chosen_status = jnp.where(
        (chosen_status == Status.OK) & ~determined, Status.DEGENERATE, chosen_status
    ).astype(jnp.int32)
    return PointEstimate(
        points=take(points),
        cov=take(cov),
        posterior_cov=take(posterior),
        order=jnp.asarray(order, jnp.int32)[pick],
        dct_k=jnp.asarray(size, jnp.int32)[pick],
        depth_uncertainty=take(depth),
        kappas=kappa,
        predicted_rmse=rmse,
        process_psd=take(psd),
        rms_px=take(rms),
        num_observed=fits[0][0].num_observed,
        status=chosen_status,
    )


@eqx.filter_jit
def _estimate(P, uv, times, weights, orders, dct_ks, tau, opts, per_step):
    C = camera_centres(P)

    def one(args):
        return _estimate_one(P, C, args[0], times, args[1], orders, dct_ks, tau, opts)

    # on a CPU, groups of MAP_BATCH points (lax.map): one vmap over thousands of points
    # makes every step of the smoothers stream all points' arrays through memory
    return map_points(one, (uv, weights), per_step)


def estimate_points(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "N F 2"],
    times: Float[ArrayLike, " F"],
    weights: Float[ArrayLike, "N F"] | None = None,
    *,
    pixel_sigma: float = 1.0,
    orders: tuple[int, ...] = (1, 2),
    dct_ks: tuple[int, ...] | None = None,
    max_depth_uncertainty: float = 0.08,
    iterations: int = 3,
    loss: str = "l2",
    loss_scale: float = 2.0,
    depth_guess: float = 1.0,
) -> PointEstimate:
    """Trajectories of N points seen by the same cameras, with the model chosen per point,
    an uncertainty that includes the error along the viewing rays, and a status that
    flags what the data cannot determine (see the module notes for the method).

    jit-, vmap- and grad-compatible (the model choice is a selection, so gradients flow
    through the chosen fit). Called eagerly on a CPU with several cores, the points are
    split into one chunk per core, each estimated from its own thread
    (:func:`jaxtraj._batching.on_cores`; the same result per point).

    Args:
        P: (F, 3, 4) projection matrices of undistorted cameras.
        uv: (N, F, 2) pixels [px]; entries with weight 0 are ignored and may be NaN.
        times: (F,) strictly increasing frame times [s].
        weights: (N, F) non-negative weights (relative inverse pixel variances); 0 marks
            a missing detection. Default: all 1.
        pixel_sigma: pixel noise standard deviation [px] (scales the covariances).
        orders: candidate orders of the smoothness prior (a subset of 1, 2, 3). Order 3
            (white-noise jerk) costs about 3x orders 1 and 2 together and helped only on
            the simulated cell's fast cameras (2.7 against 3.7 mm), so it is opt-in.
        dct_ks: candidate sizes of a DCT basis (:mod:`._dct_candidate`); ``()``: none;
            default: those of ``DCT_KS`` (4, 6, 9, 12) up to ``F // 2``. The DCT fits are
            least squares on the pixels whatever ``loss`` is.
        max_depth_uncertainty: largest ``kappa`` (along-ray error relative to the
            distance to the camera) with which a track is reported ``Status.OK``.
        iterations, loss, loss_scale, depth_guess: as in
            :func:`jaxtraj.estimators.smooth_trajectory`.

    Returns:
        A :class:`PointEstimate`.
    """
    _validate_batch(P, uv, times, weights)
    orders = tuple(orders)
    if not orders or len(set(orders)) != len(orders) or any(m not in ORDERS for m in orders):
        raise ValueError(f"orders: expected distinct values from {ORDERS}, got {orders!r}")
    if not isinstance(iterations, int) or iterations < 0:
        raise ValueError(f"iterations: expected a non-negative int, got {iterations!r}")
    F = np.shape(P)[0]
    dct_ks = tuple(k for k in DCT_KS if k <= F // 2) if dct_ks is None else tuple(dct_ks)
    if len(set(dct_ks)) != len(dct_ks) or any(
        not isinstance(k, (int, np.integer)) or not 1 <= k <= F // 2 for k in dct_ks
    ):
        raise ValueError(f"dct_ks: expected distinct ints in 1..{F // 2} (F // 2), got {dct_ks!r}")
    dct_ks = tuple(int(k) for k in dct_ks)
    check_loss(loss, loss_scale)
    check_positive("pixel_sigma", pixel_sigma, "a pixel standard deviation")
    check_positive("max_depth_uncertainty", max_depth_uncertainty, "a relative depth error")
    check_positive("depth_guess", depth_guess, "a depth in metres")
    if np.shape(P)[0] < 2 * max(orders) + 2:
        raise ValueError(
            f"P: expected at least {2 * max(orders) + 2} frames for orders {orders}, "
            f"got {np.shape(P)[0]}"
        )
    if weights is not None and is_concrete(weights):
        n_obs = np.sum(np.asarray(weights) > 0, axis=1)
        few = np.flatnonzero(n_obs < MIN_OBSERVED)
        if few.size:
            raise ValueError(
                f"weights: tracks {few[:8].tolist()} have fewer than {MIN_OBSERVED} observed "
                f"frames (weight > 0); {n_obs[few[:8]].tolist()} observed frames"
            )
    P, uv, times, weights = as_float(P, uv, times, weights)
    dtype = P.dtype
    w = jnp.ones(uv.shape[:2], dtype) if weights is None else weights
    opts = dict(
        pixel_sigma=jnp.asarray(pixel_sigma, dtype),
        iterations=iterations,
        loss=loss,
        loss_scale=jnp.asarray(loss_scale, dtype),
        depth_guess=jnp.asarray(depth_guess, dtype),
        criterion="ml",
    )
    tau = jnp.asarray(max_depth_uncertainty, dtype)
    per_step = points_per_step(MAP_BATCH, MAP_BATCH_ACCELERATOR, uv)
    return on_cores(  # one chunk of points per CPU core, each from a thread (eager calls)
        lambda a: _estimate(P, a[0], times, a[1], orders, dct_ks, tau, opts, per_step),
        (uv, w),
        (P, times, opts),
    )

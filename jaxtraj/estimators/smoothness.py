"""Smoothness-prior trajectory estimation (a "trajectory filter" without a basis size k).

The unknowns are the states ``s_i`` of the point at every frame time: position, and for
``order >= 2`` velocity (and acceleration). The prior is the continuous-time integrated
Wiener process of the given order, i.e. white noise of power spectral density ``q`` on
the ``order``-th derivative (order 2: white-noise acceleration, the constant-velocity
model). Exactly discretised at the real, possibly irregular, frame times::

    s_{i+1} = A(dt_i) s_i + n_i,   n_i ~ N(0, q Qbar(dt_i)),   A_jl = dt^(l-j) / (l-j)!

so that the negative log prior is the time-step-weighted ``order``-th difference
penalty ``||G x||^2`` of Valmadre & Lucey's trajectory filters (exact for order 1; for
order 2 its maximum a posteriori estimate is the cubic smoothing spline). The data term
is the reprojection error ``sum_i w_i ||pi(P_i p_i) - uv_i||^2 / sigma^2``. We minimise::

    sum_i w_i rho(||pi(P_i p_i) - uv_i||^2) / sigma^2
        + sum_i (s_{i+1} - A_i s_i)^T (q Qbar_i)^-1 (s_{i+1} - A_i s_i)

starting (no initial guess) from the depth-weighted linear ray constraints of paper eq. 4,
reweighted once by the recovered depths, then Gauss-Newton steps (IRLS for a robust
``rho``); when ``q`` is chosen, the linear solution is computed at a mid-grid ``q`` for the
choice and again at the chosen one, so that the result is the fixed-``q`` result. Every
step is one block-tridiagonal solve of size (F, 3 order) in O(F) (see :mod:`._blocktri`);
the posterior covariances are the smoother's (selected inversion).
The noise density ``q`` is in physical units (m^2 / s^(2 order - 1)), so a value tuned on
one scene transfers to others; with ``process_psd=None`` it is chosen per trajectory over
a log grid (one batched solve) by the marginal likelihood (``criterion="ml"``, the
restricted likelihood of the diffuse prior, from the block Cholesky log-determinant) or by
Mallows' unbiased risk estimate (``"ubre"``), both with the known pixel noise.
Generalised cross-validation is *not* offered: the pixels constrain only two of three
coordinates per frame, so any large ``q`` interpolates the data exactly and GCV's
``RSS / (n - edf)^2`` runs to 0/0 there (measured: it picked the largest ``q`` on every
scene, 10-100x the error of the marginal-likelihood choice).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._checks import check_shape, check_tracks, is_concrete
from .._linalg import matmul_small, solve_spd_small
from ..depth import camera_centres, depth_uncertainty
from ..solve import Status
from . import _blocktri as bt
from ._common import (
    algebraic_blocks,
    as_float,
    check_loss,
    check_positive,
    gauss_newton_blocks,
    linearise,
    normalise_cameras,
    rho,
    rho_weight,
    validate_track,
)

__all__ = [
    "Smoothed",
    "default_psd_grid",
    "predict",
    "select_process_psd",
    "smooth_points",
    "smooth_trajectory",
]


class Smoothed(eqx.Module):
    """Result of :func:`smooth_trajectory` (one trajectory; leading axes come from vmap).

    Attributes:
        states: (F, order, 3) position [m], velocity [m/s], acceleration [m/s^2] per frame.
        state_cov: (F, 3 order, 3 order) posterior covariance of each state, flattened
            as (order, 3), for pixel noise ``pixel_sigma`` and the prior.
        times: (F,) frame times [s].
        process_psd: the noise density ``q`` used [m^2 / s^(2 order - 1)].
        pixel_sigma: the pixel noise standard deviation assumed [px].
        rms_px: reprojection RMS over the observed frames [px].
        edf: effective degrees of freedom of the fit (trace of the hat matrix).
        num_observed: number of frames with non-zero weight.
        status: a :class:`jaxtraj.Status` code (int32).
    """

    states: Float[Array, "F m 3"]
    state_cov: Float[Array, "F s s"]
    times: Float[Array, " F"]
    process_psd: Float[Array, ""]
    pixel_sigma: Float[Array, ""]
    rms_px: Float[Array, ""]
    edf: Float[Array, ""]
    num_observed: Int[Array, ""]
    status: Int[Array, ""]

    @property
    def points(self) -> Float[Array, "F 3"]:
        """(F, 3) positions at the frame times [m]."""
        return self.states[..., 0, :]

    @property
    def velocities(self) -> Float[Array, "F 3"]:
        """(F, 3) velocities [m/s] (order >= 2 only)."""
        if self.states.shape[-2] < 2:
            raise ValueError("velocities: an order-1 (random-walk) fit has no velocity state")
        return self.states[..., 1, :]

    @property
    def cov(self) -> Float[Array, "F 3 3"]:
        """(F, 3, 3) posterior covariance of the positions [m^2]."""
        return self.state_cov[..., :3, :3]


def default_psd_grid(order: int = 2) -> np.ndarray:
    """Default log grid of noise densities: 10^-4 .. 10^5 in decades (order 2).

    In m^2/s^3 for order 2; shifted by two decades per order for order 1 and 3.
    """
    return 10.0 ** np.arange(-4.0, 5.01, 1.0) * 10.0 ** (2 * (order - 2))


def _q_unit(order: int) -> np.ndarray:
    """``Qbar(1)`` and its inverse for unit time step and unit density."""
    m = order
    Q = np.array(
        [
            [
                1.0 / ((2 * m - 1 - j - l) * math.factorial(m - 1 - j) * math.factorial(m - 1 - l))
                for l in range(m)
            ]
            for j in range(m)
        ]
    )
    return Q, np.linalg.inv(Q)


def _transition(dt, order: int):
    """``A(dt)`` (.., m, m) and ``Qbar(dt)^-1`` (.., m, m) for unit density."""
    m = order
    j = np.arange(m)
    powers = j[None, :] - j[:, None]
    fact = np.array([[math.factorial(max(p, 0)) for p in row] for row in powers])
    dtp = dt[..., None, None] ** np.maximum(powers, 0)
    A = jnp.where(powers >= 0, dtp / fact, 0.0)
    _, Qinv1 = _q_unit(order)
    d = _q_scale(dt, order)
    Qinv = jnp.asarray(Qinv1, dt.dtype) / (d[..., :, None] * d[..., None, :])
    return A, Qinv


def _q_scale(dt, order: int):
    """``d`` (.., m) with ``Qbar(dt) = diag(d) Qbar(1) diag(d)``: ``dt^(m - 1/2 - j)``, in
    the dtype of ``dt`` (float32 times stay float32 with x64 enabled)."""
    j = np.arange(order)
    return dt[..., None] ** jnp.asarray(order - 0.5 - j, dt.dtype)


def _assemble(H, g, A, Qinv, inv_q, order, start=None):
    """Block-tridiagonal normal equations of data blocks (H, g) plus the prior (and an
    optional Gaussian prior ``start = (information, mean)`` on the first state)."""
    s = 3 * order
    eye3 = jnp.eye(3, dtype=H.dtype)

    def kron3(a):  # (n, m, m) -> (n, 3m, 3m): each block a (x) I_3, as a broadcast
        n, m = a.shape[0], a.shape[-1]
        return (a[:, :, None, :, None] * eye3[None, None, :, None, :]).reshape(n, 3 * m, 3 * m)

    # the prior's blocks per coordinate (order x order), then the same for x, y and z:
    # products of order x order blocks instead of (3 order)^2 ones
    Wq = Qinv * inv_q
    WA = matmul_small(Wq, A)  # broadcast-and-sums (vmap), see matmul_small
    zero = jnp.zeros((1, order, order), H.dtype)
    prior = jnp.concatenate([matmul_small(jnp.swapaxes(A, 1, 2), WA), zero]) + jnp.concatenate(
        [zero, Wq]
    )
    D = kron3(prior) + jnp.pad(H, ((0, 0), (0, s - 3), (0, s - 3)))
    E = -kron3(WA)
    b = jnp.pad(g, ((0, 0), (0, s - 3)))
    if start is not None:
        L0, m0 = start
        D = D.at[0].add(L0)
        b = b.at[0].add(L0 @ m0)
    scale = jnp.mean(jnp.trace(D, axis1=1, axis2=2)) / s
    D = D + (jnp.finfo(H.dtype).eps * scale) * jnp.eye(s, dtype=H.dtype)
    return D, E, b


def _refine_window(wq, wc, size):
    """Index of the best of the first ``size`` points of a window (kept off its ends) and
    the geometric midpoints on either side of it."""
    i = jnp.argmin(jnp.where(jnp.isfinite(wc), wc, jnp.inf))
    i = jnp.clip(i, 1, size - 2)
    return i, jnp.sqrt(wq[i + jnp.array([-1, 0])] * wq[i + jnp.array([0, 1])])


def _ml_grid_search(evidence, grid, rounds: int):
    """``evidence`` on ``grid``, then ``rounds`` times at the two geometric midpoints next to
    the minimum, going on with those five points; returns the last points and values.

    Every evaluation runs in one loop, so the evidence is compiled once rather than once
    for the grid and once per round (each copy of the block-tridiagonal evidence cost
    about a second of compilation)."""
    if rounds == 0:
        return grid, jax.lax.map(evidence, grid)
    G = grid.shape[0]
    if G < 3:
        raise ValueError(f"grid: a refined search needs at least 3 densities, got {G}")
    W = max(G, 5)  # the window: the grid, then the five points about the minimum
    wq = jnp.concatenate([grid, jnp.full(W - G, grid[-1])])
    wc = jnp.full(W, jnp.inf, grid.dtype)

    def body(j, carry):
        wq, wc, c_first = carry
        on_grid = j < G
        second = ~on_grid & ((j - G) % 2 == 1)  # the second midpoint of a round
        size = jnp.where(j < G + 2, G, 5)  # the window holds the grid until a round ends
        i, mid = _refine_window(wq, wc, size)
        at = jnp.minimum(j, W - 1)  # the grid point of this step (while on the grid)
        c = evidence(jnp.where(on_grid, wq[at], jnp.where(second, mid[1], mid[0])))
        wc = jnp.where(on_grid, wc.at[at].set(c), wc)
        # after a round's second midpoint: go on with the five points about the minimum
        new_q = jnp.stack([wq[i - 1], mid[0], wq[i], mid[1], wq[i + 1]])
        new_c = jnp.stack([wc[i - 1], c_first, wc[i], c, wc[i + 1]])
        pad_q, pad_c = jnp.full(W - 5, new_q[-1]), jnp.full(W - 5, jnp.inf, grid.dtype)
        wq = jnp.where(second, jnp.concatenate([new_q, pad_q]), wq)
        wc = jnp.where(second, jnp.concatenate([new_c, pad_c]), wc)
        c_first = jnp.where(on_grid | second, c_first, c)
        return wq, wc, c_first

    wq, wc, _ = jax.lax.fori_loop(0, G + 2 * rounds, body, (wq, wc, jnp.zeros((), grid.dtype)))
    return wq[:5], wc[:5]


def _argmin_log(grid, values):
    """Minimiser of ``values`` over a log grid, refined by a parabola in ``log q``."""
    values = jnp.where(jnp.isfinite(values), values, jnp.inf)
    i = jnp.clip(jnp.argmin(values), 1, grid.shape[0] - 2)
    lo, mid, hi = values[i - 1], values[i], values[i + 1]
    denom = lo - 2.0 * mid + hi
    step = jnp.where((denom > 0) & jnp.isfinite(denom), 0.5 * (lo - hi) / denom, 0.0)
    step = jnp.where(mid <= jnp.minimum(lo, hi), jnp.clip(step, -0.5, 0.5), 0.0)
    logq = jnp.log(grid[i]) + step * (jnp.log(grid[i + 1]) - jnp.log(grid[i - 1])) / 2.0
    best = jnp.argmin(values)
    return jnp.where(best == i, jnp.exp(logq), grid[best])


def _prior_cost(x, A, Qinv, inv_q, order, start=None):
    S = x.reshape(x.shape[0], order, 3)
    r = S[1:] - jnp.einsum("fjl,fla->fja", A, S[:-1])
    cost = inv_q * jnp.einsum("fja,fjl,fla->", r, Qinv, r)
    if start is not None:
        d0 = x[0] - start[1]
        cost = cost + d0 @ start[0] @ d0
    return cost


def _solve(H, g, A, Qinv, inv_q, order, with_cov, start=None):
    D, E, b = _assemble(H, g, A, Qinv, inv_q, order, start)
    chol, y = bt.factor_forward(D, E, b)
    x = bt.back_substitute(chol, y)
    cov = bt.diag_inverse(chol) if with_cov else None
    return x, cov, bt.min_pivot_ratio(chol, D)


def _neg2_log_evidence(H, g, c, A, Qinv, q, order, start=None):
    """-2 log marginal likelihood (up to a constant) of the linearised model at ``q``.

    The minimum of ``x^T N x - 2 b^T x + c`` is ``c - |L^-1 b|^2``; the diffuse prior
    contributes ``log det N + (F - 1) 3 order log q`` (its null space, the polynomial
    part, is not penalised). A prior on the first state adds terms that do not depend on
    ``q`` (left out). Needs only the forward half of the solve.
    """
    D, E, b = _assemble(H, g, A, Qinv, 1 / q, order, start)
    chol, y = bt.factor_forward(D, E, b)
    F = H.shape[0]
    return c - jnp.sum(y * y) + bt.logdet(chol) + (F - 1) * 3 * order * jnp.log(q)


def _validate_options(
    order, iterations, loss, loss_scale, criterion, process_psd, pixel_sigma, depth_guess, grid
) -> None:
    if order not in (1, 2, 3):
        raise ValueError(f"order: expected 1, 2 or 3, got {order!r}")
    if not isinstance(iterations, int) or iterations < 0:
        raise ValueError(f"iterations: expected a non-negative int, got {iterations!r}")
    check_loss(loss, loss_scale)
    if criterion not in ("ml", "ubre"):
        raise ValueError(f"criterion: expected 'ml' or 'ubre', got {criterion!r}")
    check_positive("process_psd", process_psd, "a noise density")
    check_positive("pixel_sigma", pixel_sigma, "a pixel standard deviation")
    check_positive("depth_guess", depth_guess, "a depth in metres")
    if grid is not None:
        if np.ndim(grid) != 1 or np.shape(grid)[0] < 3:
            raise ValueError(f"psd_grid: expected shape (G,) with G >= 3, got {np.shape(grid)}")
        check_positive("psd_grid", grid, "noise densities")


def _validate_batch(P, uv, times, weights) -> None:
    if np.ndim(uv) != 3:
        raise ValueError(f"uv: expected shape (N, F, 2), got {np.shape(uv)}")
    if weights is not None and np.shape(weights) != np.shape(uv)[:2]:
        raise ValueError(f"weights: expected shape {np.shape(uv)[:2]}, got {np.shape(weights)}")
    validate_track(P, uv[0], times, None if weights is None else weights[0])
    check_tracks(uv, weights)


def smooth_trajectory(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "F 2"],
    times: Float[ArrayLike, " F"],
    weights: Float[ArrayLike, " F"] | None = None,
    *,
    order: int = 2,
    process_psd: float | None = None,
    pixel_sigma: float = 1.0,
    psd_grid: ArrayLike | None = None,
    iterations: int = 3,
    loss: str = "l2",
    loss_scale: float = 2.0,
    depth_guess: float = 1.0,
    criterion: str = "ml",
    covariance: bool = True,
    start_mean: Float[ArrayLike, "order 3"] | None = None,
    start_cov: Float[ArrayLike, "s s"] | None = None,
    max_depth_uncertainty: float | None = 0.08,
) -> Smoothed:
    """Estimate one point's trajectory with a smoothness prior (no basis, no k).

    jit-, vmap- and grad-compatible (see :func:`smooth_points` for a batched driver).

    Args:
        P: (F, 3, 4) projection matrices of undistorted cameras.
        uv: (F, 2) pixels [px]; entries with weight 0 are ignored and may be NaN.
        times: (F,) strictly increasing frame times [s].
        weights: (F,) non-negative weights (relative inverse pixel variances); 0 marks a
            missing detection. Default: all 1.
        order: 1 (random walk of the position, first differences), 2 (white-noise
            acceleration, second differences; the default) or 3 (white-noise jerk).
        process_psd: noise density ``q`` of the ``order``-th derivative
            [m^2 / s^(2 order - 1)]; ``None`` chooses it per trajectory (``criterion``).
        pixel_sigma: pixel noise standard deviation [px] (scales the covariances; the
            estimate depends on ``process_psd / pixel_sigma^2`` only).
        psd_grid: candidate densities (default :func:`default_psd_grid`).
        iterations: Gauss-Newton (IRLS) steps on the reprojection error after the two
            linear passes; 0 keeps the reweighted linear (algebraic) solution.
        loss: ``"l2"``, ``"huber"`` or ``"cauchy"`` on the reprojection error.
        loss_scale: robust loss threshold [px].
        depth_guess: depth [m] used to weight the very first linear pass only.
        criterion: ``"ml"`` (marginal likelihood) or ``"ubre"`` (unbiased risk) for the
            choice of ``process_psd``; both use ``pixel_sigma``.
        covariance: compute the posterior covariances and ``edf`` (a selected inversion,
            about as costly as one more solve); ``False`` leaves them NaN.
        start_mean, start_cov: optional Gaussian prior on the state at ``times[0]``: mean
            (order, 3) (position [m], velocity [m/s], ...) and covariance (3 order,
            3 order) in the order of ``Smoothed.states`` flattened (position first), e.g.
            a hand-over pose known from the robot or the end of an earlier track. Without
            it the start is free (no initial guess needed). Both or neither.
        max_depth_uncertainty: without a start prior, a track whose relative depth
            uncertainty ``kappa`` (:func:`jaxtraj.depth_uncertainty`: how far the estimate
            can slide along its viewing rays before this prior notices, relative to the
            distance to the camera) exceeds this is ``Status.DEGENERATE``: its depth is
            set by the prior, not by the data (slow cameras, a camera that follows the
            point), and the posterior covariance understates its error along the rays.
            ``None`` turns the check off.

    Returns:
        A :class:`Smoothed` with states, posterior covariances and a status.
    """
    validate_track(P, uv, times, weights)
    _validate_options(
        order,
        iterations,
        loss,
        loss_scale,
        criterion,
        process_psd,
        pixel_sigma,
        depth_guess,
        psd_grid,
    )
    grid = default_psd_grid(order) if psd_grid is None else psd_grid
    _validate_start(start_mean, start_cov, order)
    check_positive("max_depth_uncertainty", max_depth_uncertainty, "a relative depth error")
    P, uv, times, weights = as_float(P, uv, times, weights)
    dtype = P.dtype
    return _smooth_jit(
        P,
        uv,
        times,
        weights,
        order=order,
        process_psd=None if process_psd is None else jnp.asarray(process_psd, dtype),
        pixel_sigma=jnp.asarray(pixel_sigma, dtype),
        grid=jnp.asarray(grid, dtype),
        iterations=iterations,
        loss=loss,
        loss_scale=jnp.asarray(loss_scale, dtype),
        depth_guess=jnp.asarray(depth_guess, dtype),
        criterion=criterion,
        covariance=covariance,
        start_mean=None if start_mean is None else jnp.asarray(start_mean, dtype),
        start_cov=None if start_cov is None else jnp.asarray(start_cov, dtype),
        max_depth_uncertainty=max_depth_uncertainty,
    )


def _validate_start(start_mean, start_cov, order) -> None:
    if (start_mean is None) != (start_cov is None):
        raise ValueError(
            "start_mean and start_cov: give both (a prior on the first state) or neither"
        )
    if start_mean is None:
        return
    s = 3 * order
    check_shape("start_mean", start_mean, (order, 3), "(order, 3) first state [m, m/s, ...]")
    check_shape("start_cov", start_cov, (s, s), f"({s}, {s}) covariance of the first state")
    if is_concrete(start_cov):
        C = np.asarray(start_cov, float)
        if not np.all(np.isfinite(C)) or not np.allclose(C, C.T, rtol=1e-9, atol=0.0):
            raise ValueError("start_cov: expected a finite symmetric matrix")
        if np.linalg.eigvalsh(C).min() <= 0:
            raise ValueError("start_cov: expected a positive definite covariance")


def _smooth(
    P,
    uv,
    times,
    weights,
    *,
    order,
    process_psd,
    pixel_sigma,
    grid,
    iterations,
    loss,
    loss_scale,
    depth_guess,
    criterion,
    covariance,
    start_mean=None,
    start_cov=None,
    curve_only=False,
    max_depth_uncertainty=None,
    refine_grid=0,
):
    """The traced body of :func:`smooth_trajectory` (inputs already validated).

    ``refine_grid`` (criterion "ml"): that many times, evaluate the marginal likelihood at
    the two geometric midpoints next to the grid's minimum and go on with those five points
    (each halves the spacing about the minimum for two more evaluations)."""
    dtype = P.dtype
    F = P.shape[0]
    w = jnp.ones(F, dtype) if weights is None else weights
    sigma2 = jnp.asarray(pixel_sigma, dtype) ** 2
    observed = w > 0
    finite_in = jnp.all(jnp.isfinite(uv) | ~observed[:, None]) & jnp.all(jnp.isfinite(P))
    uv = jnp.where(observed[:, None], uv, 0.0)
    n_obs = jnp.sum(observed)

    Pn = normalise_cameras(P)
    tau = (times[-1] - times[0]) / (F - 1)  # time unit: the mean frame step
    A, Qinv = _transition(jnp.diff(times) / tau, order)
    qscale = tau ** (2 * order - 1)  # q in units of m^2 / tau^(2 order - 1)
    grid = jnp.asarray(grid, dtype) * qscale
    unit = (tau ** -np.repeat(np.arange(order), 3).astype(float)).astype(dtype)  # to seconds
    start = None
    if start_mean is not None:  # in the solver's time unit tau
        cov_tau = start_cov / (unit[:, None] * unit[None, :])
        info = solve_spd_small(cov_tau, jnp.eye(3 * order, dtype=dtype))  # no LAPACK call
        start = (info, start_mean.reshape(-1) / unit)

    Qa, qa = algebraic_blocks(Pn, uv)
    QtQ = jnp.sum(Qa[:, :, :, None] * Qa[:, :, None, :], axis=1)
    Qtq = jnp.sum(Qa * qa[:, :, None], axis=1)

    def data_cost(X):
        e, _, _ = linearise(Pn, uv, X)
        return jnp.sum(w * rho(jnp.sum(e * e, axis=1), loss, loss_scale)) / sigma2

    def gn_blocks(X, omega):
        """Data blocks of the reprojection error linearised at X."""
        return gauss_newton_blocks(Pn, uv, w * omega / sigma2, X)

    def robust_weight(X):
        e, _, _ = linearise(Pn, uv, X)
        return rho_weight(jnp.sum(e * e, axis=1), loss, loss_scale)

    # Two linear passes on the ray constraints, weighted by 1 / depth^2 so that the
    # algebraic residual measures pixels; the first with a nominal depth.
    if process_psd is None:
        q = jnp.sqrt(grid[0] * grid[-1])
    else:
        q = jnp.asarray(process_psd, dtype) * qscale
    z0, omega0 = jnp.full(F, depth_guess, dtype), jnp.ones(F, dtype)

    def linear_pass(q, z, omega):
        ww = w * omega / (sigma2 * z * z)
        x, _, piv = _solve(
            ww[:, None, None] * QtQ, ww[:, None] * Qtq, A, Qinv, 1 / q, order, False, start
        )
        z = jnp.sum(Pn[:, 2, :3] * x[:, :3], axis=1) + Pn[:, 2, 3]
        # a depth near zero (an estimate at the camera) must not dominate the weights
        z = jnp.maximum(jnp.abs(z), 0.1 * jnp.median(jnp.abs(z)) + jnp.finfo(dtype).tiny)
        return x, z, robust_weight(x[:, :3]), piv

    def linear_solution(q):
        # a loop rather than unrolled Python: the solve is compiled once (compile time)
        return jax.lax.fori_loop(
            0,
            2,
            lambda _, c: linear_pass(q, c[1], c[2]),
            (jnp.zeros((F, 3 * order), dtype), z0, omega0, jnp.zeros((), dtype)),
        )

    x, _, omega, pivot = linear_solution(q)

    def ubre(q, H, g, e, J, X0):
        """Unbiased risk ``RSS / sigma^2 + 2 edf - n``, edf and the solve at ``q``."""
        x, cov, pivot = _solve(H, g, A, Qinv, 1 / q, order, True, start)
        r = e + jnp.sum(J * (x[:, None, :3] - X0[:, None, :]), axis=2)
        rss = jnp.sum(w * omega * jnp.sum(r * r, axis=1)) / sigma2
        edf = jnp.sum(H * jnp.swapaxes(cov[:, :3, :3], 1, 2))
        return rss + 2.0 * edf - 2.0 * n_obs, edf, cov, pivot

    if process_psd is None:
        H, g, c, e, J = gn_blocks(x[:, :3], omega)

        def evidence(q):
            return _neg2_log_evidence(H, g, c, A, Qinv, q, order, start)

        if criterion == "ml":
            # a loop over the densities, not a vmap: under the drivers' vmap over points a
            # vmap here made every block-tridiagonal step a batch of batches (measured with
            # estimate_points, 256 points, F = 150: first call 33.4 -> 30.6 s, warm 2.74
            # -> 2.57 ms per point, means of two alternated runs; see the README)
            grid, crit = _ml_grid_search(evidence, grid, 0 if curve_only else refine_grid)
        else:
            crit = jax.vmap(lambda q: ubre(q, H, g, e, J, x[:, :3])[0])(grid)
        if curve_only:
            return crit
        q = _argmin_log(grid, crit)
        # again from the nominal depth at the chosen q: the depths of the first solution
        # (q in the middle of the grid) can be far off where the camera moves slowly, and
        # Gauss-Newton steps from there under a much stiffer prior did not always recover
        x, _, omega, pivot = linear_solution(q)

    def gauss_newton_step(_, carry):
        x, best, _ = carry
        H, g, _, _, _ = gn_blocks(x[:, :3], robust_weight(x[:, :3]))
        x_new, _, pivot = _solve(H, g, A, Qinv, 1 / q, order, False, start)
        cost = data_cost(x_new[:, :3]) + _prior_cost(x_new, A, Qinv, 1 / q, order, start)
        better = (cost <= best) | ~jnp.isfinite(best)
        return jnp.where(better, x_new, x), jnp.where(better, cost, best), pivot

    best = data_cost(x[:, :3]) + _prior_cost(x, A, Qinv, 1 / q, order, start)
    x, best, pivot = jax.lax.fori_loop(0, iterations, gauss_newton_step, (x, best, pivot))

    omega = robust_weight(x[:, :3])
    if covariance:
        H, g, _, e, J = gn_blocks(x[:, :3], omega)
        _, edf, cov, pivot = ubre(q, H, g, e, J, x[:, :3])
    else:
        edf, cov = jnp.nan, jnp.full((F, 3 * order, 3 * order), jnp.nan, dtype)

    states = (x * unit).reshape(F, order, 3)
    cov = cov * unit[:, None] * unit[None, :]
    edf = jnp.asarray(edf, dtype)
    e = linearise(Pn, uv, states[:, 0])[0]
    rms = jnp.sqrt(
        jnp.sum(jnp.where(observed, jnp.sum(e * e, axis=1), 0.0)) / jnp.maximum(n_obs, 1)
    )
    undetermined = False
    if max_depth_uncertainty is not None and start_mean is None:
        kappa = depth_uncertainty(states[:, 0], camera_centres(P), times, order)
        undetermined = kappa > max_depth_uncertainty
    status = jnp.where(
        ~finite_in | ~jnp.all(jnp.isfinite(states)),
        Status.NONFINITE,
        jnp.where(
            2 * n_obs < 3 * order,
            Status.UNDERDETERMINED,
            jnp.where(
                (pivot < 1e3 * jnp.finfo(dtype).eps) | undetermined,
                Status.DEGENERATE,
                Status.OK,
            ),
        ),
    ).astype(jnp.int32)
    return Smoothed(
        states=states,
        state_cov=cov,
        times=times,
        process_psd=q / qscale,
        pixel_sigma=jnp.sqrt(sigma2),
        rms_px=rms,
        edf=edf,
        num_observed=n_obs.astype(jnp.int32),
        status=status,
    )


_smooth_jit = eqx.filter_jit(_smooth)


def smooth_points(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "N F 2"],
    times: Float[ArrayLike, " F"],
    weights: Float[ArrayLike, "N F"] | None = None,
    **kwargs,
) -> Smoothed:
    """:func:`smooth_trajectory` for N points seen by the same cameras (jit + vmap).

    Keyword arguments are those of :func:`smooth_trajectory`; ``process_psd`` and
    ``pixel_sigma`` are shared by all points. ``start_mean`` may be (order, 3) for all
    points or (N, order, 3), one per point; ``start_cov`` is shared. Fields gain a leading
    axis of size N.
    """
    _validate_batch(P, uv, times, weights)
    P, uv, times, weights = as_float(P, uv, times, weights)
    w = jnp.ones(uv.shape[:2], P.dtype) if weights is None else weights
    for name in ("process_psd", "pixel_sigma", "loss_scale", "depth_guess", "psd_grid"):
        if kwargs.get(name) is not None:  # traced, so a new value does not recompile
            check_positive(name, kwargs[name], "a positive value")
            kwargs[name] = jnp.asarray(kwargs[name], P.dtype)
    mean, cov = kwargs.pop("start_mean", None), kwargs.pop("start_cov", None)
    order = kwargs.get("order", 2)
    if mean is not None and np.ndim(mean) == 3:
        check_shape("start_mean", mean, (uv.shape[0], order, 3), "(N, order, 3), one per point")
        _validate_start(mean[0], cov, order)
    else:
        _validate_start(mean, cov, order)
    if mean is not None:
        mean = jnp.broadcast_to(jnp.asarray(mean, P.dtype), (uv.shape[0], order, 3))
        cov = jnp.asarray(cov, P.dtype)
    return _smooth_points(P, uv, times, w, mean, cov, kwargs)


@eqx.filter_jit
def _smooth_points(P, uv, times, weights, start_mean, start_cov, kwargs):
    def one(u, w, m):
        return smooth_trajectory(P, u, times, w, start_mean=m, start_cov=start_cov, **kwargs)

    if start_mean is None:
        return jax.vmap(lambda u, w: one(u, w, None))(uv, weights)
    return jax.vmap(one)(uv, weights, start_mean)


@eqx.filter_jit
def _curves(P, uv, times, weights, kwargs):
    fn = lambda u, w: _smooth(P, u, times, w, process_psd=None, curve_only=True, **kwargs)  # noqa: E731
    return jax.vmap(fn)(uv, weights)


def select_process_psd(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "N F 2"],
    times: Float[ArrayLike, " F"],
    weights: Float[ArrayLike, "N F"] | None = None,
    *,
    order: int = 2,
    pixel_sigma: float = 1.0,
    psd_grid: ArrayLike | None = None,
    criterion: str = "ml",
    loss: str = "l2",
    loss_scale: float = 2.0,
    depth_guess: float = 1.0,
) -> Float[Array, ""]:
    """One noise density ``q`` for N points moving together (same object, same cameras).

    Maximises the summed marginal likelihood (or minimises the summed unbiased risk) of
    all tracks over the grid, refined by a parabola in ``log q``. The process noise is a
    property of the object's motion, so one value serves every point of it (and, being in
    physical units, later recordings of the same process); the per-point solves with a
    fixed ``process_psd`` are then about 3x cheaper than per-point selection.

    Returns:
        The scalar density [m^2 / s^(2 order - 1)] to pass as ``process_psd``.
    """
    _validate_batch(P, uv, times, weights)
    _validate_options(
        order, 0, loss, loss_scale, criterion, None, pixel_sigma, depth_guess, psd_grid
    )
    grid = default_psd_grid(order) if psd_grid is None else np.asarray(psd_grid)
    P, uv, times, weights = as_float(P, uv, times, weights)
    w = jnp.ones(uv.shape[:2], P.dtype) if weights is None else weights
    kwargs = dict(
        order=order,
        pixel_sigma=pixel_sigma,
        grid=grid,
        iterations=0,
        loss=loss,
        loss_scale=loss_scale,
        depth_guess=depth_guess,
        criterion=criterion,
        covariance=False,
    )
    curves = _curves(P, uv, times, w, kwargs)
    F = P.shape[0]
    tau = (times[-1] - times[0]) / (F - 1)
    qscale = tau ** (2 * order - 1)
    return _argmin_log(jnp.asarray(grid, P.dtype) * qscale, jnp.sum(curves, axis=0)) / qscale


def predict(result: Smoothed, horizon: float) -> tuple[Float[Array, "m 3"], Float[Array, "s s"]]:
    """Extrapolate the last state ``horizon`` seconds ahead with the prior model.

    Returns the predicted state (order, 3) (position, velocity, ...) and its covariance
    (3 order, 3 order). For one trajectory; vmap for more.
    """
    order = result.states.shape[-2]
    h = jnp.asarray(horizon, result.states.dtype)
    A, _ = _transition(h[None], order)
    Qbar, _ = _q_unit(order)
    d = _q_scale(h, order)
    Qh = jnp.asarray(Qbar, h.dtype) * d[:, None] * d[None, :] * result.process_psd
    eye3 = jnp.eye(3, dtype=h.dtype)
    Ak = jnp.kron(A[0], eye3)
    mean = A[0] @ result.states[-1]
    cov = Ak @ result.state_cov[-1] @ Ak.T + jnp.kron(Qh, eye3)
    return mean, 0.5 * (cov + cov.T)

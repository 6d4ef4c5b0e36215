"""Maximum-likelihood refinement of a DCT reconstruction (reprojection error).

The linear solve of paper eq. 6 minimises an algebraic error weighted by depth. Under
Gaussian pixel noise the maximum-likelihood coefficients minimise the reprojection error
``sum_i w_i rho(||pi(P_i Phi_i beta) - uv_i||^2) / sigma^2``; we minimise it over the
(k, 3) coefficients with optimistix (Levenberg-Marquardt or Gauss-Newton), started from
the linear solution. A robust ``rho`` (Huber, Cauchy) downweights outlier detections; it
enters as the residual transform ``e -> e sqrt(rho(|e|^2)) / |e|``, whose squared norm is
``rho``. The solver runs with ``throw=False`` so that it can be vmapped; its outcome is
reported in ``converged`` and the result never has a larger objective than the start
(if the solver did not improve, the starting coefficients are returned).

Pass the linear solve's ``status``: a start flagged DEGENERATE (or otherwise not OK) lies
on an almost flat likelihood along the viewing rays, where lowering the reprojection error
by a fraction of a pixel can move the point metres away; such starts are kept unchanged.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._batching import with_one_blas_thread
from .._checks import check_shape
from .._precision import cast_floats, least_squares_dtype
from ..solve import Status
from ._common import as_float, check_loss, check_positive, homogeneous, rho, validate_track

__all__ = ["Refined", "refine_dct", "refine_points"]


class Refined(eqx.Module):
    """Result of :func:`refine_dct` (one trajectory; leading axes from vmap).

    Attributes:
        coeffs: (k, 3) refined coefficients; points: (F, 3) trajectory [m].
        rms_px: reprojection RMS over observed frames after refinement [px].
        rms_px_initial: the same for the starting coefficients [px].
        cost, cost_initial: the robust objective (sum of rho / sigma^2) after and before.
        steps: optimiser steps taken.
        converged: the optimiser reported success (False: hit max_steps or failed).
        kept_start: the start was returned unchanged (no improvement, or a ``status``
            other than OK).
    """

    coeffs: Float[Array, "k 3"]
    points: Float[Array, "F 3"]
    rms_px: Float[Array, ""]
    rms_px_initial: Float[Array, ""]
    cost: Float[Array, ""]
    cost_initial: Float[Array, ""]
    steps: Int[Array, ""]
    converged: Bool[Array, ""]
    kept_start: Bool[Array, ""]


def _errors(P, uv, basis, coeffs):
    h = homogeneous(P, basis @ coeffs)
    return h[:, :2] / h[:, 2:3] - uv


def _robust_residual(e, loss, scale):
    s = jnp.sum(e * e, axis=-1)
    if loss == "l2":
        return e
    safe = jnp.where(s > 0, s, 1.0)
    factor = jnp.where(s > 0, jnp.sqrt(rho(safe, loss, scale) / safe), 1.0)
    return e * factor[:, None]


def refine_dct(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "F 2"],
    basis: Float[ArrayLike, "F k"],
    coeffs: Float[ArrayLike, "k 3"],
    weights: Float[ArrayLike, " F"] | None = None,
    *,
    status: Int[ArrayLike, ""] | None = None,
    pixel_sigma: float = 1.0,
    loss: str = "l2",
    loss_scale: float = 2.0,
    solver: str = "lm",
    max_steps: int = 50,
    rtol: float = 1e-8,
    atol: float = 1e-10,
) -> Refined:
    """Refine DCT coefficients by minimising the (robust) reprojection error.

    jit-, vmap- and grad-compatible (gradients flow through the optimiser's solution by
    the implicit function theorem).

    Args:
        P: (F, 3, 4) projection matrices; uv: (F, 2) pixels [px] (weight 0: ignored).
        basis: (F, k) trajectory basis; coeffs: (k, 3) start, e.g. ``reconstruct(...).coeffs``.
        weights: (F,) weights (relative inverse variances), 0 for missing detections.
        status: the linear solve's :class:`~jaxtraj.Status` for this start (e.g.
            ``reconstruct(...).status``); if it is not OK the start is returned unchanged.
            ``None``: refine every start.
        pixel_sigma: pixel noise standard deviation [px] (scales the cost only).
        loss: ``"l2"``, ``"huber"`` or ``"cauchy"``; loss_scale: its threshold [px].
        solver: ``"lm"`` (Levenberg-Marquardt) or ``"gn"`` (Gauss-Newton).
        max_steps, rtol, atol: optimiser settings.

    Returns:
        A :class:`Refined` (cost never above the start's).
    """
    validate_track(P, uv, None, weights)
    F = np.shape(P)[0]
    check_shape("basis", basis, (F, None), "(F, k) basis at the frame times")
    k = np.shape(basis)[1]
    check_shape("coeffs", coeffs, (k, 3), "(k, 3) starting coefficients")
    check_loss(loss, loss_scale)
    check_positive("pixel_sigma", pixel_sigma, "a pixel standard deviation")
    if solver not in ("lm", "gn"):
        raise ValueError(f"solver: expected 'lm' or 'gn', got {solver!r}")
    if not isinstance(max_steps, int) or max_steps < 1:
        raise ValueError(f"max_steps: expected a positive int, got {max_steps!r}")
    P, uv, basis, coeffs, weights = as_float(P, uv, basis, coeffs, weights)
    out_dtype = P.dtype
    P, uv, basis, coeffs, weights = cast_floats(  # float32 under x64: solved in float64
        (P, uv, basis, coeffs, weights), least_squares_dtype(out_dtype)
    )
    w = jnp.ones(F, P.dtype) if weights is None else weights
    obs = w > 0
    uv = jnp.where(obs[:, None], uv, 0.0)
    sw = jnp.sqrt(w) / pixel_sigma

    def residuals(beta, _):
        e = _errors(P, uv, basis, beta)
        return _robust_residual(e, loss, loss_scale) * sw[:, None]

    def cost(beta):
        r = residuals(beta, None)
        return jnp.sum(r * r)

    opt = (optx.LevenbergMarquardt if solver == "lm" else optx.GaussNewton)(rtol=rtol, atol=atol)
    sol = optx.least_squares(residuals, opt, coeffs, max_steps=max_steps, throw=False, options={})
    c0, c1 = cost(coeffs), cost(sol.value)
    better = jnp.isfinite(c1) & (c1 <= c0)
    if status is not None:
        better = better & (jnp.asarray(status) == Status.OK)
    beta = jnp.where(better, sol.value, coeffs)

    def rms(b):
        e = _errors(P, uv, basis, b)
        sq = jnp.where(obs, jnp.sum(e * e, axis=1), 0.0)
        return jnp.sqrt(jnp.sum(sq) / jnp.maximum(jnp.sum(obs), 1))

    refined = Refined(
        coeffs=beta,
        points=basis @ beta,
        rms_px=rms(beta),
        rms_px_initial=rms(coeffs),
        cost=jnp.where(better, c1, c0),
        cost_initial=c0,
        steps=jnp.asarray(sol.stats["num_steps"], jnp.int32),
        converged=sol.result == optx.RESULTS.successful,
        kept_start=~better,
    )
    return cast_floats(refined, out_dtype)


@eqx.filter_jit
def _refine_points(P, uv, basis, coeffs, weights, status, kwargs):
    fn = lambda u, c, w, s: refine_dct(P, u, basis, c, w, status=s, **kwargs)  # noqa: E731
    return jax.vmap(fn)(uv, coeffs, weights, status)


def refine_points(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "N F 2"],
    basis: Float[ArrayLike, "F k"],
    coeffs: Float[ArrayLike, "N k 3"],
    weights: Float[ArrayLike, "N F"] | None = None,
    status: Int[ArrayLike, " N"] | None = None,
    **kwargs,
) -> Refined:
    """:func:`refine_dct` for N points seen by the same cameras (jit + vmap).

    ``status``: (N,) statuses of the linear solves (``reconstruct_points(...).status``);
    points whose status is not OK keep their start."""
    if np.ndim(uv) != 3:
        raise ValueError(f"uv: expected shape (N, F, 2), got {np.shape(uv)}")
    N = np.shape(uv)[0]
    check_shape("coeffs", coeffs, (N, np.shape(basis)[-1], 3), "(N, k, 3) starts")
    validate_track(P, uv[0], None, None if weights is None else weights[0])
    P, uv, basis, coeffs, weights = as_float(P, uv, basis, coeffs, weights)
    w = jnp.ones(uv.shape[:2], P.dtype) if weights is None else weights
    st = jnp.zeros(N, jnp.int32) if status is None else jnp.asarray(status, jnp.int32)
    if st.shape != (N,):
        raise ValueError(f"status: expected shape ({N},), one per point, got {st.shape}")
    # its QR calls are small (module notes of jaxtraj._batching)
    return with_one_blas_thread(_refine_points, P, uv, basis, coeffs, w, st, kwargs)

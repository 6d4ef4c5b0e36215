"""Uncertainty of a DCT reconstruction: first order in the pixel and camera-pose noise,
plus the basis's model error (:func:`dct_covariance`).

The linear solve of :func:`jaxtraj.reconstruct` is ``g(beta, uv, P) = 0`` with
``g = sum_i w_i phi_i (x) Q_i^T (q_i - Q_i T_i)``. Differentiating at the solution gives
``d beta = N^-1 (dg/d uv d uv + dg/d xi d xi)`` with the normal matrix ``N``, so::

    Cov(beta) = N^-1 [ sum_i (phi_i phi_i^T) (x) (G_i Sigma_i G_i^T) ] N^-1

where, for the pixels of frame i, ``G_i = w_i (d_i Q_i^T - p3_i r_i^T)`` (3x2) with the
depth-like ``d_i = p3_i . [T_i; 1]`` and residual ``r_i = q_i - Q_i T_i`` (the second term
is exact, not a small-residual approximation), and for the camera pose the 3x6 Jacobian of
the same per-frame term with respect to a perturbation ``xi = (rho, theta)`` of the camera
pose in the world frame, ``T_w_c <- exp(xi^) T_w_c`` (translation [m], rotation [rad]),
i.e. ``P <- P exp(-xi^)``. Costs O(F k^2 + k^3); the point covariances are
``(phi_i^T (x) I_3) Cov(beta) (phi_i (x) I_3)`` at any rows ``phi_i`` (frames, prediction
times, or a derivative basis for velocities).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._checks import check_shape
from ..depth import _on_rays, camera_centres
from ..solve import (
    _angular_miss2,
    _factorise,
    _frame_spread,
    _gain_bound,
    _kron_sum,
    _reprojection_rms,
    normal_equations,
)
from ._common import as_float, validate_track

__all__ = ["ReconstructionCovariance", "dct_covariance", "points_covariance"]


class ReconstructionCovariance(eqx.Module):
    """Covariances of one DCT reconstruction (leading axes from vmap).

    Attributes:
        coeffs: (3k, 3k) covariance of the coefficients flattened row-major from (k, 3).
        points: (F, 3, 3) covariance of each reconstructed point [m^2].
    """

    coeffs: Float[Array, "3k 3k"]
    points: Float[Array, "F 3 3"]

    @property
    def std(self) -> Float[Array, "F 3"]:
        """(F, 3) standard deviation of each coordinate [m]."""
        return jnp.sqrt(jnp.diagonal(self.points, axis1=-2, axis2=-1))


def points_covariance(
    basis_rows: Float[ArrayLike, "T k"], coeffs_cov: Float[ArrayLike, "3k 3k"]
) -> Float[Array, "T 3 3"]:
    """Covariance (T, 3, 3) of ``phi_t^T beta`` at basis rows (times or derivatives)."""
    rows = jnp.asarray(basis_rows)
    C = jnp.asarray(coeffs_cov, rows.dtype)
    k = rows.shape[1]
    check_shape("coeffs_cov", C, (3 * k, 3 * k), "covariance of (k, 3) coefficients")
    C4 = C.reshape(k, 3, k, 3)
    return jnp.einsum("tu,uavb,tv->tab", rows, C4, rows)


def _per_frame_term(P_i, uv_i, T_i, w_i):
    """``w Q^T (q - Q T)`` (3,) of one frame, as a function of P and uv."""
    rows = P_i[:2, :] - uv_i[:, None] * P_i[2:3, :]
    Q, q = rows[:, :3], -rows[:, 3]
    return w_i * Q.T @ (q - Q @ T_i)


def _hat(xi):
    rho, theta = xi[:3], xi[3:]
    Wx = jnp.array(
        [[0.0, -theta[2], theta[1]], [theta[2], 0.0, -theta[0]], [-theta[1], theta[0], 0.0]],
        dtype=xi.dtype,
    )
    return jnp.concatenate([jnp.concatenate([Wx, rho[:, None]], 1), jnp.zeros((1, 4), xi.dtype)], 0)


def dct_covariance(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "F 2"],
    basis: Float[ArrayLike, "F k"],
    coeffs: Float[ArrayLike, "k 3"],
    weights: Float[ArrayLike, " F"] | None = None,
    *,
    pixel_sigma: float | Float[ArrayLike, " F"] = 1.0,
    pose_cov: Float[ArrayLike, "F 6 6"] | None = None,
    model_error: bool = True,
    penalty: Float[ArrayLike, " k"] | None = None,
) -> ReconstructionCovariance:
    """Covariance of :func:`jaxtraj.reconstruct`'s coefficients and points: first-order
    noise terms and, in ``points``, the basis's model error.

    The first-order terms cover the pixel (and pose) noise only. A basis too small for the
    motion leaves a model error that no noise level explains; with ``model_error`` the
    point covariances add, per frame, the part of the reprojection residual beyond the
    stated ``pixel_sigma``: across the ray, the fit's measured miss ``m_i`` (fit to its
    ray at the same depth, :func:`jaxtraj.depth.on_rays`), and along it the error scale of
    :attr:`jaxtraj.Reconstruction.relative_error` (gain times RMS angular miss) times the
    distance from the camera, both scaled by ``1 - 2 pixel_sigma^2 / rms^2`` (``rms``: the
    reprojection RMS of the 2D pixel error; 0 when the
    residual is at the noise level, so that a fit inside the span keeps the first-order
    covariance). Frames without a pixel (weight 0) take the observed frames' mean term.
    ``coeffs`` stays the first-order covariance.

    jit-, vmap- and grad-compatible.

    Args:
        P: (F, 3, 4) projection matrices.
        uv: (F, 2) pixels [px] (weight-0 entries are ignored).
        basis: (F, k) basis at the frame times, as passed to ``reconstruct``.
        coeffs: (k, 3) the solution returned by ``reconstruct``.
        weights: (F,) weights as passed to ``reconstruct`` (default all 1).
        pixel_sigma: pixel noise standard deviation [px], scalar or (F,).
        pose_cov: optional (F, 6, 6) covariance of the camera-pose perturbation
            ``(rho [m], theta [rad])`` of ``T_w_c`` in the world frame per frame.
        model_error: add the basis's model error to ``points`` (above).
        penalty: (k,) the diagonal penalty of a penalised fit (``penalty=`` of
            :func:`jaxtraj.reconstruct`), read as a prior on the coefficients: the
            posterior covariance ``N^-1 (J + s^2 pen) N^-1`` (``N`` with the penalty, ``J``
            the noise terms, ``s^2`` a ray-constraint row's noise variance averaged over the
            frames), about ``s^2 N^-1``. The noise-only sandwich would leave out the
            penalty's bias, which a stiff penalty makes larger than the spread.
            :func:`~jaxtraj.estimators.regularised_covariance` adds the along-ray bound.

    Returns:
        A :class:`ReconstructionCovariance`.
    """
    validate_track(P, uv, None, weights)
    F = np.shape(P)[0]
    k = np.shape(basis)[-1] if np.ndim(basis) == 2 else -1
    check_shape("basis", basis, (F, None), "(F, k) basis at the frame times")
    check_shape("coeffs", coeffs, (k, 3), "(k, 3) coefficients from reconstruct")
    if np.ndim(pixel_sigma) not in (0, 1) or (np.ndim(pixel_sigma) == 1 and len(pixel_sigma) != F):
        raise ValueError(
            f"pixel_sigma: expected a scalar or shape ({F},), got {np.shape(pixel_sigma)}"
        )
    if pose_cov is not None:
        check_shape("pose_cov", pose_cov, (F, 6, 6), "per-frame 6x6 pose covariance")
    if penalty is not None:
        check_shape("penalty", penalty, (k,), "(k,) diagonal penalty per coefficient")
    P, uv, basis, coeffs, weights, sig, pose_cov, penalty = as_float(
        P, uv, basis, coeffs, weights, pixel_sigma, pose_cov, penalty
    )
    w = jnp.ones(F, P.dtype) if weights is None else weights
    obs = w > 0
    uv = jnp.where(obs[:, None], uv, 0.0)
    N, _ = normal_equations(P, uv, basis, w)
    pen3 = None if penalty is None else jnp.repeat(penalty, 3)
    if pen3 is not None:
        N = N + jnp.diag(pen3)
    T = basis @ coeffs
    blocks = _pixel_blocks(P, uv, T, w, jnp.broadcast_to(sig**2, (F,)))
    if pose_cov is not None:

        def frame_jac(P_i, uv_i, T_i, w_i):
            def term(xi):
                P_xi = P_i @ (jnp.eye(4, dtype=xi.dtype) - _hat(xi))
                return _per_frame_term(P_xi, uv_i, T_i, w_i)

            return jax.jacfwd(term)(jnp.zeros(6, P_i.dtype))

        Gp = jax.vmap(frame_jac)(P, uv, T, w)  # (F, 3, 6)
        blocks = blocks + jnp.einsum("fia,fab,fjb->fij", Gp, pose_cov, Gp)
    # N^-1 from the solver's own factor (jaxtraj.solve._factorise: no LAPACK call, which
    # batched over points or design samples deadlocked on 2 cores with jaxlib 0.10)
    W, dd = _factorise(N)
    middle = _kron_sum(basis, blocks)
    if pen3 is not None:
        middle = middle + _prior_scale(P, T, w, sig) * jnp.diag(pen3)
    cov = _sandwich(W, dd, middle)
    points = points_covariance(basis, cov)
    if model_error:
        sig2 = jnp.broadcast_to(sig**2, (F,))
        points = points + _model_error_blocks(P, uv, basis, T, w, W, dd, sig2, pen3)
    return ReconstructionCovariance(coeffs=cov, points=points)


def _prior_scale(P, T, w, sig):
    """Variance of one ray-constraint row per unit weight, averaged over the observed
    frames: ``w_i d_i^2 sigma_i^2`` (``d_i`` the depth-like ``p3_i . [T_i; 1]``)."""
    F = P.shape[0]
    d = jnp.einsum("fj,fj->f", P[:, 2, :], jnp.concatenate([T, jnp.ones((F, 1), P.dtype)], 1))
    obs = w > 0
    v = jnp.where(obs, w * d**2 * jnp.broadcast_to(sig**2, (F,)), 0.0)
    return jnp.sum(v) / jnp.maximum(jnp.sum(obs), 1)


def _model_error_blocks(P, uv, basis, T, w, W, dd, sig2, pen3=None):
    """(F, 3, 3) model-error term of :func:`dct_covariance` at the fit ``T`` (F, 3)."""
    obs = w > 0
    Q = P[:, :2, :3] - uv[:, :, None] * P[:, 2:3, :3]  # normals of the planes through each ray
    C = camera_centres(P)
    gain = _gain_bound(basis, W, dd, _frame_spread(Q, w)[1], pen3=pen3)
    y = _on_rays(T, Q, C, obs)
    m = y - T  # across the ray: the fit's measured miss
    v = y - C  # along the observed ray, to the fit's depth
    n = jnp.maximum(jnp.sum(obs), 1)
    angle2 = _angular_miss2(T, y, C, obs)  # relative_error = gain sqrt(angle2)
    rms2 = _reprojection_rms(P, uv, T, obs) ** 2
    noise2 = 2.0 * jnp.sum(jnp.where(obs, sig2, 0.0)) / n  # two pixel coordinates
    excess = jnp.clip(1.0 - noise2 / jnp.maximum(rms2, jnp.finfo(T.dtype).tiny), 0.0)
    along = (gain**2 * angle2) * v[:, :, None] * v[:, None, :]  # (rel |v|)^2 along the ray
    # the miss is measured against the noisy ray: add the ray's own pixel noise at that depth
    J = jax.vmap(_ray_point_jacobian)(P, uv, v)  # (F, 3, 2)
    across = m[:, :, None] * m[:, None, :] + sig2[:, None, None] * jnp.einsum("fia,fja->fij", J, J)
    blocks = jnp.where(obs[:, None, None], across + along, 0.0)
    # frames without a pixel (outside the image) have no miss to measure, but the basis
    # misses the motion there too: they take the observed frames' mean block
    blocks = jnp.where(obs[:, None, None], blocks, jnp.sum(blocks, axis=0) / n)
    return jnp.where(jnp.isfinite(gain), excess, 0.0) * blocks


def _ray_point_jacobian(P_i, uv_i, v_i):
    """(3, 2) derivative with respect to the pixel of the point at offset ``v_i`` from the
    camera along the ray through ``uv_i`` (the point's distance held fixed)."""
    dist = jnp.linalg.norm(v_i)

    def point(u):
        rows = P_i[:2, :3] - u[:, None] * P_i[2:3, :3]
        d = jnp.cross(rows[0], rows[1])
        d = d / jnp.linalg.norm(d)
        return dist * jnp.sign(jax.lax.stop_gradient(d @ v_i)) * d

    return jax.jacfwd(point)(uv_i)


def _pixel_blocks(P, uv, T, w, sig2):
    """(F, 3, 3) per-frame ``G_i Sigma_i G_i^T`` of the pixel noise (module notes) at the
    points ``T`` (F, 3), with ``Sigma_i = sig2_i I`` and ``uv`` zero where ``w`` is."""
    F = P.shape[0]
    Th = jnp.concatenate([T, jnp.ones((F, 1), P.dtype)], axis=1)
    rows = P[:, :2, :] - uv[:, :, None] * P[:, 2:3, :]
    Q, q = rows[:, :, :3], -rows[:, :, 3]
    r = q - jnp.einsum("fai,fi->fa", Q, T)
    d = jnp.einsum("fj,fj->f", P[:, 2, :], Th)
    G = w[:, None, None] * (
        d[:, None, None] * jnp.swapaxes(Q, 1, 2) - P[:, 2, :3, None] * r[:, None, :]
    )
    return sig2[:, None, None] * jnp.einsum("fia,fja->fij", G, G)


def _sandwich(W, dd, S):
    """``N^-1 S N^-1`` (symmetrised) from ``N^-1 = D W^T W D`` (``dd`` the diagonal of D)."""
    WD = W * dd[None, :]
    cov = WD.T @ (WD @ S @ WD.T) @ WD
    return 0.5 * (cov + cov.T)

"""Expected error of the known-layout pose (per-image PnP) for a camera path.

When the workpiece carries reference points at known positions ``m_j`` (its marker
layout, object frame), every image gives the object pose ``(R_w_o, p_w_o)`` on its own
(PnP refined by Levenberg-Marquardt, as the pipeline's ``pose_method="pnp"``). To first
order in the pixel noise (isotropic, ``sigma`` px per point) the estimate is unbiased and
its error ``delta = (dphi, dp)`` (rotation about the object origin in the world frame,
translation) has the covariance

    Cov delta = sigma^2 (sum_j J_j^T J_j)^-1,   J_j = d pi(P x_j) / d x  [-[R m_j]_x, I],

with ``x_j = R m_j + p`` the reference point in the world. The error of a point ``a`` of
the object (e.g. the assembly point) is ``G delta`` with ``G = [-[R a]_x, I]``, so its
expected squared error per image is ``sigma^2 tr(G (sum J^T J)^-1 G^T)``. No temporal
model is involved: each image is measured alone, which is why the layout-based pose needs
no camera motion at all but gains from a camera that sees the layout from close and
obliquely. Exact to first order; checked against Monte-Carlo runs of OpenCV's PnP in the
tests.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._linalg import cholesky_small, matmul_small, solve_triangular_small
from ..fusion.imu import skew

__all__ = [
    "expected_pose_errors_for_cameras",
    "gaussian_mean_norm",
    "pose_point_covariances",
]


def _frame_covariance(P, R, p, layout, point, pixel_sigma):
    """(3, 3) covariance of the object point ``point`` from one image's PnP."""
    offsets = layout @ R.T  # (M, 3): R m_j
    X = offsets + p
    h = X @ P[:, :3].T + P[:, 3]  # (M, 3)
    uv = h[:, :2] / h[:, 2:3]
    dudx = (P[None, :2, :3] - uv[:, :, None] * P[None, 2:3, :3]) / h[:, 2, None, None]
    G = jnp.concatenate(
        [-skew(offsets), jnp.broadcast_to(jnp.eye(3, dtype=P.dtype), (len(X), 3, 3))], -1
    )
    J = matmul_small(dudx, G).reshape(-1, 6)  # (2 M, 6)
    info = jnp.sum(J[:, :, None] * J[:, None, :], axis=0)
    Ga = jnp.concatenate([-skew(jnp.sum(R * point, axis=1)), jnp.eye(3, dtype=P.dtype)], -1)
    # the information is symmetric positive definite for >= 3 points in general position;
    # small unrolled factorisation: no LAPACK call per frame and sample under vmap
    A = solve_triangular_small(cholesky_small(info), Ga.T)  # (6, 3)
    return jnp.asarray(pixel_sigma, P.dtype) ** 2 * jnp.sum(A[:, :, None] * A[:, None, :], axis=0)


def _checked_layout(layout, dtype):
    layout = jnp.asarray(layout, dtype)
    if layout.ndim != 2 or layout.shape[1] != 3 or layout.shape[0] < 4:
        raise ValueError(f"layout: expected (M, 3) reference points, M >= 4, got {layout.shape}")
    return layout


def pose_point_covariances(
    P: Float[ArrayLike, "F 3 4"],
    R_w_o: Float[ArrayLike, "F 3 3"],
    p_w_o: Float[ArrayLike, "F 3"],
    layout: Float[ArrayLike, "M 3"],
    point: Float[ArrayLike, " 3"] = (0.0, 0.0, 0.0),
    pixel_sigma: float = 0.3,
) -> Float[Array, "F 3 3"]:
    """First-order covariance (F, 3, 3) [m^2] of an object point measured by per-image PnP.

    Args:
        P: (F, 3, 4) projection matrices (pixels of the reference points).
        R_w_o, p_w_o: (F, 3, 3), (F, 3) the object's true pose per image.
        layout: (M, 3) the reference points in the object frame [m] (M >= 4, not all on
            one line).
        point: (3,) the object point whose error is wanted (object frame) [m].
        pixel_sigma: detection noise per reference point and axis [px].
    """
    P = jnp.asarray(P)
    dtype = P.dtype
    layout = _checked_layout(layout, dtype)
    F = P.shape[0]
    R_w_o = jnp.asarray(R_w_o, dtype)
    p_w_o = jnp.asarray(p_w_o, dtype)
    if R_w_o.shape != (F, 3, 3) or p_w_o.shape != (F, 3):
        raise ValueError(
            f"R_w_o, p_w_o: expected shapes ({F}, 3, 3) and ({F}, 3), got {R_w_o.shape} and "
            f"{p_w_o.shape}"
        )
    point = jnp.asarray(point, dtype)
    return jax.vmap(lambda Pf, R, p: _frame_covariance(Pf, R, p, layout, point, pixel_sigma))(
        P, R_w_o, p_w_o
    )


def expected_pose_errors_for_cameras(
    P: Float[ArrayLike, "F 3 4"],
    samples: Float[ArrayLike, "S F 3"],
    R_w_o: Float[ArrayLike, "3 3"],
    layout: Float[ArrayLike, "M 3"],
    point: Float[ArrayLike, " 3"] = (0.0, 0.0, 0.0),
    pixel_sigma: float = 0.3,
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Expected ``(rms, mean)`` error [m] of the object point ``point`` measured by
    per-image PnP, over sample trajectories of that point, as
    :func:`jaxtraj.design.expected_errors_for_cameras` for the DCT.

    Args:
        P: (F, 3, 4) cameras.
        samples: (S, F, 3) plausible trajectories of the object point ``point`` [m].
        R_w_o: (3, 3) the object's orientation (held over the recording).
        layout, point, pixel_sigma: as :func:`pose_point_covariances`.

    The RMS is ``sqrt(mean tr Cov)``; the mean is the expected Euclidean error of the
    Gaussian first-order error, ``mean E|e|`` (:func:`gaussian_mean_norm`; the estimate is
    unbiased to first order, so unlike the temporal estimators' Jensen bound this is the
    expected mean error itself).
    """
    P = jnp.asarray(P)
    dtype = P.dtype
    samples = jnp.asarray(samples, dtype)
    if samples.ndim != 3 or samples.shape[1:] != (P.shape[0], 3):
        raise ValueError(
            f"samples: expected shape (S, {P.shape[0]}, 3) (one point per camera), got "
            f"{samples.shape}"
        )
    return _pose_metrics(_sample_covariances(P, samples, R_w_o, layout, point, pixel_sigma))


def _pose_metrics(covs):
    """``(rms, mean)`` [m] of :func:`expected_pose_errors_for_cameras` from the (S, F, 3, 3)
    covariances (+inf where they are NaN)."""
    rms = jnp.sqrt(jnp.mean(jnp.trace(covs, axis1=-2, axis2=-1)))
    mean = jnp.mean(gaussian_mean_norm(covs))
    return jnp.where(jnp.isnan(rms), jnp.inf, rms), jnp.where(jnp.isnan(mean), jnp.inf, mean)


def _sample_covariances(P, samples, R_w_o, layout, point, pixel_sigma):
    """(S, F, 3, 3) covariances of the followed point along each sample trajectory, the
    object held at the orientation ``R_w_o``."""
    dtype = P.dtype
    layout = _checked_layout(layout, dtype)
    R = jnp.broadcast_to(jnp.asarray(R_w_o, dtype), (P.shape[0], 3, 3))
    point = jnp.asarray(point, dtype)

    def one(x):
        return pose_point_covariances(P, R, x - R @ point, layout, point, pixel_sigma)

    return jax.vmap(one)(jnp.asarray(samples, dtype))


#: quadrature of :func:`gaussian_mean_norm`: the integrand in ``u = log s`` decays only as
#: ``exp(-|u| / 2)`` on both sides, so the trapezoidal rule in ``u`` needed 321 nodes over
#: [-40, 40]; the substitution ``u = 4 sinh(t)`` makes the decay double-exponential, and 33
#: nodes over ``t`` in [-3, 3] (``u`` in [-40, 40]) give the same integral within 6e-9
#: (relative; 27 covariances from isotropic to rank one and eigenvalue ratios of 1e6, against
#: a rule with step 0.01 over [-90, 90]). The objective of a pose design evaluates it for
#: every image and plausible trajectory: with 321 nodes it was half of the objective's cost.
#: The nodes ``u`` and the trapezoidal weights ``du/dt dt`` (the end nodes' integrand is
#: below 1e-8 of the sum) are numpy constants, so importing the module creates no JAX array.
_DE_T = np.linspace(-3.0, 3.0, 33)
_DE_U = 4.0 * np.sinh(_DE_T)
_DE_W = 4.0 * np.cosh(_DE_T) * (_DE_T[1] - _DE_T[0])


def gaussian_mean_norm(cov: Float[ArrayLike, "... 3 3"]) -> Float[Array, "..."]:
    """``E|e|`` for ``e ~ N(0, cov)`` (3-D), differentiable and free of eigen-decompositions.

    From ``E sqrt(Y) = (4 pi)^(-1/2) int_0^inf (1 - E exp(-s Y)) s^(-3/2) ds`` with
    ``Y = |e|^2`` and ``E exp(-s Y) = det(I + 2 s cov)^(-1/2)``; the determinant is the
    cubic in ``s`` of ``cov``'s invariants, integrated by the trapezoidal rule after the
    double-exponential substitution ``s = exp(4 sinh t)`` (33 nodes; relative error below
    1e-8). ``sqrt(tr cov)`` (Jensen's bound) is 1.09x this for an isotropic error and 1.25x
    for an error along one axis.
    """
    cov = jnp.asarray(cov)
    m = jnp.trace(cov, axis1=-2, axis2=-1)
    c = cov / m[..., None, None]
    e2 = 0.5 * (1.0 - jnp.sum(c * jnp.swapaxes(c, -1, -2), axis=(-2, -1)))
    e3 = jnp.linalg.det(c)
    w = jnp.asarray(_DE_W, cov.dtype)
    s = jnp.exp(jnp.asarray(_DE_U, cov.dtype))
    det = 1.0 + 2.0 * s + 4.0 * s**2 * e2[..., None] + 8.0 * s**3 * e3[..., None]
    f = -jnp.expm1(-0.5 * jnp.log(det)) / jnp.sqrt(s)
    integral = jnp.sum(f * w, -1)
    return jnp.sqrt(m) * integral / (2.0 * jnp.sqrt(jnp.pi))

"""Reconstructibility and failure analysis (DESIGN.md section 2, paper eq. 7).

* :func:`reconstructibility` - Park et al.'s eta, the ratio of the camera path's and the
  point path's components outside the basis span. A simulation/design quantity: it needs
  the true trajectory.
* :func:`on_ray_decomposition` - write an estimate as ``a_i T_i + (1 - a_i) C_i`` (eq. 7):
  ``a = 1`` is the truth, ``a = 0`` the camera centre.
* :func:`conditioning_gain` - the solver's degeneracy figure, without solving.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._checks import check_shape
from .solve import _gain_only, _validate

__all__ = ["OnRay", "conditioning_gain", "on_ray_decomposition", "reconstructibility"]


def _residual_from_span(basis: Array, X: Array) -> Array:
    """``P_perp X``: the part of each coordinate column of X outside ``span(basis)``."""
    Qb, _ = jnp.linalg.qr(basis)
    return X - Qb @ (Qb.T @ X)


def reconstructibility(
    camera_centres: Float[ArrayLike, "F 3"],
    points: Float[ArrayLike, "F 3"],
    basis: Float[ArrayLike, "F k"],
) -> Float[Array, ""]:
    """Reconstructibility ``eta = ||P_perp c|| / ||P_perp x||`` (Park et al., ECCV 2010).

    ``P_perp = I - Theta (Theta^T Theta)^-1 Theta^T`` with ``Theta = basis (x) I_3``. eta
    tends to 0 when the camera path lies in the basis span and grows without bound as the
    reconstruction becomes exact. Invariant to a rigid change of world frame. If the true
    trajectory lies exactly in the span the ratio is infinite.

    Args:
        camera_centres: (F, 3) camera centres at the frame times [m].
        points: (F, 3) true point trajectory [m].
        basis: (F, k) trajectory basis at the frame times.
    """
    check_shape("camera_centres", camera_centres, (None, 3), "one centre per frame")
    F = jnp.shape(camera_centres)[0]
    check_shape("points", points, (F, 3), "one true point per frame")
    check_shape("basis", basis, (F, None), "(F, k) basis at the frame times")
    c = jnp.asarray(camera_centres)
    dtype = jnp.result_type(c.dtype, jnp.float32)
    x = jnp.asarray(points, dtype)
    b = jnp.asarray(basis, dtype)
    return jnp.linalg.norm(_residual_from_span(b, c.astype(dtype))) / jnp.linalg.norm(
        _residual_from_span(b, x)
    )


class OnRay(eqx.Module):
    """Eq. 7 decomposition of an estimate. ``a``: (F,) position along each ray (1 = truth,
    0 = camera centre); ``off_ray``: (F,) distance of the estimate from the line [m]."""

    a: Float[Array, " F"]
    off_ray: Float[Array, " F"]


def on_ray_decomposition(
    estimate: Float[ArrayLike, "F 3"],
    points: Float[ArrayLike, "F 3"],
    camera_centres: Float[ArrayLike, "F 3"],
) -> OnRay:
    """Fit ``estimate_i ~ a_i points_i + (1 - a_i) camera_centres_i`` per frame (eq. 7)."""
    check_shape("estimate", estimate, (None, 3), "(F, 3) estimated points")
    F = jnp.shape(estimate)[0]
    check_shape("points", points, (F, 3), "(F, 3) true points")
    check_shape("camera_centres", camera_centres, (F, 3), "(F, 3) camera centres")
    e, x, c = (jnp.asarray(a) for a in (estimate, points, camera_centres))
    ray = x - c
    a = jnp.sum((e - c) * ray, axis=1) / jnp.sum(ray * ray, axis=1)
    off = jnp.linalg.norm(e - c - a[:, None] * ray, axis=1)
    return OnRay(a=a, off_ray=off)


def conditioning_gain(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "F 2"],
    basis: Float[ArrayLike, "F k"],
    weights: Float[ArrayLike, " F"] | None = None,
) -> Float[Array, ""]:
    """The conditioning gain ``||Theta N^-1 Theta^T Q^T W Q||_2`` of a reconstruction.

    The noise-free estimate is ``Pi x`` with that oblique projector, so the error is at
    most the gain times the distance of the true trajectory from the basis span. About
    1.5-5 on healthy problems; 1e3 and more when the camera path is nearly in the span.
    Computed with a symmetric eigensolver (exact); :func:`jaxtraj.reconstruct` reports
    a power-iteration estimate of the same number.
    """
    _validate(P, uv, basis, weights)
    return _gain_only(P, uv, basis, weights)

"""Is the depth of a trajectory estimate determined by the data?

The pixels fix two of the three coordinates of each frame; the third, the depth along the
viewing ray, is not seen. The trajectories ``c + s (x - c)`` (``c`` the camera centres)
project to the same pixels for every ``s``, and when the camera moves slowly or follows
the point they are all about as smooth as ``x``: the model (a smoothness prior, the span
of a basis) then decides ``s``, not the data. The roughness ratio::

    kappa_m^2 = R_m(x) / R_m(x - c),    R_m(y) = sum_i h_i |D^m y_i|^2

(``D^m``: ``m``-th divided differences in units of the mean frame step, ``h_i`` the span
of each difference) measures how far an estimate can slide along its rays, relative to
its distance from the cameras, before a prior of order ``m`` notices; the notes of
:mod:`jaxtraj.estimators.estimate` derive it. It is 0.001-0.05 for orbits of 20 deg/frame
or more and random cameras, and near 1 or above when the camera is not rougher than the
point (slow orbits, a camera that follows the point).

:func:`ray_depth_uncertainty` measures ``kappa`` of an estimate moved onto its viewing
rays (each observed frame's point replaced by the point of its ray at the estimate's
depth). A fit of the ray constraints that is not on its rays is either limited by its
model (a truncated basis) or has collapsed towards the camera centres, which satisfy
every ray constraint exactly; moving it onto the rays keeps its depths and discards the
part the pixels do not support, so that ``kappa`` then judges the depths alone. The
solver (:mod:`jaxtraj.solve`) flags a fit whose on-ray ``kappa`` exceeds its
``max_depth_uncertainty``. :func:`with_ray_bound` puts the answer into a covariance: the
standard deviation along each ray becomes at least ``kappa / 2`` of the distance
(``estimate_points``, ``regularised_covariance``).

Pure JAX, no LAPACK call; one trajectory per call (vmap for more).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from .camera import camera_centre

__all__ = [
    "camera_centres",
    "depth_uncertainty",
    "on_rays",
    "ray_depth_uncertainty",
    "with_ray_bound",
]


def camera_centres(P: Float[Array, "F 3 4"]) -> Float[Array, "F 3"]:
    """(F, 3) centres ``C`` with ``P [C; 1] = 0`` of finite cameras."""
    return jax.vmap(camera_centre)(P)


def _roughness(y: Float[Array, "F 3"], t: Float[Array, " F"], order: int) -> Float[Array, ""]:
    """``sum_i h_i |D^m y_i|^2``: squared ``order``-th divided differences of ``y`` (time
    in units of the mean frame step), each weighted by its span ``h_i / order`` so that
    an integrated white noise gives the same expected value per term at any spacing."""
    d = y
    for j in range(1, order + 1):
        span = (t[j:] - t[:-j])[:, None]
        d = j * jnp.diff(d, axis=0) / span
    span = t[order:] - t[:-order]
    return jnp.sum(span / order * jnp.sum(d * d, axis=-1))


def depth_uncertainty(
    points: Float[ArrayLike, "F 3"],
    centres: Float[ArrayLike, "F 3"],
    times: Float[ArrayLike, " F"],
    order: int = 2,
) -> Float[Array, ""]:
    """Relative depth uncertainty ``kappa`` of one trajectory estimate (module notes).

    ``sqrt(R(x) / R(x - c))`` with ``R`` the ``order``-th divided-difference roughness:
    how much the estimate can slide along its viewing rays, towards or away from the
    cameras ``c``, relative to its distance from them, before the prior of that order
    notices. Works for any estimator's output (one trajectory; vmap for more).
    """
    x = jnp.asarray(points)
    c = jnp.asarray(centres, x.dtype)
    t = jnp.asarray(times, x.dtype)
    t = (t - t[0]) / ((t[-1] - t[0]) / (t.shape[0] - 1))
    num = _roughness(x, t, order)
    den = _roughness(x - c, t, order)
    tiny = jnp.finfo(x.dtype).tiny
    return jnp.sqrt(num / jnp.maximum(den, tiny))


def on_rays(
    points: Float[ArrayLike, "F 3"],
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "F 2"],
    observed: Bool[ArrayLike, " F"],
    centres: Float[ArrayLike, "F 3"] | None = None,
) -> Float[Array, "F 3"]:
    """``points`` moved onto the viewing rays of the pixels ``uv``: on each observed frame
    the point of the ray through ``uv`` at the same depth (orthogonal projection onto the
    ray's line); unobserved frames keep their point. ``centres``: the cameras' centres
    when already computed (:func:`camera_centres`)."""
    x = jnp.asarray(points)
    P = jnp.asarray(P, x.dtype)
    observed = jnp.asarray(observed)
    uv = jnp.where(observed[:, None], jnp.asarray(uv, x.dtype), 0.0)
    C = camera_centres(P) if centres is None else jnp.asarray(centres, x.dtype)
    rows = P[:, :2, :3] - uv[:, :, None] * P[:, 2:3, :3]  # normals of two planes through the ray
    return _on_rays(x, rows, C, observed)


def _on_rays(x, rows, C, observed):
    """:func:`on_rays` from each frame's (2, 3) normals ``rows`` of two planes through its
    ray (the solver's ray constraints ``Q``)."""
    d = jnp.cross(rows[:, 0], rows[:, 1])
    d = d / jnp.maximum(jnp.linalg.norm(d, axis=-1, keepdims=True), jnp.finfo(x.dtype).tiny)
    y = C + d * jnp.sum(d * (x - C), axis=-1, keepdims=True)
    return jnp.where(observed[:, None], y, x)


def ray_depth_uncertainty(
    points: Float[ArrayLike, "F 3"],
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "F 2"],
    observed: Bool[ArrayLike, " F"],
    times: Float[ArrayLike, " F"] | None = None,
    order: int = 2,
    centres: Float[ArrayLike, "F 3"] | None = None,
) -> Float[Array, ""]:
    """``kappa`` (:func:`depth_uncertainty`, prior ``order``) of ``points`` moved onto
    their viewing rays (:func:`on_rays`). ``times`` default to equal frame steps."""
    x = jnp.asarray(points)
    C = camera_centres(jnp.asarray(P, x.dtype)) if centres is None else centres
    t = jnp.arange(x.shape[0], dtype=x.dtype) if times is None else times
    return depth_uncertainty(on_rays(x, P, uv, observed, C), C, t, order)


def with_ray_bound(
    cov: Float[ArrayLike, "F 3 3"], d: Float[ArrayLike, "F 3"], rel_sd: Float[ArrayLike, ""]
) -> Float[Array, "F 3 3"]:
    """Point covariances ``cov`` with the standard deviation along each ray ``d_i`` (the
    point minus the camera centre) raised to at least ``rel_sd |d_i|``: adds
    ``max(rel_sd^2 |d_i|^2 - u_i^T cov_i u_i, 0) u_i u_i^T`` (``u_i = d_i / |d_i|``). The
    estimators pass ``rel_sd = kappa / 2`` (:func:`depth_uncertainty` as a two-standard-
    deviation bound of the relative error along the rays)."""
    cov = jnp.asarray(cov)
    d = jnp.asarray(d, cov.dtype)
    n2 = jnp.sum(d * d, axis=-1)
    tiny = jnp.finfo(d.dtype).tiny
    u = d / jnp.sqrt(jnp.maximum(n2, tiny))[:, None]
    along = jnp.einsum("fi,fij,fj->f", u, cov, u)
    extra = jnp.maximum(rel_sd**2 * n2 - along, 0.0)
    return cov + extra[:, None, None] * u[:, :, None] * u[:, None, :]

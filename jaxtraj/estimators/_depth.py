"""Depth determinability of a trajectory estimate (see :mod:`.estimate` for the method).

Shared by :func:`jaxtraj.estimate_points` and the statuses of the smoother and the
regularised DCT.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ..camera import camera_centre
from ..solve import Status


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
    """Relative depth uncertainty ``kappa`` of one trajectory estimate (the notes of
    :mod:`jaxtraj.estimators.estimate` derive it).

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


def flag_undetermined_depth(
    res,
    P,
    times,
    order: int,
    max_depth_uncertainty: float = 0.08,
    max_rms_px: float | None = None,
):
    """``res`` (a :class:`jaxtraj.Reconstruction`, one point or a batch) with its status set
    to ``DEGENERATE`` where ``kappa`` of the roughness ``order`` exceeds
    ``max_depth_uncertainty``: the roughness penalty, not the data, set the depth.

    With ``max_rms_px``, also where the fit's reprojection RMS exceeds it: ``kappa`` is
    measured at the estimate and assumes that the estimate explains its pixels. A fit of
    the ray constraints can instead collapse towards the camera centres, which satisfy
    every ray constraint exactly; with a stiff penalty on a slow camera such a fit was
    1.4 m off at 48 px RMS with ``kappa`` 0.036 (estimate 0.14 m from the cameras)."""
    P = jnp.asarray(P, res.points.dtype)
    C = camera_centres(P)
    t = jnp.asarray(times, res.points.dtype)
    kappa_of = lambda x: depth_uncertainty(x, C, t, order)  # noqa: E731
    kappa = kappa_of(res.points) if res.points.ndim == 2 else jax.vmap(kappa_of)(res.points)
    undetermined = kappa > max_depth_uncertainty
    if max_rms_px is not None:
        undetermined = undetermined | ~(res.rms_px <= max_rms_px)
    status = jnp.where(
        (res.status == Status.OK) & undetermined, Status.DEGENERATE, res.status
    ).astype(res.status.dtype)
    return eqx.tree_at(lambda r: r.status, res, status)

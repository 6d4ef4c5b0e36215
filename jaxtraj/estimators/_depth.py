"""Depth determinability of a trajectory estimate (see :mod:`.estimate` for the method).

Shared by :func:`jaxtraj.estimate_points` and the statuses of the smoother and the
regularised DCT.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..depth import camera_centres, depth_uncertainty
from ..solve import Status


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

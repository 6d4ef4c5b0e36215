"""Limits of a real robot cell, as normalised constraint values ``g <= 0``.

Every constraint is scaled to be dimensionless (a violation of 0.1 means 10 % beyond
the limit, or 0.1 of the tolerance), so one penalty weight serves them all:

* ``workspace`` - camera centre inside the box ``[lo, hi]`` (on the limit grid);
* ``standoff`` - distance to the predicted point within ``[d_min, d_max]`` (images);
* ``field_of_view`` - every plausible point at most ``half_fov - margin`` off the optical
  axis (images);
* ``velocity``, ``acceleration`` - camera speed and acceleration below the robot's limits
  (limit grid);
* ``end`` - final camera centre within ``end_tolerance`` of ``predicted[-1] + end_offset``
  (the camera rides with the part to be assembled, which must arrive at the assembly
  point).

The start pose is met exactly by construction (:class:`~jaxtraj.design.CameraPathModel`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .path import CameraPathModel

__all__ = ["CONSTRAINTS", "CellLimits", "constraint_values", "penalty"]

CONSTRAINTS = ("workspace", "standoff", "field_of_view", "velocity", "acceleration", "end")


class CellLimits(eqx.Module):
    """Limits of the camera robot and the cell (SI units, radians).

    Attributes:
        workspace_lo, workspace_hi: (3,) corners of the reachable box [m].
        standoff: (2,) allowed distance to the workpiece point [m].
        half_fov: half of the camera's (smaller) field of view [rad].
        fov_margin: margin kept inside the field of view [rad].
        max_velocity [m/s], max_acceleration [m/s^2]: camera-centre limits.
        end_offset: (3,) camera position relative to the last predicted point [m].
        end_tolerance: allowed distance from that end position [m].
    """

    workspace_lo: Float[Array, " 3"] = eqx.field(converter=jnp.asarray)
    workspace_hi: Float[Array, " 3"] = eqx.field(converter=jnp.asarray)
    standoff: Float[Array, " 2"] = eqx.field(converter=jnp.asarray, default=(0.5, 1.5))
    half_fov: Float[ArrayLike, ""] = 0.33
    fov_margin: Float[ArrayLike, ""] = 0.05
    max_velocity: Float[ArrayLike, ""] = 1.0
    max_acceleration: Float[ArrayLike, ""] = 4.0
    end_offset: Float[Array, " 3"] = eqx.field(converter=jnp.asarray, default=(0.0, 0.0, 0.6))
    end_tolerance: Float[ArrayLike, ""] = 0.05


def safe_norm(x: Array, axis: int = -1) -> Array:
    """Euclidean norm with a finite gradient at zero (double-where trick)."""
    sq = jnp.sum(x * x, axis=axis)
    zero = sq == 0
    return jnp.where(zero, 0.0, jnp.sqrt(jnp.where(zero, 1.0, sq)))


def _off_axis(R_c_w, t_c_w, x):
    """Angle between the optical axis and the ray to world point x [rad]."""
    xc = jnp.sum(R_c_w * x, axis=1) + t_c_w  # R x as a sum: fuses under vmap
    return jnp.arctan2(safe_norm(xc[:2]), xc[2])


def constraint_values(
    model: CameraPathModel,
    theta: Float[ArrayLike, "k 3"],
    limits: CellLimits,
    predicted: Float[ArrayLike, "F 3"],
    samples: Float[ArrayLike, "S F 3"],
) -> dict[str, Array]:
    """Normalised constraint values per constraint (arrays; feasible where ``<= 0``)."""
    theta = jnp.asarray(theta)
    dtype = theta.dtype
    predicted = jnp.asarray(predicted, dtype)
    c_grid = model.centres(theta, model.grid)
    lo, hi = jnp.asarray(limits.workspace_lo, dtype), jnp.asarray(limits.workspace_hi, dtype)
    size = hi - lo
    workspace = jnp.concatenate([(lo - c_grid) / size, (c_grid - hi) / size], axis=1)
    d = jnp.linalg.norm(model.centres(theta) - predicted, axis=1)
    d_lo, d_hi = limits.standoff[0], limits.standoff[1]
    standoff = jnp.stack([(d_lo - d) / d_lo, (d - d_hi) / d_hi], axis=1)
    R, t = model.poses(theta, predicted)
    ang = jax.vmap(lambda x: jax.vmap(_off_axis)(R, t, x))(jnp.asarray(samples, dtype))
    allowed = limits.half_fov - limits.fov_margin
    fov = ang / allowed - 1.0
    v = safe_norm(model.velocity(theta), axis=1)
    a = safe_norm(model.acceleration(theta), axis=1)
    end_target = predicted[-1] + jnp.asarray(limits.end_offset, dtype)
    end = safe_norm(model.centres(theta)[-1] - end_target) / limits.end_tolerance - 1.0
    return {
        "workspace": workspace,
        "standoff": standoff,
        "field_of_view": fov,
        "velocity": v / limits.max_velocity - 1.0,
        "acceleration": a / limits.max_acceleration - 1.0,
        "end": jnp.reshape(end, (1,)),
    }


def penalty(values: dict[str, Array]) -> Float[Array, ""]:
    """Sum of squared violations ``sum max(g, 0)^2`` (continuously differentiable)."""
    return sum(jnp.sum(jnp.square(jnp.maximum(g, 0.0))) for g in values.values())

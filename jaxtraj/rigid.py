"""Rigid-body helpers: the 6-DoF workpiece pose from reconstructed reference points.

Rotations and poses elsewhere in the library use ``jaxlie`` (SO3/SE3 with exp/log maps
and quaternions in (w, x, y, z) order, the library's convention).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._checks import check_shape

__all__ = ["fit_rigid"]


def fit_rigid(
    model_points: Float[ArrayLike, "M 3"],
    observed_points: Float[ArrayLike, "*F M 3"],
    weights: Float[ArrayLike, " M"] | None = None,
) -> tuple[Float[Array, "*F 3 3"], Float[Array, "*F 3"]]:
    """Least-squares rigid fit ``observed ~ R model + t`` (Kabsch / Umeyama, no scale).

    Needs M >= 3 non-collinear points. ``observed_points`` may carry leading frame axes
    (F, M, 3): the fit is then done for every frame (vectorised), giving R (F, 3, 3) and
    t (F, 3). The reflection case is corrected so that ``det R = +1``.

    Args:
        model_points: (M, 3) reference points in the object frame [m].
        observed_points: (..., M, 3) the same points measured in the world frame [m].
        weights: optional (M,) non-negative weights per point.

    Returns:
        ``(R, t)`` with ``observed = R @ model + t`` in the least-squares sense, i.e. the
        pose ``T_w_o`` of the object frame.
    """
    check_shape("model_points", model_points, (None, 3), "(M, 3) points in the object frame")
    M = jnp.shape(model_points)[0]
    if M < 3:
        raise ValueError(f"model_points: need at least 3 reference points, got {M}")
    shape = jnp.shape(observed_points)
    if len(shape) < 2 or shape[-2:] != (M, 3):
        raise ValueError(
            f"observed_points: expected shape (..., {M}, 3) matching model_points, got {shape}"
        )
    obs = jnp.asarray(observed_points)
    dtype = jnp.result_type(obs.dtype, jnp.float32)
    obs = obs.astype(dtype)
    mod = jnp.asarray(model_points, dtype)
    w = jnp.ones(M, dtype) if weights is None else jnp.asarray(weights, dtype)
    if weights is not None:
        check_shape("weights", weights, (M,), "one weight per reference point")
    w = w / jnp.sum(w)
    mu_m = w @ mod
    mu_o = jnp.einsum("m,...mi->...i", w, obs)
    cov = jnp.einsum("m,...mi,mj->...ij", w, obs - mu_o[..., None, :], mod - mu_m)
    U, _, Vt = jnp.linalg.svd(cov)
    sign = jnp.sign(jnp.linalg.det(U @ Vt))
    sign = jnp.where(sign == 0, 1.0, sign)
    D = jnp.ones((*sign.shape, 3), dtype).at[..., 2].set(sign)
    R = (U * D[..., None, :]) @ Vt
    t = mu_o - jnp.einsum("...ij,j->...i", R, mu_m)
    return R, t

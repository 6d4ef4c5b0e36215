"""Helpers shared by the estimators: camera normalisation, projection, robust losses,
and host-side validation with messages that name the argument."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._checks import check_shape, check_tracks, is_concrete
from .._linalg import det3

LOSSES = ("l2", "huber", "cauchy")


def normalise_cameras(P: Float[Array, "F 3 4"]) -> Float[Array, "F 3 4"]:
    """Scale each P so that ``||p3[:3]|| = 1`` and ``det P[:, :3] > 0``.

    Then ``p3 . [X; 1]`` is the depth of X in front of the camera, and the algebraic
    residual ``Q_i X - q_i`` equals depth times the reprojection error in pixels.
    """
    s = jnp.sign(det3(P[:, :, :3]))
    s = jnp.where(s == 0, 1.0, s)
    n = jnp.linalg.norm(P[:, 2, :3], axis=-1)
    return P * (s / n)[:, None, None]


def homogeneous(P: Float[Array, "F 3 4"], X: Float[Array, "F 3"]) -> Float[Array, "F 3"]:
    return jnp.sum(P[:, :, :3] * X[:, None, :], axis=2) + P[:, :, 3]


def linearise(P, uv, X):
    """Reprojection residual ``e = pi(P X) - uv`` (F, 2), its Jacobian (F, 2, 3), depth."""
    h = homogeneous(P, X)
    z = h[:, 2]
    tiny = jnp.finfo(P.dtype).eps
    z_safe = jnp.where(jnp.abs(z) > tiny, z, tiny)
    pi = h[:, :2] / z_safe[:, None]
    J = (P[:, :2, :3] - pi[:, :, None] * P[:, 2:3, :3]) / z_safe[:, None, None]
    return pi - uv, J, z


def gauss_newton_blocks(P, uv, ww, X):
    """Per-frame normal equations of the reprojection error linearised at ``X`` (F, 3),
    weighted by ``ww`` (F,) [1/px^2]: ``H`` (F, 3, 3), ``g`` (F, 3), ``c`` with
    ``J p ~ J X - e``, and ``e``, ``J`` themselves."""
    e, J, _ = linearise(P, uv, X)
    # broadcast-and-sums: under vmap over points, einsums over axes of size 2-3 become
    # batched products of tiny matrices, which XLA:CPU runs far slower than a fused loop
    H = ww[:, None, None] * jnp.sum(J[:, :, :, None] * J[:, :, None, :], axis=1)
    target = jnp.sum(J * X[:, None, :], axis=2) - e
    g = ww[:, None] * jnp.sum(J * target[:, :, None], axis=1)
    c = jnp.sum(ww * jnp.sum(target * target, axis=1))
    return H, g, c, e, J


def algebraic_blocks(P, uv):
    """The ray constraints ``(Q (F, 2, 3), q (F, 2))`` of paper eq. 4."""
    rows = P[:, :2, :] - uv[:, :, None] * P[:, 2:3, :]
    return rows[:, :, :3], -rows[:, :, 3]


def rho(s, loss: str, scale):
    """Robust loss of a squared residual norm ``s`` [px^2] (``l2``: ``s`` itself)."""
    if loss == "l2":
        return s
    c2 = scale * scale
    if loss == "huber":
        r = jnp.sqrt(jnp.where(s > c2, s, c2))
        return jnp.where(s > c2, 2.0 * scale * r - c2, s)
    return c2 * jnp.log1p(s / c2)


def rho_weight(s, loss: str, scale):
    """IRLS weight ``rho'(s)`` (1 for ``l2``)."""
    if loss == "l2":
        return jnp.ones_like(s)
    c2 = scale * scale
    if loss == "huber":
        r = jnp.sqrt(jnp.where(s > c2, s, c2))
        return jnp.where(s > c2, scale / r, 1.0)
    return 1.0 / (1.0 + s / c2)


def as_float(P, *xs):
    P = jnp.asarray(P)
    dtype = jnp.result_type(P.dtype, jnp.float32)
    return (P.astype(dtype), *(None if x is None else jnp.asarray(x, dtype) for x in xs))


def validate_track(P, uv, times=None, weights=None) -> None:
    """Shape/value checks for one trajectory's cameras, pixels, times and weights."""
    check_shape("P", P, (None, 3, 4), "one 3x4 projection matrix per frame")
    F = np.shape(P)[0]
    check_shape("uv", uv, (F, 2), f"one pixel per frame of P, F={F}")
    if times is not None:
        check_shape("times", times, (F,), f"one timestamp per frame, F={F}")
        if is_concrete(times):
            t = np.asarray(times)
            if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
                raise ValueError("times: must be finite and strictly increasing")
    if weights is not None:
        check_shape("weights", weights, (F,), "one non-negative weight per frame")
    if is_concrete(P) and not np.all(np.isfinite(np.asarray(P))):
        raise ValueError("P: projection matrices must be finite")
    check_tracks(uv, weights)


def check_loss(loss: str, scale) -> None:
    if loss not in LOSSES:
        raise ValueError(f"loss: expected one of {LOSSES}, got {loss!r}")
    if is_concrete(scale) and not float(scale) > 0:
        raise ValueError(f"loss_scale: expected a positive threshold in pixels, got {scale}")


def check_positive(name: str, value, what: str) -> None:
    if value is not None and is_concrete(value):
        v = np.asarray(value)
        if not np.all(np.isfinite(v)) or np.any(v <= 0):
            raise ValueError(f"{name}: expected {what} > 0, got {value}")

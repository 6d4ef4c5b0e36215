"""Per-frame ray constraints of the paper (eq. 4-6) and their explicit block forms.

For a camera with projection matrix ``P`` (rows ``p1, p2, p3``) and pixel ``(x, y)``,
every point ``T`` on the viewing ray satisfies (paper eq. 4)::

    Q_i T = q_i,   Q_i = [p1[:3] - x p3[:3]; p2[:3] - y p3[:3]],
                   q_i = [x p3[3] - p1[3]; y p3[3] - p2[3]].

Stacking all frames gives the block-diagonal system ``Q T = q`` (eq. 5) and, with
``T = Theta beta`` and ``Theta = Phi (x) I_3``, the least-squares problem of eq. 6.
The dense forms here are for teaching and small reference checks; the solver never
builds them (see :mod:`jaxtraj.solve`).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

__all__ = ["block_diagonal_Q", "ray_constraints", "theta_matrix", "trajectory_from_coeffs"]


def ray_constraints(
    P: Float[ArrayLike, "F 3 4"], uv: Float[ArrayLike, "F 2"]
) -> tuple[Float[Array, "F 2 3"], Float[Array, "F 2"]]:
    """The per-frame constraints ``(Q, q)`` of eq. 4, shapes (F, 2, 3) and (F, 2)."""
    P = jnp.asarray(P)
    uv = jnp.asarray(uv, P.dtype)
    p3 = P[:, 2, :]  # (F, 4)
    rows = P[:, :2, :] - uv[:, :, None] * p3[:, None, :]  # (F, 2, 4)
    return rows[:, :, :3], -rows[:, :, 3]


def block_diagonal_Q(Q: Float[ArrayLike, "F 2 3"]) -> Float[Array, "2F 3F"]:
    """The dense block-diagonal (2F, 3F) matrix of eq. 5 (small problems only)."""
    Q = jnp.asarray(Q)
    F = Q.shape[0]
    eye = jnp.eye(F, dtype=Q.dtype)
    return jnp.einsum("fg,fab->fagb", eye, Q).reshape(2 * F, 3 * F)


def theta_matrix(basis: Float[ArrayLike, "F k"]) -> Float[Array, "3F 3k"]:
    """``Theta = Phi (x) I_3`` (eq. 6), acting on coefficients flattened row-major (k, 3)."""
    basis = jnp.asarray(basis)
    return jnp.kron(basis, jnp.eye(3, dtype=basis.dtype))


def trajectory_from_coeffs(
    basis: Float[ArrayLike, "F k"], coeffs: Float[ArrayLike, "k 3"]
) -> Float[Array, "F 3"]:
    """Points ``T_i = sum_u Phi[i, u] beta_u`` of a trajectory with coefficients (k, 3)."""
    return jnp.asarray(basis) @ jnp.asarray(coeffs)

"""Forward kinematics of a serial chain in JAX (jit, vmap and grad), and its Jacobian.

For joint ``i`` with fixed origin ``O_i``, unit axis ``a_i`` and value ``q_i``:

    T_base_tip(q) = O_1 M_1(q_1) O_2 M_2(q_2) ... O_n M_n(q_n) T_tip,

``M_i`` the rotation by ``q_i`` about ``a_i`` (Rodrigues, revolute) or the translation
``q_i a_i`` (prismatic). The camera pose of a robot-carried camera is
``T_w_c = T_w_base FK(q) T_f_c`` (DESIGN 5b), :func:`camera_pose`.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._linalg import matmul_small
from .chain import KinematicChain

__all__ = ["axis_rotation", "camera_pose", "forward_kinematics", "jacobian", "joint_frames"]


def axis_rotation(axis: Float[Array, " 3"], angle: Float[ArrayLike, ""]) -> Float[Array, "3 3"]:
    """Rotation matrix by ``angle`` [rad] about the unit ``axis`` (Rodrigues' formula)."""
    x, y, z = axis[0], axis[1], axis[2]
    zero = jnp.zeros_like(x)
    K = jnp.stack([jnp.stack([zero, -z, y]), jnp.stack([z, zero, -x]), jnp.stack([-y, x, zero])])
    s, c = jnp.sin(angle), jnp.cos(angle)
    return jnp.eye(3, dtype=K.dtype) + s * K + (1.0 - c) * (K @ K)


def _motion(kind: str, axis, q):
    """(4, 4) joint motion ``M(q)``."""
    dtype = axis.dtype
    if kind == "revolute":
        top = jnp.concatenate([axis_rotation(axis, q), jnp.zeros((3, 1), dtype)], axis=1)
    else:
        top = jnp.concatenate([jnp.eye(3, dtype=dtype), (q * axis)[:, None]], axis=1)
    return jnp.concatenate([top, jnp.asarray([[0.0, 0.0, 0.0, 1.0]], dtype)], axis=0)


def joint_frames(chain: KinematicChain, q: Float[ArrayLike, " n"]) -> Float[Array, "n+1 4 4"]:
    """Poses in the base frame of every joint's moving frame and, last, of the tip.

    Row ``i`` (< n) is ``T_base_i = O_1 M_1 ... O_i M_i``; its rotation maps the joint's
    axis to the base frame. Row ``n`` is the tip (flange), ``forward_kinematics``.
    """
    q = jnp.asarray(q, chain.origins.dtype)
    frames = []
    T = jnp.eye(4, dtype=chain.origins.dtype)
    # n is static and small (6): unrolled; 4x4 products as broadcast-and-sums, which fuse
    # under vmap over many configurations (a path's grid) where ``@`` would not
    for i, kind in enumerate(chain.joint_types):
        T = matmul_small(matmul_small(T, chain.origins[i]), _motion(kind, chain.axes[i], q[i]))
        frames.append(T)
    frames.append(matmul_small(T, chain.tip))
    return jnp.stack(frames)


def forward_kinematics(chain: KinematicChain, q: Float[ArrayLike, " n"]) -> Float[Array, "4 4"]:
    """Tip (flange) pose ``T_base_f`` (4, 4) of the configuration ``q`` (n,) [rad, m].

    Batched over configurations with ``jax.vmap``; differentiable in ``q``.
    """
    return joint_frames(chain, q)[-1]


def camera_pose(
    chain: KinematicChain,
    q: Float[ArrayLike, " n"],
    T_f_c: Float[ArrayLike, "4 4"] | None = None,
    T_w_base: Float[ArrayLike, "4 4"] | None = None,
) -> Float[Array, "4 4"]:
    """Camera pose ``T_w_c = T_w_base FK(q) T_f_c`` (4, 4); identities where omitted."""
    T = forward_kinematics(chain, q)
    if T_w_base is not None:
        T = jnp.asarray(T_w_base, T.dtype) @ T
    if T_f_c is not None:
        T = T @ jnp.asarray(T_f_c, T.dtype)
    return T


def jacobian(chain: KinematicChain, q: Float[ArrayLike, " n"]) -> Float[Array, "6 n"]:
    """Geometric Jacobian (6, n) of the tip in the base frame: rows 0-2 the tip origin's
    linear velocity, rows 3-5 the angular velocity, per unit joint speed.

    Revolute joint ``i`` with world axis ``z_i`` through ``p_i``: ``[z_i x (p_tip - p_i);
    z_i]``; prismatic: ``[z_i; 0]``.
    """
    frames = joint_frames(chain, q)
    p_tip = frames[-1, :3, 3]
    cols = []
    for i, kind in enumerate(chain.joint_types):
        z = frames[i, :3, :3] @ chain.axes[i]
        if kind == "revolute":
            cols.append(jnp.concatenate([jnp.cross(z, p_tip - frames[i, :3, 3]), z]))
        else:
            cols.append(jnp.concatenate([z, jnp.zeros_like(z)]))
    return jnp.stack(cols, axis=1)

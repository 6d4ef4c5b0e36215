"""Small dense linear algebra written out step by step (matrices up to about 16x16).

Inside a ``lax.scan`` a LAPACK call is a library call that XLA:CPU must dispatch on its
own at every step. A loop that makes no such call can be compiled into one native kernel
(see :mod:`jaxtraj._xla`), which for the small blocks of the smoothers and filters is
several times faster. Results equal LAPACK's up to rounding. The Python loops unroll into
one step per column or row, so keep these for small, static sizes. Products are written as
broadcast-and-sums, which stay fused loops under ``vmap`` (``@`` would become batched
products of tiny matrices).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = ["cholesky_small", "det3", "matmul_small", "solve_spd_small", "solve_triangular_small"]


def cholesky_small(A: Float[Array, "s s"]) -> Float[Array, "s s"]:
    """Lower Cholesky factor of a small SPD matrix, one column per step (NaN if not
    positive definite, as LAPACK's result under JAX)."""
    s = A.shape[-1]
    rows = jnp.arange(s)
    L = jnp.zeros_like(A)
    for j in range(s):
        v = A[:, j] - jnp.sum(L * L[j], axis=1)  # columns >= j of L are still zero
        d = jnp.sqrt(v[j])
        L = L.at[:, j].set(jnp.where(rows > j, v / d, jnp.where(rows == j, d, 0.0)))
    return L


def solve_triangular_small(C: Float[Array, "s s"], B: Array, *, trans: int = 0) -> Array:
    """Solve ``C x = B`` (``trans=0``) or ``C^T x = B`` (``trans=1``) for lower-triangular
    ``C``; ``B`` is (s,) or (s, m). One row of ``x`` per step."""
    s = C.shape[-1]
    M = C if trans == 0 else C.T
    x = jnp.zeros_like(B)
    for i in range(s) if trans == 0 else range(s - 1, -1, -1):
        row = M[i].reshape((s,) + (1,) * (x.ndim - 1))
        x = x.at[i].set((B[i] - jnp.sum(row * x, axis=0)) / M[i, i])  # unknown rows are 0
    return x


def solve_spd_small(A: Float[Array, "s s"], B: Array) -> Array:
    """``A^-1 B`` for a small symmetric positive definite ``A`` by its Cholesky factor."""
    L = cholesky_small(A)
    return solve_triangular_small(L, solve_triangular_small(L, B), trans=1)


def det3(M: Float[Array, "*b 3 3"]) -> Float[Array, " *b"]:
    """Determinants of 3x3 matrices (any leading axes) as triple products of their rows:
    ``jnp.linalg.det`` is an LU factorisation, a batched LAPACK call over the leading axes."""
    return jnp.sum(M[..., 0, :] * jnp.cross(M[..., 1, :], M[..., 2, :]), axis=-1)


def matmul_small(A: Float[Array, "*b m k"], B: Float[Array, "*b k n"]) -> Float[Array, "*b m n"]:
    """``A @ B`` for small matrices (any broadcast leading axes) as a broadcast-and-sum.

    Under ``vmap``, ``@`` on 3x3 or 4x4 blocks becomes a batched matrix product, which
    XLA:CPU runs as many tiny GEMM calls; this form fuses into one loop. Measured on the
    joint-path constraints (forward kinematics of 8 x 591 configurations with gradient):
    30 -> 12 ms.
    """
    return jnp.sum(A[..., :, :, None] * B[..., None, :, :], axis=-2)

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

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._spd import _unrolled as _bordering

__all__ = [
    "cholesky_small",
    "det3",
    "inverse_cholesky_small",
    "matmul_small",
    "solve_spd_small",
    "solve_triangular_small",
]


@jax.custom_jvp
def cholesky_small(A: Float[Array, "s s"]) -> Float[Array, "s s"]:
    """Lower Cholesky factor of a small SPD matrix, one column per step (NaN if not
    positive definite, as LAPACK's result under JAX). Only the lower triangle of ``A`` is
    read. Differentiated by the analytic rule ``dL = L Phi(L^-1 dA L^-T)`` (``Phi``: the
    strict lower triangle plus half the diagonal; ``dA`` is the symmetric matrix of its
    lower triangle), whose products transpose into products: differentiating the unrolled
    column steps instead made the smoother's design objective (value and gradient at a
    fixed density, with :func:`solve_triangular_small`'s rule) 1.7x as slow."""
    return _cholesky_steps(A)


@cholesky_small.defjvp
def _cholesky_small_jvp(primals, tangents):
    (A,), (dA,) = primals, tangents
    L = _cholesky_steps(A)
    dA = jnp.tril(dA) + jnp.tril(dA, -1).T  # the symmetric matrix of the lower triangle
    return L, matmul_small(L, _phi_congruence(_lower_inverse(L), dA))


def _phi_congruence(W, dA):
    """``Phi(W dA W^T)``: the strict lower triangle plus half the diagonal (the factor
    rules' common part)."""
    s = W.shape[-1]
    phi = jnp.tril(jnp.ones((s, s), W.dtype), -1) + 0.5 * jnp.eye(s, dtype=W.dtype)
    return matmul_small(matmul_small(W, dA), W.T) * phi


def _cholesky_steps(A):
    s = A.shape[-1]
    rows = jnp.arange(s)
    L = jnp.zeros_like(A)
    for j in range(s):
        v = A[:, j] - jnp.sum(L * L[j], axis=1)  # columns >= j of L are still zero
        d = jnp.sqrt(v[j])
        L = L.at[:, j].set(jnp.where(rows > j, v / d, jnp.where(rows == j, d, 0.0)))
    return L


@jax.custom_jvp
def inverse_cholesky_small(A: Float[Array, "s s"]) -> Float[Array, "s s"]:
    """``W = L^-1`` (lower triangular) of ``A = L L^T`` for a small SPD matrix, one row per
    step (bordering: with ``W_i`` the inverse factor of the leading ``i x i`` block, row i
    of ``L`` is ``l = W_i a``, ``a = A[:i, i]``, its pivot ``d = sqrt(A_ii - l.l)`` and row i
    of ``W`` is ``[-(l^T W_i) / d, 1 / d]``). NaN if not positive definite, as
    :func:`cholesky_small`; only the upper triangle of ``A`` is read.

    With the inverse factor every later solve with ``A``'s factor is a product, so a
    recursion that solves several times with one block (the block-tridiagonal factor of
    :mod:`jaxtraj.estimators._blocktri`) unrolls one loop per block instead of one per
    solve, and differentiates through products. Differentiated by ``dW = -Phi(W dA W^T) W``
    (``Phi`` as in :func:`cholesky_small`).
    """
    return _inverse_cholesky_steps(A)


@inverse_cholesky_small.defjvp
def _inverse_cholesky_small_jvp(primals, tangents):
    (A,), (dA,) = primals, tangents
    W = _inverse_cholesky_steps(A)
    dA = jnp.triu(dA) + jnp.triu(dA, 1).T  # the symmetric matrix of the upper triangle
    return W, -matmul_small(_phi_congruence(W, dA), W)


def _inverse_cholesky_steps(A):
    # the bordering steps of the batched solvers' factor, without their pivot clamp
    return _bordering(A, jnp.diagonal(A), clamp=False)


def solve_triangular_small(C: Float[Array, "s s"], B: Array, *, trans: int = 0) -> Array:
    """Solve ``C x = B`` (``trans=0``) or ``C^T x = B`` (``trans=1``) for lower-triangular
    ``C`` (its upper triangle is not read); ``B`` is (s,) or (s, m). One row of ``x`` per
    step. Differentiated analytically, ``dx = C^-1 (dB - dC x)`` (transposed for
    ``trans=1``), as :func:`cholesky_small`."""
    return _solve_triangular(C, B, trans == 1)


def _apply(M, r):
    """``M @ r`` for (s, s) ``M`` and ``r`` of shape (s, ...), as a broadcast-and-sum."""
    s = M.shape[-1]
    return jnp.sum(M.reshape((s, s) + (1,) * (r.ndim - 1)) * r[None], axis=1)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def _solve_triangular(C, B, transposed: bool):
    return _triangular_steps(C, B, trans=int(transposed))


@_solve_triangular.defjvp
def _solve_triangular_jvp(transposed, primals, tangents):
    (C, B), (dC, dB) = primals, tangents
    x = _triangular_steps(C, B, trans=int(transposed))
    Cinv = _lower_inverse(C)
    dC = jnp.tril(dC)
    if transposed:  # C^T x = B: dx = C^-T (dB - dC^T x)
        return x, _apply(Cinv.T, dB - _apply(dC.T, x))
    return x, _apply(Cinv, dB - _apply(dC, x))


def _lower_inverse(C):
    """``C^-1`` of a small lower-triangular ``C`` (for the derivative rules)."""
    return _triangular_steps(C, jnp.eye(C.shape[-1], dtype=C.dtype))


def _triangular_steps(C, B, *, trans: int = 0):
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

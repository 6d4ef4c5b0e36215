"""Symmetric positive-definite block-tridiagonal systems, solved in O(F s^3).

The normal matrix of a trajectory with a Markov (state-space) prior is block tridiagonal:
diagonal blocks ``D_i`` (F, s, s) and sub-diagonal blocks ``E_i = A[i+1, i]``
(F-1, s, s). A block Cholesky factorisation ``A = L L^T`` with diagonal blocks ``C_i``
and sub-diagonal blocks ``M_i`` is a forward ``lax.scan``; the solve is one forward and
one backward scan; the diagonal blocks of ``A^-1`` (the posterior covariances, as in a
Rauch-Tung-Striebel smoother) come from a second backward scan::

    C_0 C_0^T = D_0,   M_i = E_i C_i^-T,   C_{i+1} C_{i+1}^T = D_{i+1} - M_i M_i^T
    S_i = C_i^-T C_i^-1 + K_i S_{i+1} K_i^T,   K_i = C_i^-T M_i^T

The factor keeps the inverse diagonal blocks ``W_i = C_i^-1``
(:func:`jaxtraj._linalg.inverse_cholesky_small`), so that every solve with a block is a
product: one unrolled loop per block instead of one per triangular solve, and derivatives
through products. On the smoother's design objective (value and gradient, F = 60, order 2)
this took 1.10-1.19 -> 0.93 ms and its compilation 4.6-4.8 -> 2.9-3.0 s against
triangular solves with ``C_i`` (README, issue 21).

No dense (F s, F s) matrix is ever formed, and no LAPACK call is made.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._linalg import inverse_cholesky_small as _inverse_cholesky
from .._linalg import matmul_small as mm
from .._spd import matvec, vecmat


class BlockCholesky(eqx.Module):
    """Factor of a block-tridiagonal matrix: the inverse diagonal blocks ``W = C^-1``
    (F, s, s) lower, and ``M`` (F-1, s, s)."""

    W: Float[Array, "F s s"]
    M: Float[Array, "Fm1 s s"]


def factor_forward(
    D: Float[Array, "F s s"], E: Float[Array, "Fm1 s s"], b: Float[Array, "F s"]
) -> tuple[BlockCholesky, Float[Array, "F s"]]:
    """Block Cholesky factor of the matrix (diagonal ``D``, sub-diagonal ``E``) and the
    forward substitution ``y = L^-1 b``, in one scan."""
    W0 = _inverse_cholesky(D[0])
    y0 = matvec(W0, b[0])

    def step(carry, inputs):
        W_prev, y_prev = carry
        D_i, E_prev, b_i = inputs
        M = mm(E_prev, W_prev.T)  # M = E C_prev^-T
        W = _inverse_cholesky(D_i - mm(M, M.T))
        y = matvec(W, b_i - matvec(M, y_prev))
        return (W, y), (W, M, y)

    _, (Ws, Ms, ys) = jax.lax.scan(step, (W0, y0), (D[1:], E, b[1:]))
    chol = BlockCholesky(W=jnp.concatenate([W0[None], Ws]), M=Ms)
    return chol, jnp.concatenate([y0[None], ys])


def back_substitute(chol: BlockCholesky, y: Float[Array, "F s"]) -> Float[Array, "F s"]:
    """Solve ``L^T x = y`` (the second half of a solve)."""
    W, M = chol.W, chol.M
    xl = vecmat(y[-1], W[-1])

    def bwd(x_next, inputs):
        W_i, M_i, y_i = inputs
        x = vecmat(y_i - vecmat(x_next, M_i), W_i)
        return x, x

    _, xs = jax.lax.scan(bwd, xl, (W[:-1], M, y[:-1]), reverse=True)
    return jnp.concatenate([xs, xl[None]])


def factor(D: Float[Array, "F s s"], E: Float[Array, "Fm1 s s"]) -> BlockCholesky:
    """Block Cholesky factor of the matrix with diagonal ``D`` and sub-diagonal ``E``."""
    return factor_forward(D, E, jnp.zeros(D.shape[:2], D.dtype))[0]


def solve(chol: BlockCholesky, b: Float[Array, "F s"]) -> Float[Array, "F s"]:
    """Solve ``A x = b`` with the block Cholesky factor of ``A``."""
    W, M = chol.W, chol.M
    y0 = matvec(W[0], b[0])

    def fwd(y_prev, inputs):
        W_i, M_prev, b_i = inputs
        y = matvec(W_i, b_i - matvec(M_prev, y_prev))
        return y, y

    _, ys = jax.lax.scan(fwd, y0, (W[1:], M, b[1:]))
    return back_substitute(chol, jnp.concatenate([y0[None], ys]))


def _inverse_parts(chol: BlockCholesky) -> tuple[Array, Array]:
    """``own_i = C_i^-T C_i^-1`` (F, s, s) and ``K_i = C_i^-T M_i^T`` (F-1, s, s): the
    off-diagonal blocks of ``A^-1`` are ``G_ij = -K_i G_i+1,j`` (``i < j``)."""
    W, M = chol.W, chol.M
    WT = jnp.swapaxes(W, 1, 2)
    # small products as broadcast-and-sums (see matmul_small): under vmap and reverse-mode
    # differentiation einsums here met an XLA shape-verifier error (jax 0.9.2)
    return mm(WT, W), mm(WT[:-1], jnp.swapaxes(M, 1, 2))


def _diag_inverse(own: Array, K: Array) -> Array:
    def bwd(S_next, inputs):
        own_i, K_i = inputs
        S = own_i + mm(mm(K_i, S_next), K_i.T)
        S = 0.5 * (S + S.T)
        return S, S

    _, Ss = jax.lax.scan(bwd, own[-1], (own[:-1], K), reverse=True)
    return jnp.concatenate([Ss, own[-1][None]])


def diag_inverse(chol: BlockCholesky) -> Float[Array, "F s s"]:
    """The diagonal blocks of ``A^-1`` (selected inversion, O(F s^3))."""
    return _diag_inverse(*_inverse_parts(chol))


def diag_sandwich(chol: BlockCholesky, H: Float[Array, "F r r"]) -> Float[Array, "F s s"]:
    """Diagonal blocks of ``A^-1 H A^-1`` for block-diagonal ``H`` (its blocks ``H_j``
    (r <= s) act on the first r components of each state), in O(F s^3).

    With ``S_i`` the diagonal blocks of ``A^-1`` (:func:`diag_inverse`) and its
    off-diagonal blocks ``G_ij = -K_i G_i+1,j`` (``i < j``, ``K_i = C_i^-T M_i^T``), block
    i of the sandwich is ``S_i (H_i + P_i) S_i + N_i`` with the frames before i summed
    forward, ``P_i+1 = K_i^T (H_i + P_i) K_i``, and those after summed backward,
    ``N_i = K_i (S_i+1 H_i+1 S_i+1 + N_i+1) K_i^T`` (the signs cancel in pairs). This is
    the noise covariance of a linear smoother's estimate (``A^-1 J^T W eps``), which 2F
    solves gave in O(F^2 s^2).
    """
    own, K = _inverse_parts(chol)
    S = _diag_inverse(own, K)
    F, s, _ = S.shape
    r = H.shape[-1]
    Hs = jnp.zeros((F, s, s), S.dtype).at[:, :r, :r].set(H)
    Kt = jnp.swapaxes(K, 1, 2)
    zero = jnp.zeros((s, s), S.dtype)

    def fwd(P_i, inputs):
        H_i, K_i, Kt_i = inputs
        P_next = mm(mm(Kt_i, H_i + P_i), K_i)
        return P_next, P_next

    _, Ps = jax.lax.scan(fwd, zero, (Hs[:-1], K, Kt))
    P = jnp.concatenate([zero[None], Ps])
    SHS = mm(mm(S, Hs), S)

    def bwd(N_next, inputs):
        SHS_next, K_i, Kt_i = inputs
        N = mm(mm(K_i, SHS_next + N_next), Kt_i)
        return N, N

    _, Ns = jax.lax.scan(bwd, zero, (SHS[1:], K, Kt), reverse=True)
    return mm(mm(S, Hs + P), S) + jnp.concatenate([Ns, zero[None]])


def logdet(chol: BlockCholesky) -> Float[Array, ""]:
    """``log det A`` from the factor."""
    return -2.0 * jnp.sum(jnp.log(jnp.diagonal(chol.W, axis1=1, axis2=2)))


def min_pivot_ratio(chol: BlockCholesky, D: Float[Array, "F s s"]) -> Float[Array, ""]:
    """``min_j C_jj^2 / D_jj``: near 0 when the system is (numerically) singular."""
    piv = 1.0 / jnp.diagonal(chol.W, axis1=1, axis2=2) ** 2  # C_jj = 1 / W_jj
    dd = jnp.maximum(jnp.diagonal(D, axis1=1, axis2=2), jnp.finfo(D.dtype).tiny)
    return jnp.min(piv / dd)


def dense(D: Float[Array, "F s s"], E: Float[Array, "Fm1 s s"]) -> Float[Array, "Fs Fs"]:
    """The dense matrix (small problems and tests only)."""
    F, s, _ = D.shape
    A = jnp.zeros((F * s, F * s), D.dtype)
    for i in range(F):
        A = A.at[i * s : (i + 1) * s, i * s : (i + 1) * s].set(D[i])
    for i in range(F - 1):
        A = A.at[(i + 1) * s : (i + 2) * s, i * s : (i + 1) * s].set(E[i])
        A = A.at[i * s : (i + 1) * s, (i + 1) * s : (i + 2) * s].set(E[i].T)
    return A

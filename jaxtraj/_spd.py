"""Symmetric positive-definite algebra for the batched solvers, without LAPACK calls.

Every function works on one small matrix and is written in broadcast-and-sum form, so that
under ``jax.vmap`` (many points sharing cameras) it becomes elementwise operations and
reductions rather than batched matrix-vector products or batched LAPACK calls. jaxlib 0.10
runs batched CPU LAPACK calls on XLA's thread pool, where small ones got slower and vmapped
solves were seen to hang on 2 cores (jax-ml/jax#36927); nothing here makes such a call.

* :func:`inverse_cholesky` - ``W = L^-1`` of ``A = L L^T`` by bordering, so that every
  later solve is two triangular matrix-vector products; its derivative is an analytic
  rule (matrix products), not the bordering steps' own.
* :func:`top_eigenvalue` - the largest eigenvalue of a symmetric positive semi-definite
  operator given as a matrix-vector product: a few Lanczos steps with full
  re-orthogonalisation and a Sturm bisection of the small tridiagonal matrix. Its result
  is a Ritz value, so it never exceeds the true eigenvalue (up to rounding).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = ["inverse_cholesky", "matvec", "top_eigenvalue", "vecmat"]

#: up to this size the bordering steps are unrolled with exact static slices (fewest
#: operations); larger matrices are factorised by blocks of at most this size
UNROLL_MAX = 48


def matvec(M: Float[Array, "m n"], x: Float[Array, " n"]) -> Float[Array, " m"]:
    """``M @ x`` as a broadcast-and-sum (a fused reduction under vmap)."""
    return jnp.sum(M * x[None, :], axis=1)


def vecmat(x: Float[Array, " m"], M: Float[Array, "m n"]) -> Float[Array, " n"]:
    """``x @ M`` (that is ``M^T x``) as a broadcast-and-sum."""
    return jnp.sum(x[:, None] * M, axis=0)


def _pivot(a_ii, ll, eps, ref):
    # Clamp at rounding level (relative to the matrix's own diagonal entry ``ref``) so a
    # (numerically) singular matrix gives a huge but finite inverse instead of NaN; callers
    # judge singularity from the pivots.
    return jnp.sqrt(jnp.maximum(a_ii - ll, eps * jnp.abs(ref)))


def _unrolled(A, ref, clamp: bool = True):
    """The bordering steps unrolled (static slices; only the upper triangle of ``A`` is
    read). ``clamp=False``: no pivot clamp, NaN where ``A`` is not positive definite
    (:func:`jaxtraj._linalg.inverse_cholesky_small`)."""
    n = A.shape[-1]
    eps = jnp.finfo(A.dtype).eps

    def pivot(a_ii, ll, ref_i):
        return _pivot(a_ii, ll, eps, ref_i) if clamp else jnp.sqrt(a_ii - ll)

    W = jnp.zeros_like(A).at[0, 0].set(1.0 / pivot(A[0, 0], 0.0, ref[0]))
    for i in range(1, n):
        Wi = W[:i, :i]
        l = matvec(Wi, A[:i, i])
        d = pivot(A[i, i], jnp.sum(l * l), ref[i])
        row = jnp.concatenate([-vecmat(l, Wi) / d, (1.0 / d)[None]])
        W = jax.lax.dynamic_update_slice(W, row[None, :], (i, 0))
    return W


def _looped(A, ref):
    """:func:`_unrolled` as a ``fori_loop`` over the rows, each step on the whole (masked)
    matrix: about 2x slower than unrolled at 30-48 rows but compiled in a tenth of the
    time; the diagonal blocks of :func:`_blocked`, where it costs little."""
    n = A.shape[-1]
    eps = jnp.finfo(A.dtype).eps
    idx = jnp.arange(n)

    def step(i, W):
        l = matvec(W, jnp.where(idx < i, A[:, i], 0.0))  # rows >= i of W are still zero
        d = _pivot(A[i, i], jnp.sum(l * l), eps, ref[i])
        row = jnp.where(idx == i, 1.0 / d, -vecmat(l, W) / d)
        return jax.lax.dynamic_update_slice(W, row[None, :], (i, 0))

    return jax.lax.fori_loop(0, n, step, jnp.zeros_like(A))


def _blocked(A):
    """Block bordering, ``b <= UNROLL_MAX`` rows at a time (the blocks unrolled, static
    slices): with ``W`` the inverse factor of the leading ``s x s`` block, the next rows of
    ``L`` are ``L21 = A21 W^T``, the block's own factor comes from the Schur complement
    ``A22 - L21 L21^T`` (:func:`_looped`), and its rows of ``W`` are
    ``[-W22 L21 W, W22]``. About ``2 n^3 / 3`` multiply-adds, in matrix products. Measured
    against a ``fori_loop`` over full-width masked blocks (``2 n^3``), 64 matrices: 60 rows
    0.118 -> 0.069 ms each, compiled in 0.6 s instead of 3.0 s; 180 rows 1.63 -> 1.02 ms,
    2.0 s instead of 6.3 s."""
    n = A.shape[-1]
    blocks = -(-n // UNROLL_MAX)
    b = -(-n // blocks)
    W = jnp.zeros_like(A)
    for s in range(0, n, b):
        e = min(s + b, n)
        A22 = A[s:e, s:e]
        if s == 0:
            W = W.at[:e, :e].set(_looped(A22, jnp.diagonal(A22)))
            continue
        W11 = W[:s, :s]
        L21 = A[s:e, :s] @ W11.T
        W22 = _looped(A22 - L21 @ L21.T, jnp.diagonal(A22))
        W = W.at[s:e, :s].set(-(W22 @ L21) @ W11).at[s:e, s:e].set(W22)
    return W


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def inverse_cholesky(A: Float[Array, "n n"], unroll: bool = True) -> Float[Array, "n n"]:
    """Lower-triangular ``W = L^-1`` with ``A = L L^T`` (A symmetric positive definite).

    Bordering: with ``W_i`` the inverse factor of the leading ``i x i`` block, row ``i`` of
    ``L`` is ``l = W_i a`` (``a = A[:i, i]``), its pivot ``d = sqrt(A_ii - l.l)``, and row
    ``i`` of ``W`` is ``[-(l^T W_i) / d, 1 / d]``. ``A^-1 = W^T W``, ``1 / W_ii = L_ii``.
    Pivots below ``eps * A_ii`` are clamped there (singular input: huge, finite ``W``).
    Up to :data:`UNROLL_MAX` rows the steps are unrolled (about ``2 n^3 / 3``
    multiply-adds); larger matrices go by blocks of rows (matrix products, about
    ``2 n^3 / 3`` too, see :func:`_blocked`). ``unroll=False`` runs the steps of a small
    matrix as a loop instead (:func:`_looped`): slower per call, compiled far faster, for
    programs that hold many factorisations.

    Differentiable in forward and reverse mode by an analytic rule (a custom JVP, three
    matrix products; see :func:`_inverse_cholesky_jvp`), not through the bordering steps
    (batched 36 x 36 factors: gradient 31 instead of 450 us each, compiled 3x faster). At
    a clamped pivot the derivative is that of the exact factor (huge).
    """
    if A.shape[-1] > UNROLL_MAX:
        return _blocked(A)
    if unroll:
        return _unrolled(A, jnp.diagonal(A))
    return _looped(A, jnp.diagonal(A))


@inverse_cholesky.defjvp
def _inverse_cholesky_jvp(unroll, primals, tangents):
    # With X = W dL (lower triangular), W dA W^T = X + X^T, so X = Phi(W dA W^T) (the
    # lower triangle, diagonal halved) and dW = -W dL W = -X W: three matrix products
    # instead of differentiating through the n bordering steps (whose derivative cost
    # 10-20x the factor and most of its compile time). A symmetric input is assumed; the
    # tangent is symmetrised.
    (A,), (dA,) = primals, tangents
    W = inverse_cholesky(A, unroll)
    dA = 0.5 * (dA + jnp.swapaxes(dA, -1, -2))
    S = W @ dA @ W.T
    n = A.shape[-1]
    phi = jnp.tril(jnp.ones((n, n), A.dtype), -1) + 0.5 * jnp.eye(n, dtype=A.dtype)
    return W, -(S * phi) @ W


def _sturm_top(alpha: Array, beta: Array, iters: int) -> Array:
    """Largest eigenvalue of the symmetric tridiagonal matrix (diagonal ``alpha`` (m,),
    off-diagonal ``beta`` (m-1,)) by bisection on the Sturm count; the lower end of the
    final bracket (a lower bound)."""
    m = alpha.shape[0]
    tiny = jnp.finfo(alpha.dtype).tiny
    b2 = beta * beta
    ab = jnp.abs(beta)
    radius = jnp.concatenate([ab, jnp.zeros(1, alpha.dtype)]) + jnp.concatenate(
        [jnp.zeros(1, alpha.dtype), ab]
    )
    lo = jnp.max(alpha)  # a Rayleigh quotient of T: below its top eigenvalue
    hi = jnp.maximum(jnp.max(alpha + radius), lo)  # Gershgorin

    def below(x):
        # number of eigenvalues below x (negative pivots of T - x I = L D L^T)
        q = alpha[0] - x
        count = (q < 0).astype(jnp.int32)
        for i in range(1, m):
            q = jnp.where(q == 0, -tiny, q)
            q = alpha[i] - x - b2[i - 1] / q
            count = count + (q < 0)
        return count

    def step(_, bracket):
        lo, hi = bracket
        mid = 0.5 * (lo + hi)
        all_below = below(mid) == m
        return jnp.where(all_below, lo, mid), jnp.where(all_below, mid, hi)

    lo, _ = jax.lax.fori_loop(0, iters, step, (lo, hi))
    return lo


def top_eigenvalue(
    apply: Callable[[Array], Array], v0: Float[Array, " n"], steps: int = 8
) -> Float[Array, ""]:
    """Largest eigenvalue of a symmetric positive semi-definite ``n x n`` operator.

    ``min(steps, n)`` Lanczos steps from ``v0`` (re-orthogonalised against every earlier
    vector, so the tridiagonal matrix is a true Rayleigh-Ritz projection), then bisection of
    its top eigenvalue. The result is at most the true one (up to rounding) and, for
    ``steps >= n``, equal to it; a few steps suffice when the top eigenvalue is separated
    or when the spectrum near it is tight (then every Ritz value there is close).
    """
    n = v0.shape[0]
    m = min(steps, n)
    dtype = v0.dtype
    eps = jnp.finfo(dtype).eps
    q = v0 / jnp.linalg.norm(v0)
    basis, alphas, betas = [q], [], []
    scale = jnp.zeros((), dtype)
    for j in range(m):
        w = apply(q)
        a = jnp.sum(q * w)
        alphas.append(a)
        scale = jnp.maximum(scale, jnp.abs(a))
        if j == m - 1:
            break
        V = jnp.stack(basis)  # (j + 1, n)
        w = w - vecmat(matvec(V, w), V)  # one Gram-Schmidt pass: enough for a few steps
        b = jnp.linalg.norm(w)
        alive = b > 1e3 * eps * scale  # invariant subspace found: stop growing T
        b = jnp.where(alive, b, 0.0)
        betas.append(b)
        q = jnp.where(alive, w / jnp.where(alive, b, 1.0), 0.0)
        basis.append(q)
    alpha = jnp.stack(alphas)
    beta = jnp.stack(betas) if betas else jnp.zeros(0, dtype)
    iters = 24 if dtype == jnp.float64 else 20
    return _sturm_top(alpha, beta, iters)

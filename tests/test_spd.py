"""The LAPACK-free SPD algebra (jaxtraj._spd): the inverse Cholesky factor, unrolled up to
UNROLL_MAX rows (or as a loop over the rows, ``unroll=False``) and by blocks beyond, against
NumPy; singular input; vmap, jit, and its
analytic derivative against differences."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtraj._spd import UNROLL_MAX, inverse_cholesky, top_eigenvalue


def _spd(rng, n, batch=()):
    X = rng.normal(size=(*batch, n, 2 * n))
    return X @ np.swapaxes(X, -1, -2) / n + 1e-3 * np.eye(n)


@pytest.mark.parametrize("unroll", [True, False])
@pytest.mark.parametrize("n", [1, 7, UNROLL_MAX, UNROLL_MAX + 1, 2 * UNROLL_MAX + 5])
def test_inverse_cholesky_equals_the_inverse_of_numpys_factor(n, unroll):
    rng = np.random.default_rng(n)
    A = _spd(rng, n, (3,))
    W = np.asarray(jax.jit(jax.vmap(lambda a: inverse_cholesky(a, unroll)))(jnp.asarray(A)))
    L = np.linalg.cholesky(A)
    np.testing.assert_allclose(W, np.linalg.inv(L), rtol=0, atol=1e-10 * np.abs(W).max())
    assert np.all(np.triu(W, 1) == 0.0)
    # A^-1 = W^T W
    np.testing.assert_allclose(np.swapaxes(W, -1, -2) @ W @ A, np.broadcast_to(np.eye(n), A.shape),
                               rtol=0, atol=1e-9)  # fmt: skip


@pytest.mark.parametrize("n", [5, UNROLL_MAX + 12])
def test_singular_input_gives_a_finite_factor(n):
    rng = np.random.default_rng(1)
    X = rng.normal(size=(n, n - 2))  # rank n - 2
    W = np.asarray(jax.jit(inverse_cholesky)(jnp.asarray(X @ X.T)))
    assert np.all(np.isfinite(W))
    assert np.abs(W).max() > 1e6  # the clamped pivots show up as huge entries


@pytest.mark.parametrize(("n", "unroll"), [(7, True), (7, False), (UNROLL_MAX + 4, True)])
def test_gradient_of_the_factor_matches_differences(n, unroll):
    # the derivative is the analytic rule of inverse_cholesky's custom JVP: the unrolled
    # and the looped (n <= UNROLL_MAX) and the blocked factor, in reverse and forward mode
    rng = np.random.default_rng(2)
    A = jnp.asarray(_spd(rng, n))
    E = jnp.asarray(rng.normal(size=(n, n)))
    E = E + E.T

    @jax.jit
    def f(t):
        W = inverse_cholesky(A + t * E, unroll=unroll)
        return jnp.sum(W[-1] ** 2)  # the last row crosses every block

    g = jax.jit(jax.grad(f))(0.0)
    h = 1e-6
    fd = (f(h) - f(-h)) / (2 * h)
    assert np.isfinite(g) and abs(g - fd) <= 1e-5 * abs(fd)
    assert abs(jax.jacfwd(f)(0.0) - g) <= 1e-10 * abs(g)


def test_gradient_with_respect_to_every_entry_is_symmetric_and_matches_differences():
    # the factor reads a symmetric matrix: its gradient is the symmetric one, and the
    # derivative along a symmetric direction E is <grad, E>
    n = 9
    rng = np.random.default_rng(4)
    A = jnp.asarray(_spd(rng, n))
    C = jnp.asarray(rng.normal(size=(n, n)))

    def f(M):
        return jnp.sum(C * inverse_cholesky(M))

    G = np.asarray(jax.grad(f)(A))
    np.testing.assert_allclose(G, G.T, rtol=0, atol=1e-12 * np.abs(G).max())
    E = rng.normal(size=(n, n))
    E = jnp.asarray(E + E.T)
    h = 1e-6
    fd = (f(A + h * E) - f(A - h * E)) / (2 * h)
    assert abs(np.sum(G * np.asarray(E)) - fd) <= 1e-6 * abs(fd)


def test_top_eigenvalue_is_a_lower_bound_and_exact_with_enough_steps():
    rng = np.random.default_rng(3)
    A = _spd(rng, 12)
    top = np.linalg.eigvalsh(A)[-1]
    v0 = jnp.ones(12)
    few = float(top_eigenvalue(lambda v: jnp.asarray(A) @ v, v0, steps=3))
    full = float(top_eigenvalue(lambda v: jnp.asarray(A) @ v, v0, steps=12))
    assert few <= top * (1 + 1e-12) and full <= top * (1 + 1e-12)
    # with n steps the Ritz value is the eigenvalue; 24 bisection steps of a Gershgorin
    # bracket leave a relative error of about 2^-24
    assert top - full <= 1e-6 * top

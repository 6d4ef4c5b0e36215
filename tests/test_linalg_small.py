"""The small step-by-step factorisations (`jaxtraj._linalg`): values equal LAPACK's, and
their analytic derivative rules equal the derivatives of the steps themselves."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtraj import _linalg as la

jax.config.update("jax_enable_x64", True)


def _spd(rng, s):
    X = rng.normal(size=(s, s))
    return X @ X.T + s * np.eye(s)


def test_cholesky_rule_equals_the_steps_derivative(rng):
    s = 6
    A = _spd(rng, s)
    A[np.triu_indices(s, 1)] += rng.normal(size=s * (s - 1) // 2)  # upper triangle not read
    A = jnp.asarray(A)
    L = la.cholesky_small(A)
    np.testing.assert_allclose(L, np.linalg.cholesky(np.tril(A) + np.tril(A, -1).T), atol=1e-12)
    # under vmap and jit, and differentiated once and twice
    As = jnp.stack([A, A + jnp.eye(s)])
    np.testing.assert_allclose(jax.jit(jax.vmap(la.cholesky_small))(As)[0], L, atol=1e-13)
    _assert_rule_equals_steps(la.cholesky_small, la._cholesky_steps, A, twice=True)


def _assert_rule_equals_steps(rule, steps, A, twice):
    """A factor's analytic rule against the derivatives of its steps: forward and reverse
    Jacobians and (``twice``) the Hessian of a scalar of it, jitted."""
    for jac in (jax.jacfwd, jax.jacrev):
        np.testing.assert_allclose(
            jax.jit(jac(rule))(A), jax.jit(jac(steps))(A), rtol=1e-10, atol=1e-12
        )
    if twice:
        h = jax.jit(jax.hessian(lambda a: jnp.sum(rule(a) ** 3)))(A)
        h_steps = jax.jit(jax.hessian(lambda a: jnp.sum(steps(a) ** 3)))(A)
        np.testing.assert_allclose(h, h_steps, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("s", [1, 3, 6, 9])
def test_inverse_cholesky_rule_equals_the_steps_derivative(rng, s):
    A = _spd(rng, s)
    A[np.tril_indices(s, -1)] += rng.normal(size=s * (s - 1) // 2)  # lower triangle not read
    A = jnp.asarray(A)
    W = la.inverse_cholesky_small(A)
    sym = np.triu(A) + np.triu(A, 1).T
    np.testing.assert_allclose(W, np.linalg.inv(np.linalg.cholesky(sym)), rtol=1e-11, atol=1e-13)
    # the Hessian only up to 6x6 (the 9x9 steps' Hessian compiles slowly)
    _assert_rule_equals_steps(
        la.inverse_cholesky_small, la._inverse_cholesky_steps, A, twice=s <= 6
    )
    # not positive definite: NaN, as cholesky_small
    bad = np.asarray(sym).copy()
    bad[-1, -1] = -1.0
    assert np.isnan(np.asarray(la.inverse_cholesky_small(jnp.asarray(bad)))).any()


@pytest.mark.parametrize("trans", [0, 1])
@pytest.mark.parametrize("rhs", [(), (4,)])
def test_triangular_solve_rule_equals_the_steps_derivative(rng, trans, rhs):
    s = 6
    C = np.tril(rng.normal(size=(s, s))) + 3 * np.eye(s)
    C[np.triu_indices(s, 1)] = rng.normal(size=s * (s - 1) // 2)  # not read
    C, B = jnp.asarray(C), jnp.asarray(rng.normal(size=(s, *rhs)))
    x = la.solve_triangular_small(C, B, trans=trans)
    T = np.tril(np.asarray(C))
    np.testing.assert_allclose(x, np.linalg.solve(T.T if trans else T, np.asarray(B)), atol=1e-12)

    def rule(C, B):
        return la.solve_triangular_small(C, B, trans=trans)

    def steps(C, B):
        return la._triangular_steps(C, B, trans=trans)

    for jac in (jax.jacfwd, jax.jacrev):
        for got, want in zip(
            jax.jit(jac(rule, argnums=(0, 1)))(C, B),
            jax.jit(jac(steps, argnums=(0, 1)))(C, B),
            strict=True,
        ):
            np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)

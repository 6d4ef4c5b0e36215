import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraj as jt
from jaxtraj.basis import DCTBasis, max_k, paper_dct_matrix


@pytest.mark.parametrize("F,k", [(10, 4), (150, 10), (7, 7)])
def test_uniform_times_reproduce_paper_eq3(F, k):
    phi = np.asarray(jt.dct_basis(jnp.arange(F, dtype=float), k))
    ref = paper_dct_matrix(F, k)
    # Same columns up to a positive scale; orthonormal by default.
    scale = np.linalg.norm(ref, axis=0)
    np.testing.assert_allclose(phi, ref / scale, atol=1e-12)
    np.testing.assert_allclose(phi.T @ phi, np.eye(k), atol=1e-12)
    raw = np.asarray(jt.dct_basis(jnp.arange(F, dtype=float), k, orthonormal=False))
    np.testing.assert_allclose(raw, ref, atol=1e-12)


def test_matches_scipy_dct_matrix():
    scipy_fft = pytest.importorskip("scipy.fft")
    F, k = 32, 8
    ref = scipy_fft.idct(np.eye(F), type=2, norm="ortho", axis=0)  # columns: basis vectors
    phi = np.asarray(jt.dct_basis(jnp.arange(F, dtype=float), k))
    np.testing.assert_allclose(phi, ref[:, :k], atol=1e-12)


def test_time_unit_and_offset_invariance():
    F, k = 40, 6
    t = np.linspace(0.0, 1.0, F)
    a = jt.dct_basis(t, k)
    b = jt.dct_basis(3.5 + 2.0 * t, k)  # shift and stretch: same normalised time
    np.testing.assert_allclose(a, b, atol=1e-12)


@pytest.mark.parametrize("order", [1, 2])
def test_derivatives_equal_autodiff(rng, order):
    times = np.sort(rng.uniform(0.0, 2.0, 25))
    basis = DCTBasis.from_times(times, 7)

    def row(t):
        return basis(jnp.atleast_1d(t))[0]

    d = jax.jacfwd(row)
    if order == 2:
        d = jax.jacfwd(d)
    auto = jax.vmap(d)(jnp.asarray(times))
    np.testing.assert_allclose(basis(times, derivative=order), auto, rtol=1e-10, atol=1e-10)


def test_velocity_of_fitted_curve_matches_finite_difference(rng):
    times = np.sort(rng.uniform(0.0, 2.0, 30))
    basis = DCTBasis.from_times(times, 8)
    beta = rng.normal(size=(8, 3))
    t = jnp.linspace(0.1, 1.9, 11)
    h = 1e-6
    fd = (basis(t + h) @ beta - basis(t - h) @ beta) / (2 * h)
    np.testing.assert_allclose(basis(t, 1) @ beta, fd, rtol=1e-6, atol=1e-6)


def test_evaluation_past_last_frame_is_continuous(rng):
    times = np.sort(rng.uniform(0.0, 2.0, 30))
    basis = DCTBasis.from_times(times, 5)
    t = jnp.array([times[-1], times[-1] + 0.02])
    vals = basis(t)
    assert np.all(np.isfinite(vals))
    assert np.max(np.abs(vals[1] - vals[0])) < 0.05


def test_jit_and_vmap(rng):
    times = jnp.asarray(np.sort(rng.uniform(0, 1, 20)))
    f = jax.jit(lambda t: jt.dct_basis(t, 5))
    np.testing.assert_allclose(f(times), jt.dct_basis(times, 5), atol=1e-14)
    batch = jnp.stack([times, times * 2.0 + 1.0])
    out = jax.vmap(lambda t: jt.dct_basis(t, 5))(batch)
    for i in range(2):
        np.testing.assert_allclose(out[i], jt.dct_basis(batch[i], 5), atol=1e-14)


def test_float32_dtype():
    phi = jt.dct_basis(jnp.arange(20, dtype=jnp.float32), 4)
    assert phi.dtype == jnp.float32
    ref = paper_dct_matrix(20, 4)
    tol = 50 * np.finfo(np.float32).eps
    np.testing.assert_allclose(phi, ref / np.linalg.norm(ref, axis=0), atol=tol)


def test_bad_input():
    with pytest.raises(ValueError, match="k:"):
        jt.dct_basis(jnp.arange(10.0), 0)
    with pytest.raises(ValueError, match="k:"):
        jt.dct_basis(jnp.arange(10.0), 2.5)
    with pytest.raises(ValueError, match="times"):
        jt.dct_basis(jnp.zeros((3, 2)), 2)
    with pytest.raises(ValueError, match="derivative"):
        DCTBasis.from_times(jnp.arange(10.0), 3)(jnp.arange(10.0), derivative=3)
    assert max_k(150) == 100 and max_k(4) == 2

"""Property tests (hypothesis) for cheap geometric invariants of the core."""

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxtraj as jt
from tests._scenes import project_np, random_cameras

seeds = st.integers(min_value=0, max_value=2**31 - 1)
SETTINGS = settings(max_examples=25, deadline=None)

# Compiled once for all examples (same shapes); called eagerly, the solver's power
# iteration would be compiled again for every example.
_eta = jax.jit(jt.reconstructibility)
_gain = jax.jit(jt.conditioning_gain)
_solve = jax.jit(lambda P, uv, basis: jt.reconstruct(P, uv, basis, max_gain=np.inf))


def _rotation(rng):
    return np.asarray(jaxlie.SO3.exp(jnp.asarray(rng.normal(size=3))).as_matrix())


@SETTINGS
@given(seeds)
def test_ray_constraint_holds_along_the_whole_ray(seed):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(4, 3)) * 0.3
    P, _, _, C = random_cameras(rng, X)
    Q, q = jt.ray_constraints(P, project_np(P, X))
    s = rng.uniform(-3, 3, size=(4, 1))
    Y = C + s * (X - C)
    scale = np.abs(np.asarray(q)).max() + 1.0
    assert np.abs(np.einsum("fai,fi->fa", Q, Y) - q).max() < 1e-9 * scale


@SETTINGS
@given(seeds)
def test_fit_rigid_inverts_any_rigid_motion(seed):
    rng = np.random.default_rng(seed)
    model = rng.normal(size=(5, 3))
    R, t = _rotation(rng), rng.normal(size=3) * 3
    Rh, th = jt.fit_rigid(model, model @ R.T + t)
    assert np.abs(np.asarray(Rh) - R).max() < 1e-9
    assert np.abs(np.asarray(th) - t).max() < 1e-9


@SETTINGS
@given(seeds)
def test_eta_and_gain_are_invariant_to_a_change_of_world_frame(seed):
    rng = np.random.default_rng(seed)
    F, k = 18, 4
    times = np.linspace(0, 1, F)
    basis = np.asarray(jt.dct_basis(times, k))
    X = np.sin(np.outer(times, rng.uniform(1, 4, 3))) * 0.2
    P, _, _, C = random_cameras(rng, X)
    uv = project_np(P, X)
    R, t = _rotation(rng), rng.normal(size=3)
    # World change x' = R x + t: cameras become P [R^T, -R^T t; 0 1].
    T_inv = np.eye(4)
    T_inv[:3, :3], T_inv[:3, 3] = R.T, -R.T @ t
    P2 = P @ T_inv
    eta1 = float(_eta(C, X, basis))
    eta2 = float(_eta(C @ R.T + t, X @ R.T + t, basis))
    assert abs(eta1 - eta2) <= 1e-8 * eta1
    g1 = float(_gain(P, uv, basis))
    g2 = float(_gain(P2, uv, basis))
    assert abs(g1 - g2) <= 1e-6 * g1
    r1 = _solve(P, uv, basis)
    r2 = _solve(P2, uv, basis)
    np.testing.assert_allclose(r2.points, np.asarray(r1.points) @ R.T + t, atol=1e-8)

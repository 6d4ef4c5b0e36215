import jax.numpy as jnp
import numpy as np

import jaxtraj as jt
from tests._scenes import project_np, random_cameras


def test_points_on_ray_and_camera_centre_satisfy_eq4(rng):
    X = rng.normal(size=(12, 3)) * 0.2
    P, _, _, C = random_cameras(rng, X)
    uv = project_np(P, X)
    Q, q = jt.ray_constraints(P, uv)
    assert Q.shape == (12, 2, 3) and q.shape == (12, 2)
    np.testing.assert_allclose(jnp.einsum("fai,fi->fa", Q, X), q, atol=1e-9)
    np.testing.assert_allclose(jnp.einsum("fai,fi->fa", Q, C), q, atol=1e-9)
    # Any point on the ray C + s (X - C) satisfies it too.
    Y = C + 2.7 * (X - C)
    np.testing.assert_allclose(jnp.einsum("fai,fi->fa", Q, Y), q, atol=1e-8)


def test_explicit_block_forms(rng):
    F, k = 5, 3
    X = rng.normal(size=(F, 3))
    P, _, _, _ = random_cameras(rng, X)
    Q, q = jt.ray_constraints(P, project_np(P, X))
    Qd = np.asarray(jt.block_diagonal_Q(Q))
    assert Qd.shape == (2 * F, 3 * F)
    for i in range(F):
        np.testing.assert_array_equal(Qd[2 * i : 2 * i + 2, 3 * i : 3 * i + 3], Q[i])
    off = Qd.copy()
    for i in range(F):
        off[2 * i : 2 * i + 2, 3 * i : 3 * i + 3] = 0
    assert np.all(off == 0)
    np.testing.assert_allclose(Qd @ X.reshape(-1), np.asarray(q).reshape(-1), atol=1e-9)
    phi = rng.normal(size=(F, k))
    beta = rng.normal(size=(k, 3))
    Th = np.asarray(jt.theta_matrix(phi))
    assert Th.shape == (3 * F, 3 * k)
    np.testing.assert_allclose(Th @ beta.reshape(-1), (phi @ beta).reshape(-1), atol=1e-12)

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxtraj as jt


def _random_pose(rng):
    R = np.asarray(jaxlie.SO3.exp(jnp.asarray(rng.normal(size=3))).as_matrix())
    return R, rng.normal(size=3)


def test_recovers_exact_pose(rng):
    model = rng.normal(size=(5, 3)) * 0.1
    R, t = _random_pose(rng)
    Rh, th = jt.fit_rigid(model, model @ R.T + t)
    np.testing.assert_allclose(Rh, R, atol=1e-12)
    np.testing.assert_allclose(th, t, atol=1e-12)


def test_matches_svd_reference_with_noise_and_weights(rng):
    model = rng.normal(size=(6, 3)) * 0.1
    R, t = _random_pose(rng)
    obs = model @ R.T + t + rng.normal(size=(6, 3)) * 1e-3
    w = rng.uniform(0.5, 2.0, 6)
    Rh, th = jt.fit_rigid(model, obs, w)
    # Reference: weighted Umeyama without scale in NumPy.
    wn = w / w.sum()
    mm, mo = wn @ model, wn @ obs
    H = ((obs - mo) * wn[:, None]).T @ (model - mm)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    Rr = U @ D @ Vt
    np.testing.assert_allclose(Rh, Rr, atol=1e-12)
    np.testing.assert_allclose(th, mo - Rr @ mm, atol=1e-12)
    assert np.linalg.det(np.asarray(Rh)) == pytest.approx(1.0)


def test_reflection_is_corrected(rng):
    model = rng.normal(size=(4, 3)) * 0.1
    mirrored = model * np.array([1.0, 1.0, -1.0])
    R, _ = jt.fit_rigid(model, mirrored)
    assert np.linalg.det(np.asarray(R)) == pytest.approx(1.0)


def test_batched_over_frames_equals_loop_and_jit(rng):
    model = rng.normal(size=(4, 3)) * 0.1
    poses = [_random_pose(rng) for _ in range(6)]
    obs = np.stack([model @ R.T + t for R, t in poses]) + rng.normal(size=(6, 4, 3)) * 1e-3
    Rb, tb = jt.fit_rigid(model, obs)
    Rj, tj = jax.jit(jt.fit_rigid)(model, obs)
    Rv, tv = jax.vmap(jt.fit_rigid, in_axes=(None, 0))(model, obs)
    for f in range(6):
        Rl, tl = jt.fit_rigid(model, obs[f])
        for R_, t_ in ((Rb, tb), (Rj, tj), (Rv, tv)):
            np.testing.assert_allclose(R_[f], Rl, atol=1e-12)
            np.testing.assert_allclose(t_[f], tl, atol=1e-12)


def test_gradient(rng):
    model = jnp.asarray(rng.normal(size=(4, 3)) * 0.1)
    R, t = _random_pose(rng)
    obs = jnp.asarray(model @ R.T + t + rng.normal(size=(4, 3)) * 1e-2)
    fit = jax.jit(lambda o: jt.fit_rigid(model, o))
    check_grads(lambda o: fit(o)[1], (obs,), order=1, modes=["rev"])
    check_grads(lambda o: fit(o)[0], (obs,), order=1, modes=["rev"], atol=1e-4)


def test_bad_input(rng):
    with pytest.raises(ValueError, match="at least 3"):
        jt.fit_rigid(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="observed_points"):
        jt.fit_rigid(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="model_points"):
        jt.fit_rigid(np.zeros((4, 2)), np.zeros((4, 3)))

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

import jaxtraj as jt
from tests._scenes import K640, project_np, scene


def _eta_closed_form(C, X, basis):
    Th = np.kron(basis, np.eye(3))
    Pp = np.eye(Th.shape[0]) - Th @ np.linalg.solve(Th.T @ Th, Th.T)
    return np.linalg.norm(Pp @ C.reshape(-1)) / np.linalg.norm(Pp @ X.reshape(-1))


def test_eta_matches_closed_form_and_is_rigid_invariant(rng):
    s = scene(rng, F=40, k=6, in_span=False)
    eta = float(jt.reconstructibility(s["C"], s["X"], s["basis"]))
    assert eta == pytest.approx(_eta_closed_form(s["C"], s["X"], s["basis"]), rel=1e-10)
    R = np.asarray(jaxlie.SO3.exp(jnp.asarray(rng.normal(size=3))).as_matrix())
    t = rng.normal(size=3) * 5
    eta2 = float(jt.reconstructibility(s["C"] @ R.T + t, s["X"] @ R.T + t, s["basis"]))
    assert eta2 == pytest.approx(eta, rel=1e-9)


def test_eta_small_when_camera_path_in_span(rng):
    s = scene(rng, F=40, k=6, in_span=False)
    C_smooth = s["basis"] @ rng.normal(size=(6, 3))
    assert float(jt.reconstructibility(C_smooth, s["X"], s["basis"])) < 1e-9
    assert float(jt.reconstructibility(s["C"], s["X"], s["basis"])) > 1.0


def test_eta_jit_vmap(rng):
    s = scene(rng, F=30, k=5, in_span=False)
    f = jax.jit(jt.reconstructibility)
    assert float(f(s["C"], s["X"], s["basis"])) == pytest.approx(
        float(jt.reconstructibility(s["C"], s["X"], s["basis"])), rel=1e-12
    )
    Cs = np.stack([s["C"], s["C"] * 1.1])
    out = jax.vmap(jt.reconstructibility, in_axes=(0, None, None))(Cs, s["X"], s["basis"])
    for i in range(2):
        assert float(out[i]) == pytest.approx(_eta_closed_form(Cs[i], s["X"], s["basis"]), rel=1e-9)
    with pytest.raises(ValueError, match="points"):
        jt.reconstructibility(s["C"], s["X"][:-1], s["basis"])


def test_on_ray_decomposition_recovers_a(rng):
    s = scene(rng, F=20, k=4)
    a = rng.uniform(-0.5, 1.5, 20)
    est = a[:, None] * s["X"] + (1 - a[:, None]) * s["C"]
    dec = jt.on_ray_decomposition(est, s["X"], s["C"])
    np.testing.assert_allclose(dec.a, a, atol=1e-10)
    np.testing.assert_allclose(dec.off_ray, 0.0, atol=1e-10)
    # The linear estimate of a real reconstruction lies near its rays (eq. 7 approx.).
    res = jt.reconstruct(s["P"], s["uv"], s["basis"])
    dec = jt.on_ray_decomposition(res.points, s["X"], s["C"])
    np.testing.assert_allclose(dec.a, 1.0, atol=1e-6)


def test_conditioning_gain_matches_dense_projector_norm(rng):
    s = scene(rng, F=25, k=5, noise=0.3, in_span=False)
    w = rng.uniform(0.2, 2.0, 25)
    Q, _ = jt.ray_constraints(s["P"], s["uv"])
    Qd = np.asarray(jt.block_diagonal_Q(Q)) * np.repeat(np.sqrt(w), 2)[:, None]
    Th = np.kron(s["basis"], np.eye(3))
    A = Qd.T @ Qd
    Pi = Th @ np.linalg.solve(Th.T @ A @ Th, Th.T @ A)
    np.testing.assert_allclose(Pi @ Pi, Pi, atol=1e-8)  # a projector
    ref = np.linalg.norm(Pi, 2)
    assert float(jt.conditioning_gain(s["P"], s["uv"], s["basis"], w)) == pytest.approx(
        ref, rel=1e-7
    )
    assert ref >= 1.0


def test_solver_gain_bound_brackets_the_exact_gain():
    """The solver's gain is an upper bound from the frame blocks' eigenvalue spread: tight
    with equal weights (both non-zero eigenvalues of a pinhole frame block are ~f^2), at most
    sqrt(max w / min w) looser with unequal ones; its Lanczos part converges (>= exact)."""
    solve = jax.jit(jt.reconstruct)
    for seed in range(4):
        rng = np.random.default_rng(seed)
        s = scene(rng, F=30, k=6, noise=0.3, in_span=False)
        w = rng.uniform(0.5, 2.0, 30) if seed % 2 else np.ones(30)
        exact = float(jt.conditioning_gain(s["P"], s["uv"], s["basis"], w))
        est = float(solve(s["P"], s["uv"], s["basis"], w).gain)
        assert est >= exact * (1 - 1e-3)
        loose = 1.02 if seed % 2 == 0 else 1.02 * np.sqrt(w.max() / w.min())
        assert est <= exact * loose, (seed, est, exact)
        if seed % 2:
            assert est >= 1.05 * exact  # unequal weights do loosen it (the test can fail)


def test_diagnostics_false_skips_gain_but_flags_singular_systems(rng):
    s = scene(rng, F=30, k=6, noise=0.3, in_span=False)
    fast = jt.reconstruct(s["P"], s["uv"], s["basis"], diagnostics=False)
    full = jt.reconstruct(s["P"], s["uv"], s["basis"])
    np.testing.assert_allclose(fast.points, full.points, atol=1e-12)
    assert np.isnan(float(fast.gain)) and int(fast.status) == jt.Status.OK
    X = s["X"]
    C = X + np.array([0.2, 0.1, -1.0])  # a camera that follows the point
    P = []
    for c, x in zip(C, X, strict=True):
        R, t = jt.look_at(c, x, up_w=(0.0, 1.0, 0.0))
        P.append(K640 @ np.hstack([np.asarray(R), np.asarray(t)[:, None]]))
    P = np.array(P)
    res = jt.reconstruct(P, project_np(P, X), s["basis"], diagnostics=False)
    assert int(res.status) == jt.Status.DEGENERATE

"""Covariance of the DCT solve: the first-order part against an exact Jacobian reference and
the Monte-Carlo spread under pixel and camera-pose noise; the model-error term on tracks
outside the span; batching and bad inputs."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraj as jt
from jaxtraj.estimators import dct_covariance, points_covariance
from jaxtraj.estimators.covariance import _hat
from tests._scenes import limb_scene
from tests._scenes import scene as core_scene
from tests.test_estimators_scenes import robot_scene

F, K = 40, 6


@pytest.fixture
def scene(rng):
    s = robot_scene(rng, F=F, mode="random", noise=0.5)
    s["basis"] = np.asarray(jt.dct_basis(s["times"], K))
    return s


def _coeffs(s, uv):
    return jt.reconstruct_points(s["P"], uv[None], s["basis"]).coeffs[0]


def test_equals_linearised_solve(scene):
    """Without a penalty: the linearised noise spread of the solve (its Jacobian with
    respect to the pixels). With a penalty ``pen``: that of the penalised solve plus
    ``s^2 N^-1 pen N^-1`` (``N`` with the penalty, ``s^2`` the mean ``w d^2 sigma^2`` of a
    ray-constraint row; the posterior form), computed here densely. A zero penalty is the
    unpenalised covariance."""
    s = scene
    P, uv, B = s["P"], jnp.asarray(s["uv"]), s["basis"]
    solve = jax.jit(lambda u, pen: jt.reconstruct(P, u, B, penalty=pen).coeffs)
    jac = jax.jit(jax.jacfwd(lambda u, pen: solve(u, pen).reshape(-1)))
    cov_of = jax.jit(
        lambda c, pen: dct_covariance(P, uv, B, c, pixel_sigma=0.5, model_error=False, penalty=pen)
    )
    zero = np.zeros(K)
    pen = 2e3 * np.arange(1, K + 1, dtype=float) ** 4  # the prior term: 26 % of the trace
    N, _ = jt.normal_equations(P, uv, B)
    for p in (zero, pen):
        c = solve(uv, p)
        cov = cov_of(c, p)
        J = np.asarray(jac(uv, p)).reshape(3 * K, -1)
        Ninv = np.linalg.inv(np.asarray(N) + np.diag(np.repeat(p, 3)))
        d = np.einsum("fj,fj->f", P[:, 2, :], np.hstack([B @ np.asarray(c), np.ones((F, 1))]))
        ref = 0.25 * J @ J.T + np.mean(0.25 * d**2) * Ninv @ np.diag(np.repeat(p, 3)) @ Ninv
        np.testing.assert_allclose(
            np.asarray(cov.coeffs), ref, rtol=1e-7, atol=1e-9 * np.abs(ref).max()
        )
    plain = dct_covariance(P, uv, B, solve(uv, zero), pixel_sigma=0.5, model_error=False)
    np.testing.assert_allclose(
        np.asarray(cov_of(solve(uv, zero), zero).coeffs), np.asarray(plain.coeffs), rtol=1e-9
    )
    pts = np.asarray(points_covariance(B, plain.coeffs))
    Phi = np.kron(B, np.eye(3))
    dense = Phi @ np.asarray(plain.coeffs) @ Phi.T
    np.testing.assert_allclose(pts[7], dense[21:24, 21:24], rtol=1e-10)
    np.testing.assert_allclose(np.asarray(plain.std), np.sqrt(np.diagonal(pts, axis1=1, axis2=2)))
    with pytest.raises(ValueError, match="penalty"):
        dct_covariance(P, uv, B, c, penalty=np.ones(K + 1))


def test_matches_monte_carlo_pixel_noise(scene, rng):
    s = scene
    n = 1500
    solve = jax.jit(lambda uv: jt.reconstruct_points(s["P"], uv, s["basis"]).points)
    pts = np.asarray(solve(s["clean"][None] + 0.5 * rng.normal(size=(n, F, 2))))
    emp = np.einsum("nfi,nfj->fij", pts - pts.mean(0), pts - pts.mean(0)) / (n - 1)
    c = _coeffs(s, s["clean"])
    cov = dct_covariance(s["P"], s["clean"], s["basis"], c, pixel_sigma=0.5, model_error=False)
    ratio = np.trace(emp, axis1=1, axis2=2) / np.trace(np.asarray(cov.points), axis1=1, axis2=2)
    # sampling error of a variance from n draws: about sqrt(2 / n) = 3.7 %
    assert abs(np.mean(ratio) - 1) < 0.03
    assert np.all(np.abs(ratio - 1) < 0.15)


def test_matches_monte_carlo_pose_noise(scene, rng):
    s = scene
    n = 800
    sd = np.array([1e-3] * 3 + [5e-4] * 3)  # 1 mm, 0.5 mrad
    xi = rng.normal(size=(n, F, 6)) * sd
    step = jax.vmap(jax.vmap(lambda P, x: P @ (jnp.eye(4) - _hat(x) + 0.5 * _hat(x) @ _hat(x))))
    Ps = step(jnp.broadcast_to(jnp.asarray(s["P"]), (n, F, 3, 4)), jnp.asarray(xi))
    solve = jax.jit(jax.vmap(lambda P: jt.reconstruct(P, s["clean"], s["basis"]).points))
    pts = np.asarray(solve(Ps))
    emp = np.einsum("nfi,nfj->fij", pts - pts.mean(0), pts - pts.mean(0)) / (n - 1)
    pose_cov = np.tile(np.diag(sd**2), (F, 1, 1))
    cov = dct_covariance(
        s["P"],
        s["clean"],
        s["basis"],
        _coeffs(s, s["clean"]),
        pixel_sigma=1e-9,
        pose_cov=pose_cov,
        model_error=False,
    )
    ratio = np.trace(emp, axis1=1, axis2=2) / np.trace(np.asarray(cov.points), axis1=1, axis2=2)
    assert abs(np.mean(ratio) - 1) < 0.06


def test_jit_vmap_and_weights(scene, rng):
    s = scene
    w = np.ones(F)
    w[5:9] = 0.0
    uv = s["uv"].copy()
    uv[5:9] = np.nan
    c = jt.reconstruct(s["P"], uv, s["basis"], w).coeffs
    eager = dct_covariance(s["P"], uv, s["basis"], c, w, pixel_sigma=0.5)
    jitted = jax.jit(lambda u, c: dct_covariance(s["P"], u, s["basis"], c, w, pixel_sigma=0.5))(
        jnp.nan_to_num(uv), c
    )
    np.testing.assert_allclose(np.asarray(jitted.coeffs), np.asarray(eager.coeffs), rtol=1e-10)
    uvs = np.stack([s["uv"], s["uv"] + 0.3])
    cs = jt.reconstruct_points(s["P"], uvs, s["basis"]).coeffs
    batch = jax.jit(
        jax.vmap(lambda u, c: dct_covariance(s["P"], u, s["basis"], c, pixel_sigma=0.5))
    )(uvs, cs)
    one = dct_covariance(s["P"], uvs[1], s["basis"], cs[1], pixel_sigma=0.5)
    np.testing.assert_allclose(np.asarray(batch.points[1]), np.asarray(one.points), rtol=1e-10)
    # differentiable: d trace / d sigma = 2 trace / sigma
    g = jax.jit(
        jax.grad(
            lambda sg: jnp.trace(
                dct_covariance(s["P"], s["uv"], s["basis"], cs[0], pixel_sigma=sg).coeffs
            )
        )
    )(0.5)
    tr = float(
        jnp.trace(dct_covariance(s["P"], s["uv"], s["basis"], cs[0], pixel_sigma=0.5).coeffs)
    )
    assert float(g) == pytest.approx(2 * tr / 0.5, rel=1e-9)


def test_bad_inputs(scene):
    s = scene
    c = np.zeros((K, 3))
    with pytest.raises(ValueError, match="coeffs"):
        dct_covariance(s["P"], s["uv"], s["basis"], np.zeros((K + 1, 3)))
    with pytest.raises(ValueError, match="basis"):
        dct_covariance(s["P"], s["uv"], s["basis"][:-1], c)
    with pytest.raises(ValueError, match="pose_cov"):
        dct_covariance(s["P"], s["uv"], s["basis"], c, pose_cov=np.zeros((F, 3, 3)))
    with pytest.raises(ValueError, match="pixel_sigma"):
        dct_covariance(s["P"], s["uv"], s["basis"], c, pixel_sigma=np.ones(3))
    with pytest.raises(ValueError, match="coeffs_cov"):
        points_covariance(s["basis"], np.eye(5))


def test_model_error_covers_truncation_and_vanishes_inside_the_span(rng):
    """Outside the span (a limb-like point, fast robot-like camera, k = 8, 20): the error is
    5-300 first-order standard deviations (sd: sqrt of the trace); with the model-error
    term it is 0.09-0.35 sd on average and the mean NEES (3 dof) 1.6-2.4 (asserted: below
    1 sd and below 3). Frames without a pixel (here 12 in a row) are covered too (they take
    the observed frames' mean term). Inside the span (noise 0.5 px) the term vanishes."""
    cov = jax.jit(
        lambda P, u, B, c, w, m: (
            dct_covariance(P, u, B, c, w, pixel_sigma=0.5, model_error=m).points
        ),
        static_argnums=5,
    )
    gap = np.zeros(150, bool)
    gap[60:72] = True
    for seed in (1, 9):
        t, X, P, uv = limb_scene(np.random.default_rng(seed), camera="fast")
        w = np.where(gap, 0.0, 1.0) if seed == 9 else np.ones(150)
        for k in (8, 20):
            B = jt.dct_basis(t, k)
            res = jt.reconstruct(P, uv, B, w)
            e = np.asarray(res.points) - X
            full = np.asarray(cov(P, uv, B, res.coeffs, w, True))
            first = np.asarray(cov(P, uv, B, res.coeffs, w, False))
            sd_first = np.sqrt(np.trace(first, axis1=1, axis2=2))
            sd = np.sqrt(np.trace(full, axis1=1, axis2=2))
            err = np.linalg.norm(e, axis=1)
            assert np.mean(err / sd_first) > 4  # noise alone cannot explain it (4.7-288)
            assert np.mean(err / sd) < 1.0
            nees = np.einsum("fi,fij,fj->f", e, np.linalg.pinv(full, hermitian=True), e)
            assert np.mean(nees) < 3.0
            if seed == 9:  # in the gap: first-order NEES 4e4-3e5, with the term 0.9-1.2
                assert np.mean(nees[gap]) < 3.0
    s = core_scene(rng, F=60, k=6, noise=0.5)
    res = jt.reconstruct(s["P"], s["uv"], s["basis"])
    a = dct_covariance(s["P"], s["uv"], s["basis"], res.coeffs, pixel_sigma=0.5)
    b = dct_covariance(s["P"], s["uv"], s["basis"], res.coeffs, pixel_sigma=0.5, model_error=False)
    np.testing.assert_allclose(np.asarray(a.points), np.asarray(b.points), rtol=1e-12, atol=0)

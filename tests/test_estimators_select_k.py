"""Automatic k: solves from one factor equal separate fits, gains equal the solver's, the CV
choice is near the error-optimal k (random and fast cameras), batching and bad inputs."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import jaxtraj as jt
from jaxtraj.estimators import select_k_cv, select_k_gain
from jaxtraj.estimators.select_k import _prefix_solve
from jaxtraj.solve import _factorise, normal_equations
from tests.test_estimators_scenes import dct_fit, rmse, robot_scene

F = 60
KS = (4, 6, 8, 10, 12, 14, 16)
CV = jax.jit(lambda P, uv, t: select_k_cv(P, uv, t, KS))
GAIN = jax.jit(lambda P, uv, t: select_k_gain(P, uv, t, KS, max_gain=3.0))
# the solver's conditioning gain, compiled (run eagerly, every k costs ~70 small compilations)
SOLVER_GAIN = jax.jit(lambda P, uv, b: jt.reconstruct(P, uv, b).gain)
PREFIX = jax.jit(_prefix_solve)
SMALL_KS = (3, 5)  # the batched-driver test: small candidates keep its compilations short
CV_W = jax.jit(lambda P, uv, t, w: select_k_cv(P, uv, t, SMALL_KS, w, folds=2))


def test_prefix_solve_equals_k_column_fit(rng):
    s = robot_scene(rng, F=F, mode="random", noise=0.4)
    big = jt.dct_basis(s["times"], 12)
    N, b = normal_equations(s["P"], s["uv"], big)
    W, d = jax.jit(_factorise)(N)  # the factor of the 12-column system serves every k
    for k in (4, 7, 12):
        beta = PREFIX(W, d, N, b, k)
        ref = jt.reconstruct(s["P"], s["uv"], big[:, :k]).coeffs
        np.testing.assert_allclose(
            np.asarray(beta[: 3 * k]).reshape(k, 3), np.asarray(ref), rtol=1e-9
        )
        assert np.all(np.asarray(beta[3 * k :]) == 0.0)


def test_gains_equal_solver_gain(rng):
    s = robot_scene(rng, F=F, mode="smooth", noise=0.4)
    sel = GAIN(s["P"], s["uv"], s["times"])
    for i, k in enumerate(KS[:3]):
        g = SOLVER_GAIN(s["P"], s["uv"], jt.dct_basis(s["times"], k))
        assert float(sel.gain[i]) == pytest.approx(float(g), rel=1e-6)
    ok = np.asarray(sel.gain) <= 3.0
    expected = max([k for k, o in zip(KS, ok, strict=True) if o], default=0)
    assert int(sel.k) == expected


def _dct_errors(s):
    """3D errors of the plain DCT fits with every k in KS (the columns of one basis)."""
    basis = np.asarray(jt.dct_basis(s["times"], max(KS)))
    return [rmse(dct_fit(s["P"], s["uv"], basis[:, :k]), s["X"]) for k in KS]


def test_cv_choice_near_error_optimal_k():
    rng = np.random.default_rng(11)
    regrets = []
    for _ in range(4):
        s = robot_scene(rng, F=F, mode="random", noise=0.3)
        errs = _dct_errors(s)
        sel = CV(s["P"], s["uv"], s["times"])
        chosen = errs[KS.index(int(sel.k))]
        regrets.append(chosen / min(errs))
        assert abs(int(sel.k) - KS[int(np.argmin(errs))]) <= 4
    assert np.median(regrets) < 1.3, regrets


def test_gain_weighted_rule_on_fast_cameras():
    """Fast smooth cameras: the held-out error keeps falling with k while the 3D error
    explodes; the gain-weighted rule stays near the best single k, the plain
    reprojection rule does not."""
    rng = np.random.default_rng(5)
    errs, chosen, by_reprojection = [], [], []
    for _ in range(6):  # F = 100: at F = 60 the gain rises so steeply that both agree
        s = robot_scene(rng, F=100, mode="fast", noise=0.4)
        e = _dct_errors(s)
        sel = CV(s["P"], s["uv"], s["times"])
        score = np.where(np.asarray(sel.gain) <= 100.0, np.asarray(sel.score), np.inf)
        errs.append(e)
        chosen.append(e[KS.index(int(sel.k))])
        by_reprojection.append(e[int(np.argmin(score))])
    best_fixed = np.min(np.mean(errs, axis=0))
    assert np.mean(chosen) < 0.9 * np.mean(by_reprojection), (chosen, by_reprojection)
    assert np.mean(chosen) < 1.2 * best_fixed, (chosen, best_fixed)
    assert np.mean(by_reprojection) > 1.15 * best_fixed  # the failure the rule is for


def test_vmap_equals_loop_and_degenerate_camera(rng):
    s = robot_scene(rng, F=F, mode="random", noise=0.3)
    uvs = np.stack([s["uv"], s["uv"] + rng.normal(size=(F, 2)) * 0.3])
    batch = jax.jit(jax.vmap(lambda u: select_k_cv(s["P"], u, s["times"], KS)))(uvs)
    one = CV(s["P"], uvs[1], s["times"])
    np.testing.assert_allclose(np.asarray(batch.score[1]), np.asarray(one.score), rtol=1e-9)
    assert int(batch.k[1]) == int(one.k)
    # a camera that follows the point at a fixed offset: nothing is admissible
    P = np.array(s["P"])
    offs = s["X"] - s["X"][0]
    P[:, :, 3] = P[0, :, 3] - np.einsum("ij,fj->fi", P[0, :, :3], offs)
    P[:, :, :3] = P[0, :, :3]
    uv = s["clean"][:1].repeat(F, 0)
    assert int(GAIN(P, uv, s["times"]).k) == 0


def test_bad_inputs(rng):
    s = robot_scene(rng, F=20, mode="random")
    with pytest.raises(ValueError, match="ks"):
        select_k_cv(s["P"], s["uv"], s["times"], ks=(0, 3))
    with pytest.raises(ValueError, match="ks"):
        select_k_gain(s["P"], s["uv"], s["times"], ks=(2.5,))
    with pytest.raises(ValueError, match="folds"):
        select_k_cv(s["P"], s["uv"], s["times"], folds=1)
    with pytest.raises(ValueError, match="rule"):
        select_k_cv(s["P"], s["uv"], s["times"], rule="aic")
    with pytest.raises(ValueError, match="healthy_gain"):
        select_k_cv(s["P"], s["uv"], s["times"], healthy_gain=0.5)
    with pytest.raises(ValueError, match="times"):
        select_k_cv(s["P"], s["uv"], s["times"][:-1])


def test_points_driver_equals_per_point_selection(rng):
    from jaxtraj.estimators import select_k_points

    s = robot_scene(rng, F=F, mode="random", noise=0.3)
    uvs = np.stack([s["uv"], s["uv"] + rng.normal(size=(F, 2)) * 2.0])
    w = np.ones((2, F))
    w[1, ::7] = 0.0  # missing detections on the second point
    many = select_k_points(s["P"], uvs, s["times"], SMALL_KS, w, folds=2)
    for n in range(2):
        one = CV_W(s["P"], uvs[n], s["times"], w[n])
        np.testing.assert_allclose(np.asarray(many.score[n]), np.asarray(one.score), rtol=1e-9)
        np.testing.assert_allclose(np.asarray(many.gain[n]), np.asarray(one.gain), rtol=1e-9)
        assert int(many.k[n]) == int(one.k)
    with pytest.raises(ValueError, match=r"weights: expected shape \(2, 60\)"):
        select_k_points(s["P"], uvs, s["times"], SMALL_KS, w[:, 1:])

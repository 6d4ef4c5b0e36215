"""Smoothness-prior estimator: block-tridiagonal solver, prior model, MAP optimality,
accuracy against the plain DCT, the choice of the noise density, batching and errors."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraj as jt
from jaxtraj import _linalg as la
from jaxtraj.estimators import _blocktri as bt
from jaxtraj.estimators import predict, select_process_psd, smooth_points, smooth_trajectory
from jaxtraj.estimators.smoothness import (
    _ml_grid_search,
    _prior_cost,
    _q_unit,
    _transition,
    default_psd_grid,
)
from tests.test_estimators_scenes import dct_fit, project_np, rmse, robot_scene

SMOOTH = jax.jit(
    lambda P, uv, t, w: smooth_trajectory(P, uv, t, w, pixel_sigma=0.4),
)
SMOOTH_Q = jax.jit(
    lambda P, uv, t, q: smooth_trajectory(P, uv, t, pixel_sigma=0.4, process_psd=q, iterations=6)
)


def _random_blocktri(rng, F, s):
    G = np.zeros((F * s, F * s))
    for i in range(F):
        G[i * s : (i + 1) * s, i * s : (i + 1) * s] = rng.normal(size=(s, s)) + 3 * np.eye(s)
        if i:
            G[i * s : (i + 1) * s, (i - 1) * s : i * s] = rng.normal(size=(s, s))
    A = G @ G.T
    D = np.stack([A[i * s : (i + 1) * s, i * s : (i + 1) * s] for i in range(F)])
    E = np.stack([A[(i + 1) * s : (i + 2) * s, i * s : (i + 1) * s] for i in range(F - 1)])
    return A, D, E


@pytest.mark.parametrize("s", [1, 3, 6, 9])
def test_unrolled_small_cholesky_and_triangular_solves(rng, s):
    G = rng.normal(size=(s, s)) + 3 * np.eye(s)
    A = G @ G.T
    C = np.asarray(la.cholesky_small(jnp.asarray(A)))
    np.testing.assert_allclose(C, np.linalg.cholesky(A), rtol=1e-12, atol=1e-12)
    B = rng.normal(size=(s, 4))
    np.testing.assert_allclose(
        np.asarray(la.solve_triangular_small(jnp.asarray(C), jnp.asarray(B))),
        np.linalg.solve(C, B),
        rtol=1e-10,
        atol=1e-12,
    )
    np.testing.assert_allclose(
        np.asarray(la.solve_triangular_small(jnp.asarray(C), jnp.asarray(B[:, 0]), trans=1)),
        np.linalg.solve(C.T, B[:, 0]),
        rtol=1e-10,
        atol=1e-12,
    )
    # not positive definite: NaN, as a failed LAPACK factorisation gives under JAX
    bad = A.copy()
    bad[-1, -1] = -1.0
    assert np.isnan(np.asarray(la.cholesky_small(jnp.asarray(bad)))).any()


@pytest.mark.parametrize("s", [3, 6])
def test_block_tridiagonal_solver_matches_dense(rng, s):
    F = 9
    A, D, E = _random_blocktri(rng, F, s)
    np.testing.assert_allclose(np.asarray(bt.dense(D, E)), A, atol=1e-12)
    b = rng.normal(size=(F, s))
    chol = bt.factor(jnp.asarray(D), jnp.asarray(E))
    x = np.asarray(bt.solve(chol, jnp.asarray(b))).ravel()
    np.testing.assert_allclose(x, np.linalg.solve(A, b.ravel()), rtol=1e-9, atol=1e-12)
    Ainv = np.linalg.inv(A)
    S = np.asarray(bt.diag_inverse(chol))
    for i in range(F):
        np.testing.assert_allclose(S[i], Ainv[i * s : (i + 1) * s, i * s : (i + 1) * s], atol=1e-10)
    assert float(bt.logdet(chol)) == pytest.approx(np.linalg.slogdet(A)[1], rel=1e-11)
    # diagonal blocks of A^-1 H A^-1 for H acting on the first 3 components of each state
    H3 = rng.normal(size=(F, 3, 3))
    H3 = H3 @ np.swapaxes(H3, 1, 2)
    Hd = np.zeros_like(A)
    for i in range(F):
        Hd[i * s : i * s + 3, i * s : i * s + 3] = H3[i]
    X = Ainv @ Hd @ Ainv
    got = np.asarray(bt.diag_sandwich(chol, jnp.asarray(H3)))
    for i in range(F):
        np.testing.assert_allclose(
            got[i], X[i * s : (i + 1) * s, i * s : (i + 1) * s], atol=1e-10 * np.abs(X).max()
        )
    ch2, y = bt.factor_forward(jnp.asarray(D), jnp.asarray(E), jnp.asarray(b))
    np.testing.assert_allclose(np.asarray(bt.back_substitute(ch2, y)).ravel(), x, rtol=1e-10)


def test_prior_model_closed_forms():
    dt = np.array([0.5, 2.0])
    A, Qinv = _transition(jnp.asarray(dt), 2)
    for i, h in enumerate(dt):
        Q = np.array([[h**3 / 3, h**2 / 2], [h**2 / 2, h]])  # white-noise acceleration
        np.testing.assert_allclose(np.linalg.inv(np.asarray(Qinv[i])), Q, rtol=1e-12)
        np.testing.assert_allclose(np.asarray(A[i]), [[1, h], [0, 1]])
    Q3, _ = _q_unit(3)
    np.testing.assert_allclose(Q3[0], [1 / 20, 1 / 8, 1 / 6])
    # order 1: the prior is the first-difference penalty sum |x_{i+1} - x_i|^2 / (q dt_i)
    x = np.random.default_rng(0).normal(size=(3, 3))
    A1, Q1 = _transition(jnp.asarray(dt), 1)
    ref = sum(np.sum((x[i + 1] - x[i]) ** 2) / (0.7 * dt[i]) for i in range(2))
    assert float(_prior_cost(jnp.asarray(x), A1, Q1, 1 / 0.7, 1)) == pytest.approx(ref)


def _map_objective(P, uv, times, q, sigma, states):
    """The MAP objective written densely (reference for the structured solver)."""
    X, V = states[:, 0], states[:, 1]
    h = jnp.einsum("fij,fj->fi", P[:, :, :3], X) + P[:, :, 3]
    e = h[:, :2] / h[:, 2:3] - uv
    data = jnp.sum(e * e) / sigma**2
    d = jnp.diff(times)[:, None, None]
    Qi = q * jnp.concatenate(
        [jnp.concatenate([d**3 / 3, d**2 / 2], 2), jnp.concatenate([d**2 / 2, d], 2)], 1
    )
    r = jnp.stack([X[1:] - X[:-1] - d[:, 0] * V[:-1], V[1:] - V[:-1]], axis=1)  # (F-1, 2, 3)
    return data + jnp.sum(r * jnp.linalg.solve(Qi, r))


def test_result_is_the_map_estimate(rng):
    s = robot_scene(rng, F=30, mode="random", noise=0.4, irregular=True)
    res = SMOOTH_Q(s["P"], s["uv"], s["times"], 0.1)
    assert int(res.status) == jt.Status.OK
    args = (jnp.asarray(s["P"]), jnp.asarray(s["uv"]), jnp.asarray(s["times"]), 0.1, 0.4)
    f = jax.jit(lambda st: _map_objective(*args, st))
    g = np.asarray(jax.grad(f)(res.states))
    scale = np.asarray(jax.grad(f)(res.states + 1e-4))
    assert np.linalg.norm(g) < 1e-6 * np.linalg.norm(scale)
    # posterior covariance = inverse Hessian of the (Gauss-Newton) objective at the optimum
    H = jax.jit(jax.hessian(f))(res.states).reshape(180, 180)
    cov0 = np.linalg.inv(np.asarray(H))[:6, :6] * 2.0  # objective is -2 log posterior
    np.testing.assert_allclose(np.asarray(res.state_cov[0]), cov0, rtol=0.05)


def test_start_prior_is_part_of_the_map_objective(rng):
    s = robot_scene(rng, F=30, mode="random", noise=0.4, irregular=True)
    v0 = (s["X"][1] - s["X"][0]) / (s["times"][1] - s["times"][0])
    mean = np.stack([s["X"][0] + 0.01, v0 - 0.05])  # a prior that disagrees a little
    cov = np.diag([0.02**2] * 3 + [0.1**2] * 3)
    res = smooth_trajectory(
        s["P"],
        s["uv"],
        s["times"],
        pixel_sigma=0.4,
        process_psd=0.1,
        iterations=6,
        start_mean=mean,
        start_cov=cov,
    )
    assert int(res.status) == jt.Status.OK
    args = (jnp.asarray(s["P"]), jnp.asarray(s["uv"]), jnp.asarray(s["times"]), 0.1, 0.4)
    Ci = jnp.asarray(np.linalg.inv(cov))

    def f(st):
        d0 = (st[0] - mean).reshape(-1)
        return _map_objective(*args, st) + d0 @ Ci @ d0

    f = jax.jit(f)
    g = np.asarray(jax.grad(f)(res.states))
    scale = np.asarray(jax.grad(f)(res.states + 1e-4))
    assert np.linalg.norm(g) < 1e-6 * np.linalg.norm(scale)
    free = smooth_trajectory(s["P"], s["uv"], s["times"], pixel_sigma=0.4, process_psd=0.1)
    assert not np.allclose(np.asarray(free.states[0]), np.asarray(res.states[0]), atol=1e-6)


def test_start_prior_per_point_or_shared_pins_the_first_state(rng):
    # slow camera: without the prior the scale along the rays is free (about 1 m off);
    # the prior pins the first state, but not the scale at later frames
    s = robot_scene(rng, F=60, mode="slow", noise=0.4)
    v0 = (s["X"][1] - s["X"][0]) / (s["times"][1] - s["times"][0])
    mean = np.stack([s["X"][0], v0])
    cov = np.diag([1e-3**2] * 3 + [1e-2**2] * 3)
    uvs = np.stack([s["uv"], s["uv"]])

    def run(**start):
        return smooth_points(s["P"], uvs, s["times"], pixel_sigma=0.4, covariance=False, **start)

    free = run()
    fixed = run(start_mean=np.stack([mean, mean]), start_cov=cov)
    shared = run(start_mean=mean, start_cov=cov)
    np.testing.assert_array_equal(np.asarray(shared.points), np.asarray(fixed.points))
    e_free, e_fixed = rmse(free.points[0], s["X"]), rmse(fixed.points[0], s["X"])
    assert e_free > 0.3 and e_fixed < 0.8 * e_free
    assert np.linalg.norm(np.asarray(fixed.points[0, 0]) - s["X"][0]) < 3e-3
    with pytest.raises(ValueError, match="start_mean and start_cov"):
        smooth_points(s["P"], uvs, s["times"], start_mean=mean)
    with pytest.raises(ValueError, match="start_mean"):
        smooth_trajectory(s["P"], s["uv"], s["times"], start_mean=mean[:1], start_cov=cov)
    with pytest.raises(ValueError, match="positive definite"):
        smooth_trajectory(s["P"], s["uv"], s["times"], start_mean=mean, start_cov=-cov)


@pytest.mark.parametrize("mode", ["random", "fast"])
def test_more_accurate_than_plain_dct_with_any_k(mode):
    rng = np.random.default_rng(7)
    ratios = []
    for _ in range(3):
        s = robot_scene(rng, F=80, mode=mode, noise=0.4)
        res = SMOOTH(s["P"], s["uv"], s["times"], jnp.ones(80))
        assert int(res.status) == jt.Status.OK
        basis = np.asarray(jt.dct_basis(s["times"], 12))
        dct = min(rmse(dct_fit(s["P"], s["uv"], basis[:, :k]), s["X"]) for k in (6, 8, 10, 12))
        ratios.append(dct / rmse(res.points, s["X"]))
    assert np.median(ratios) > 1.2, ratios


def test_marginal_likelihood_choice_near_oracle():
    rng = np.random.default_rng(3)
    for _ in range(2):
        s = robot_scene(rng, F=80, mode="random", noise=0.4)
        chosen = SMOOTH(s["P"], s["uv"], s["times"], jnp.ones(80))
        errs = [
            rmse(SMOOTH_Q(s["P"], s["uv"], s["times"], q).points, s["X"])
            for q in 10.0 ** np.arange(-3, 3.1)
        ]
        assert rmse(chosen.points, s["X"]) < 1.5 * min(errs)
        assert 1e-3 < float(chosen.process_psd) < 1e2


def test_chosen_q_gives_the_fixed_q_result_even_with_a_slow_camera():
    # The choice of q linearises at a mid-grid solution; the result must then be the one
    # for that q, not Gauss-Newton steps from the mid-grid depths (which, under a much
    # stiffer prior, ended pixels off or NaN on slow-camera scenes).
    rng = np.random.default_rng(3)
    s = robot_scene(rng, F=60, mode="slow", noise=0.4)
    uvs = np.stack([s["uv"], project_np(s["P"], s["X"] + 0.05) + rng.normal(size=(60, 2)) * 0.4])
    chosen = smooth_points(s["P"], uvs, s["times"], pixel_sigma=0.4, covariance=False)
    for i in range(2):
        fixed = smooth_trajectory(
            s["P"],
            uvs[i],
            s["times"],
            pixel_sigma=0.4,
            covariance=False,
            process_psd=float(chosen.process_psd[i]),
        )
        # a slow camera: the depth along the rays is the prior's, not the data's
        assert int(chosen.status[i]) == int(fixed.status) == jt.Status.DEGENERATE
        # The Gauss-Newton system here is numerically singular (its pivot at rounding
        # level, one reason for DEGENERATE), so rounding moves the solution along the
        # singular direction: the batched and the single solve agree to 1e-9 m at XLA's
        # default optimisation level and differ by 0.35 mm (0.17 against 0.22 px) at the
        # tests' -O0 on an AMD EPYC. The bug this guards against (Gauss-Newton from the
        # mid-grid depths) ended 3-45 mm apart or 0.43-0.54 px off on these two tracks.
        np.testing.assert_allclose(chosen.points[i], fixed.points, atol=1e-3)
        assert np.all(np.isfinite(chosen.points[i]))
        assert max(float(chosen.rms_px[i]), float(fixed.rms_px)) < 0.35  # pixel noise 0.4


def test_missing_frames_and_robust_loss(rng):
    s = robot_scene(rng, F=60, mode="random", noise=0.4)
    w = np.ones(60)
    w[20:26] = 0.0
    uv = s["uv"].copy()
    uv[20:26] = np.nan
    uv[::7] += 25.0  # outliers
    l2 = smooth_trajectory(s["P"], uv, s["times"], w, pixel_sigma=0.4, process_psd=0.1)
    hub = smooth_trajectory(
        s["P"], uv, s["times"], w, pixel_sigma=0.4, process_psd=0.1, loss="huber", iterations=8
    )
    assert int(hub.status) == jt.Status.OK and int(hub.num_observed) == 54
    assert np.all(np.isfinite(np.asarray(hub.points)))
    assert rmse(hub.points, s["X"]) < 0.3 * rmse(l2.points, s["X"])


def test_velocity_and_prediction_on_constant_velocity_motion(rng):
    times = np.arange(50) / 100.0
    X = np.array([0.1, -0.2, 0.8]) + times[:, None] * np.array([0.2, 0.1, -0.05])
    s = robot_scene(rng, F=50, mode="random", noise=0.0)
    P = s["P"]
    uv = project_np(P, X)
    res = smooth_trajectory(P, uv, times, pixel_sigma=0.1, process_psd=1e-3)
    np.testing.assert_allclose(np.asarray(res.points), X, atol=1e-6)
    np.testing.assert_allclose(
        np.asarray(res.velocities), np.tile([0.2, 0.1, -0.05], (50, 1)), atol=1e-4
    )
    mean, cov = predict(res, 0.04)
    np.testing.assert_allclose(
        np.asarray(mean[0]), X[-1] + 0.04 * np.array([0.2, 0.1, -0.05]), atol=1e-5
    )
    assert np.all(np.linalg.eigvalsh(np.asarray(cov)) > 0)
    assert np.trace(np.asarray(cov)[:3, :3]) > np.trace(np.asarray(res.cov[-1]))


def test_jit_vmap_and_batch_choice(rng):
    s = robot_scene(rng, F=40, mode="fast", noise=0.4)
    uvs = np.stack([s["uv"], s["uv"] + rng.normal(size=(40, 2)) * 0.4])
    kw = dict(pixel_sigma=0.4, process_psd=0.3, covariance=False)  # keeps compiles short
    batch = smooth_points(s["P"], uvs, s["times"], **kw)
    for i in range(2):
        one = smooth_trajectory(s["P"], uvs[i], s["times"], **kw)
        np.testing.assert_allclose(np.asarray(batch.points[i]), np.asarray(one.points), atol=1e-10)
    jit_one = jax.jit(lambda u: smooth_trajectory(s["P"], u, s["times"], **kw))
    np.testing.assert_allclose(
        np.asarray(jit_one(uvs[1]).points), np.asarray(one.points), atol=1e-10
    )
    q = float(select_process_psd(s["P"], uvs, s["times"], pixel_sigma=0.4))
    assert 1e-4 < q < 1e5


def test_gradient_matches_finite_differences(rng):
    s = robot_scene(rng, F=20, mode="random", noise=0.4)

    def f(uv):
        r = smooth_trajectory(
            s["P"],
            uv,
            s["times"],
            pixel_sigma=0.4,
            process_psd=0.1,
            iterations=2,
            covariance=False,
        )
        return jnp.sum(r.points[5] + r.points[12])

    # one compiled program gives the gradient and the values for the finite differences
    value_and_grad = jax.jit(jax.value_and_grad(f))
    uv = jnp.asarray(s["uv"])
    g = np.asarray(value_and_grad(uv)[1])
    d = rng.normal(size=uv.shape)
    eps = 1e-4
    fd = (value_and_grad(uv + eps * d)[0] - value_and_grad(uv - eps * d)[0]) / (2 * eps)
    assert float(np.sum(g * d)) == pytest.approx(float(fd), rel=1e-5)


def test_status_codes(rng):
    s = robot_scene(rng, F=20, mode="random", noise=0.4)
    w = np.zeros(20)
    w[3] = 1.0
    under = smooth_trajectory(s["P"], s["uv"], s["times"], w, process_psd=0.1)
    assert int(under.status) == jt.Status.UNDERDETERMINED
    uv = s["uv"].copy()
    uv[4] = np.nan
    bad = jax.jit(lambda u: smooth_trajectory(s["P"], u, s["times"], process_psd=0.1))(uv)
    assert int(bad.status) == jt.Status.NONFINITE


def test_bad_inputs(rng):
    s = robot_scene(rng, F=20, mode="random")
    P, uv, t = s["P"], s["uv"], s["times"]
    with pytest.raises(ValueError, match="times"):
        smooth_trajectory(P, uv, t[::-1])
    with pytest.raises(ValueError, match="uv"):
        smooth_trajectory(P, uv[:-1], t)
    with pytest.raises(ValueError, match="order"):
        smooth_trajectory(P, uv, t, order=4)
    with pytest.raises(ValueError, match="loss"):
        smooth_trajectory(P, uv, t, loss="tukey")
    with pytest.raises(ValueError, match="pixel_sigma"):
        smooth_trajectory(P, uv, t, pixel_sigma=-1.0)
    with pytest.raises(ValueError, match="process_psd"):
        smooth_trajectory(P, uv, t, process_psd=0.0)
    with pytest.raises(ValueError, match="criterion"):
        smooth_trajectory(P, uv, t, criterion="gcv")
    bad = uv.copy()
    bad[2] = np.nan
    with pytest.raises(ValueError, match="uv"):
        smooth_trajectory(P, bad, t)
    with pytest.raises(ValueError, match="uv"):
        smooth_points(P, uv, t)


def _search_reference(f, grid, rounds):
    """The density search written plainly: the grid, then ``rounds`` times the two geometric
    midpoints about the minimum (kept off the ends), going on with those five points."""
    grid = np.asarray(grid, float)
    crit = np.array([f(q) for q in grid])
    for _ in range(rounds):
        i = int(np.clip(np.argmin(np.where(np.isfinite(crit), crit, np.inf)), 1, grid.size - 2))
        mid = np.sqrt(grid[[i - 1, i]] * grid[[i, i + 1]])
        c_mid = [f(q) for q in mid]
        grid = np.array([grid[i - 1], mid[0], grid[i], mid[1], grid[i + 1]])
        crit = np.array([crit[i - 1], c_mid[0], crit[i], c_mid[1], crit[i + 1]])
    return grid, crit


@pytest.mark.parametrize("grid_size", [3, 5, 10])
def test_density_search_in_one_loop_equals_the_plain_search(grid_size):
    """The marginal-likelihood search evaluates the grid and its refinements in one loop
    (one compiled copy of the evidence); it must visit the same densities as the plain
    search, also with the minimum at either end of the grid and with non-finite values."""
    grid = default_psd_grid(2)[:: max(1, 10 // grid_size)][:grid_size]
    search = jax.jit(_ml_grid_search, static_argnums=(0, 2))
    centres = (grid[0] / 10, grid[1] * 1.7, grid[grid_size // 2] * 0.6, grid[-1] * 10)
    for centre, fail_top in itertools.product(centres, (False, True)):

        def f(q, centre=centre, fail_top=fail_top):
            v = (jnp.log(q) - np.log(centre)) ** 2
            return jnp.where(fail_top & (q > grid[-1] * 0.99), jnp.nan, v)

        for rounds in (0, 1, 2):
            ref_q, ref_c = _search_reference(lambda q: float(f(q)), grid, rounds)
            q, c = search(f, jnp.asarray(grid), rounds)
            np.testing.assert_allclose(np.asarray(q), ref_q, rtol=1e-14)
            np.testing.assert_allclose(np.asarray(c), ref_c, rtol=1e-12, atol=1e-14)
    with pytest.raises(ValueError, match="at least 3 densities"):
        _ml_grid_search(lambda q: q, jnp.asarray(grid[:2]), 1)

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraj as jt
from jaxtraj.estimators import reconstruct_regularised, roughness_penalty, select_penalty_cv
from jaxtraj.sim.scene import make_scene
from tests.test_estimators_scenes import dct_fit, rmse, robot_scene


@pytest.mark.parametrize("order", [1, 2, 3])
def test_roughness_equals_integral_of_squared_derivative(rng, order):
    times = np.sort(rng.uniform(0.0, 3.0, 40))
    basis = jt.DCTBasis.from_times(times, 12)
    beta = rng.normal(size=(12, 3))
    t = np.linspace(float(basis.t0), float(basis.t1), 20001)
    if order < 3:
        deriv = np.asarray(basis(t, derivative=order))
    else:  # central difference of the analytic second derivative
        h = 1e-5
        deriv = (np.asarray(basis(t + h, 2)) - np.asarray(basis(t - h, 2))) / (2 * h)
    x = deriv @ beta
    integral = np.trapezoid(np.sum(x**2, axis=1), t)
    ours = float(np.sum(np.asarray(roughness_penalty(basis, order)) * np.sum(beta**2, axis=1)))
    assert ours == pytest.approx(integral, rel=1e-6)
    assert float(roughness_penalty(basis, order)[0]) == 0.0


def test_zero_penalty_equals_plain_solve_and_jit_vmap(rng):
    s = make_scene(jax.random.PRNGKey(2), n_frames=40, noise_px=0.3)
    Phi = jt.dct_basis(s.times, 8)
    plain = jt.reconstruct(s.P, s.uv, Phi, s.weights)
    zero = jt.reconstruct(s.P, s.uv, Phi, s.weights, penalty=jnp.zeros(8))
    np.testing.assert_allclose(zero.points, plain.points, atol=1e-12)
    pen = jnp.linspace(0.0, 1e3, 8)
    eager = jt.reconstruct(s.P, s.uv, Phi, s.weights, penalty=pen)
    jitted = jax.jit(lambda p: jt.reconstruct(s.P, s.uv, Phi, s.weights, penalty=p))(pen)
    np.testing.assert_allclose(jitted.points, eager.points, atol=1e-12)
    pens = jnp.stack([pen, 2 * pen])
    batched = jax.jit(jax.vmap(lambda p: jt.reconstruct(s.P, s.uv, Phi, s.weights, penalty=p)))(
        pens
    )
    for i in range(2):
        one = jt.reconstruct(s.P, s.uv, Phi, s.weights, penalty=pens[i])
        np.testing.assert_allclose(batched.points[i], one.points, atol=1e-11)


@pytest.mark.parametrize("camera,speed", [("random", 0.3), ("smooth", 3.0)])
def test_regularised_beats_every_fixed_k(camera, speed):
    s = make_scene(jax.random.PRNGKey(0), camera=camera, camera_speed=speed, n_frames=80)
    fixed = []
    # the fixed-k baselines by dense least squares (tests/test_estimators_scenes.dct_fit)
    Phi = np.asarray(jt.dct_basis(s.times, 30))
    for k in (6, 10, 15, 20, 30):
        points = dct_fit(s.P, s.uv, Phi[:, :k], s.weights)
        fixed.append(np.mean(np.linalg.norm(np.asarray(points) - np.asarray(s.points), axis=1)))
    res, basis, choice = reconstruct_regularised(s.P, s.uv, s.times, s.weights)
    err = np.mean(np.linalg.norm(np.asarray(res.points - s.points), axis=1))
    assert basis.k == 60 and 2 * 80 < 3 * 60  # beyond the counting bound of the plain DCT
    assert int(res.status) == jt.Status.OK
    assert err <= 1.05 * min(fixed), (err, fixed)
    # The choice is an interior minimum of the cross-validation curve.
    i = int(np.argmin(np.asarray(choice.cv_rms_px)))
    assert 0 < i < choice.grid.shape[0] - 1


def test_gain_weighted_penalty_choice_on_a_fast_camera():
    """On a fast, smooth camera path the weakest penalties reproject best but are far
    off along the rays; weighting the held-out error by the gain picks a stiffer one."""
    rng = np.random.default_rng(5)
    for _ in range(2):  # the second fast scene of this stream (F = 80 as above: one compile)
        s = robot_scene(rng, F=80, mode="fast", noise=0.4)
    basis = jt.DCTBasis.from_times(s["times"], 60)
    Phi, rough = basis(s["times"]), roughness_penalty(basis)
    choice = select_penalty_cv(s["P"], s["uv"], basis, s["times"])
    gain, cv = np.asarray(choice.gain), np.asarray(choice.cv_rms_px)
    np.testing.assert_allclose(choice.criterion, cv * np.maximum(1.0, gain / 20.0), rtol=1e-12)
    plain = choice.grid[int(np.argmin(cv))]  # rule="reprojection"
    assert float(choice.lam) > float(plain)
    chosen = jt.reconstruct(s["P"], s["uv"], Phi, penalty=choice.lam * rough)
    weak = jt.reconstruct(s["P"], s["uv"], Phi, penalty=plain * rough)
    assert rmse(chosen.points, s["X"]) < 0.6 * rmse(weak.points, s["X"])
    assert float(chosen.gain) == pytest.approx(float(gain[int(np.argmin(choice.criterion))]))


@pytest.mark.parametrize("folds", [3, 4, 20, 30])  # held-out blocks of 20, 16, 4 and 2 rows
def test_kfold_curve_equals_refits_of_each_fold(folds):
    """The K-fold choice's held-out RMS at every weight (from the fit on all frames and the
    exact update for leaving each fold out) equals refitting each fold's training frames
    with the solver, a missing frame included and folds of unequal size (30 frames in 4 or
    20), and its gain that of the solver on all frames. The fold sizes take the three ways
    of forming and solving the held-out blocks (LAPACK; written-out Cholesky; one product
    of row pairs, for folds of 2 frames and for leave-one-frame-out)."""
    s = make_scene(jax.random.PRNGKey(8), n_frames=30, noise_px=0.5)
    basis = jt.DCTBasis.from_times(s.times, 6)
    Phi, rough = basis(s.times), roughness_penalty(basis)
    uv = np.asarray(s.uv).copy()
    w = np.ones(30)
    w[7], uv[7] = 0.0, np.nan  # a missing detection
    grid = np.logspace(-3, 5, 5)
    choice = select_penalty_cv(s.P, uv, basis, s.times, w, grid=grid, folds=folds)
    held = np.arange(30)[None, :] % folds == np.arange(folds)[:, None]
    direct = []
    for j, lam in enumerate(grid):
        per_fold = []
        for mask in held:
            if not np.any(mask & (w > 0)):
                continue  # the missing frame's own fold (leave-one-frame-out) holds nothing
            fit = jt.reconstruct(s.P, uv, Phi, np.where(mask, 0.0, w), penalty=lam * rough)
            proj = np.einsum("fij,fj->fi", np.asarray(s.P)[:, :, :3], fit.points)
            proj = proj + np.asarray(s.P)[:, :, 3]
            err2 = np.sum((proj[:, :2] / proj[:, 2:] - uv) ** 2, axis=1)
            per_fold.append(np.sqrt(np.mean(err2[mask & (w > 0)])))
        direct.append(np.mean(per_fold))
        if folds == 3:
            full = jt.reconstruct(s.P, uv, Phi, w, penalty=lam * rough)
            assert float(choice.gain[j]) == pytest.approx(float(full.gain), rel=0.02)
    np.testing.assert_allclose(choice.cv_rms_px, direct, rtol=1e-7)


def test_bad_input(rng):
    s = make_scene(jax.random.PRNGKey(1), n_frames=30)
    Phi = jt.dct_basis(s.times, 6)
    with pytest.raises(ValueError, match=r"penalty: expected shape \(6,\)"):
        jt.reconstruct(s.P, s.uv, Phi, s.weights, penalty=jnp.ones(5))
    with pytest.raises(ValueError, match="penalty: must be finite and >= 0"):
        jt.reconstruct(s.P, s.uv, Phi, s.weights, penalty=-jnp.ones(6))
    with pytest.raises(ValueError, match="order"):
        roughness_penalty(jt.DCTBasis.from_times(s.times, 6), order=4)
    for bad in (1, len(s.times) + 1, 2.5, True):
        with pytest.raises(ValueError, match="folds"):
            select_penalty_cv(s.P, s.uv, jt.DCTBasis.from_times(s.times, 6), s.times, folds=bad)
    with pytest.raises(ValueError, match="times"):
        select_penalty_cv(s.P, s.uv, jt.DCTBasis.from_times(s.times, 6), s.times[:-1])
    with pytest.raises(ValueError, match="rule"):
        select_penalty_cv(s.P, s.uv, jt.DCTBasis.from_times(s.times, 6), s.times, rule="gcv")


def test_batched_points_with_penalty_equal_loop():
    s = make_scene(jax.random.PRNGKey(4), n_frames=30, noise_px=0.3)
    basis = jt.DCTBasis.from_times(s.times, 25)  # 2 * 30 < 3 * 25: needs the penalty
    Phi, pen = basis(s.times), 1e3 * roughness_penalty(basis)
    uv = jnp.stack([s.uv, s.uv + 0.5])
    many = jt.reconstruct_points(s.P, uv, Phi, penalty=pen)
    for n in range(2):
        one = jt.reconstruct(s.P, uv[n], Phi, penalty=pen)
        np.testing.assert_allclose(many.points[n], one.points, atol=1e-11)
    assert np.all(np.asarray(many.status) == jt.Status.OK)
    with pytest.raises(ValueError, match="k=25 is too large"):
        jt.reconstruct_points(s.P, uv, Phi)


def test_batched_driver_equals_per_point_choice_and_solve():
    """reconstruct_regularised_points: each point's weight is select_penalty_cv's choice
    for it (or one shared weight), and the points equal the single-point solves (with a
    weight per point they come from the choice's eigendecomposition, the gain from its
    eigenbasis: within 2 % of the solver's, both 8 Lanczos steps)."""
    from jaxtraj.estimators import reconstruct_regularised_points

    s = make_scene(jax.random.PRNGKey(6), n_frames=30, noise_px=0.3)
    rng = np.random.default_rng(6)
    uv = np.stack([np.asarray(s.uv) + rng.normal(size=(30, 2)) * sd for sd in (0.0, 3.0)])
    grid = np.logspace(-2, 6, 3)
    res, basis, choice = reconstruct_regularised_points(s.P, uv, s.times, k=6, grid=grid, folds=2)
    assert basis.k == 6 and res.points.shape == (2, 30, 3)
    Phi, rough = basis(s.times), roughness_penalty(basis)
    for n in range(2):
        one = select_penalty_cv(s.P, uv[n], basis, s.times, grid=grid, folds=2)
        assert float(choice.lam[n]) == float(one.lam)
        np.testing.assert_allclose(choice.criterion[n], one.criterion, rtol=1e-9)
        ref = jt.reconstruct(s.P, uv[n], Phi, penalty=one.lam * rough)
        # the fit at the chosen weight comes from the choice's decomposition
        np.testing.assert_allclose(res.points[n], ref.points, atol=1e-10)
        assert float(res.gain[n]) == pytest.approx(float(ref.gain), rel=0.02)  # both Lanczos
        assert int(res.status[n]) == int(ref.status)
    assert float(choice.lam[1]) > float(choice.lam[0])  # noisier track, stiffer penalty
    res_shared, _, sc = reconstruct_regularised_points(
        s.P, uv, s.times, k=6, grid=grid, folds=2, shared=True
    )
    assert float(sc.lam[0]) == float(sc.lam[1])
    best = grid[int(np.argmin(np.mean(np.asarray(choice.criterion), axis=0)))]
    assert float(sc.lam[0]) == pytest.approx(best)
    ref = jt.reconstruct(s.P, uv[1], Phi, penalty=sc.lam[1] * rough)
    np.testing.assert_allclose(res_shared.points[1], ref.points, atol=1e-10)
    assert np.asarray(sc.tracks).tolist() == [0, 1]
    # a shared weight cross-validated on a subset of the tracks (here the first): the
    # noisy second track is solved with the clean track's weight
    res_sub, _, s1 = reconstruct_regularised_points(
        s.P, uv, s.times, k=6, grid=grid, folds=2, shared=True, cv_points=1
    )
    assert np.asarray(s1.tracks).tolist() == [0] and s1.criterion.shape == (1, 3)
    assert float(s1.lam[0]) == float(choice.lam[0])
    np.testing.assert_allclose(s1.criterion[0], choice.criterion[0], rtol=1e-9)
    ref = jt.reconstruct(s.P, uv[1], Phi, penalty=choice.lam[0] * rough)
    np.testing.assert_allclose(res_sub.points[1], ref.points, atol=1e-10)
    with pytest.raises(ValueError, match="cv_points"):
        reconstruct_regularised_points(s.P, uv, s.times, k=6, shared=True, cv_points=0)


def _gcv_direct(P, uv, Phi, rough, lam):
    """sqrt(GCV) of the penalised ray-constraint fit by dense NumPy: solve, residual, trace."""
    P, uv, Phi = (np.asarray(a, np.float64) for a in (P, uv, Phi))
    rows = P[:, :2, :] - uv[:, :, None] * P[:, 2, None, :]  # (F, 2, 4)
    X = np.einsum("fri,fk->frki", rows[:, :, :3], Phi).reshape(2 * len(P), -1)
    y = -rows[:, :, 3].reshape(-1)
    N = X.T @ X + lam * np.diag(np.repeat(np.asarray(rough), 3))
    beta = np.linalg.solve(N, X.T @ y)
    rss = np.sum((y - X @ beta) ** 2)
    dof = len(y) - np.trace(np.linalg.solve(N, X.T @ X))
    return np.sqrt(len(y) * rss / dof**2)


def test_gcv_choice_equals_direct_computation_and_its_fit_the_solver():
    """criterion="gcv": the GCV curve equals a dense refit at every grid value, the fit
    and gain are those of the solver at the chosen weight, and the shared weight is the
    smallest mean criterion."""
    from jaxtraj.estimators import reconstruct_regularised_points

    s = make_scene(jax.random.PRNGKey(6), n_frames=30, noise_px=0.3)
    rng = np.random.default_rng(6)
    uv = np.stack([np.asarray(s.uv) + rng.normal(size=(30, 2)) * sd for sd in (0.0, 3.0)])
    grid = np.logspace(-2, 6, 5)
    res, basis, choice = reconstruct_regularised_points(
        s.P, uv, s.times, k=6, grid=grid, criterion="gcv"
    )
    Phi, rough = basis(s.times), roughness_penalty(basis)
    for n in range(2):
        direct = [_gcv_direct(s.P, uv[n], Phi, rough, lam) for lam in grid]
        np.testing.assert_allclose(choice.cv_rms_px[n], direct, rtol=1e-7)
        ref = jt.reconstruct(s.P, uv[n], Phi, penalty=choice.lam[n] * rough)
        np.testing.assert_allclose(res.points[n], ref.points, atol=1e-9)
        assert float(res.gain[n]) == pytest.approx(float(ref.gain), rel=0.02)  # both Lanczos
        assert int(res.status[n]) == int(ref.status)
        i = int(np.argmin(np.asarray(choice.criterion[n])))
        assert float(choice.lam[n]) == pytest.approx(grid[i])
    assert float(choice.lam[1]) > float(choice.lam[0])  # noisier track, stiffer penalty
    res_shared, _, sc = reconstruct_regularised_points(
        s.P, uv, s.times, k=6, grid=grid, criterion="gcv", shared=True
    )
    best = grid[int(np.argmin(np.mean(np.asarray(choice.criterion), axis=0)))]
    assert float(sc.lam[0]) == float(sc.lam[1]) == pytest.approx(best)
    ref = jt.reconstruct(s.P, uv[1], Phi, penalty=sc.lam[1] * rough)
    np.testing.assert_allclose(res_shared.points[1], ref.points, atol=1e-10)
    with pytest.raises(ValueError, match="criterion"):
        reconstruct_regularised_points(s.P, uv, s.times, k=6, criterion="loo")


def test_gcv_choice_is_as_accurate_as_kfold_on_random_and_fast_cameras():
    """On well-posed robot scenes the weights by GCV and by leave-one-frame-out CV give
    3D errors within 15 % of the 5-fold choice's (and all three flag a slow camera's
    tracks)."""
    from jaxtraj.estimators import reconstruct_regularised_points

    rng = np.random.default_rng(3)
    for mode, flagged in (("random", False), ("fast", False), ("slow", True)):
        s = robot_scene(rng, F=60, rate=15.0, mode=mode, noise=0.3)
        uv = np.asarray(s["uv"])[None]
        errs = {}
        for crit, folds in (("kfold", 5), ("gcv", 5), ("kfold", 60)):
            res, _, _ = reconstruct_regularised_points(
                s["P"], uv, s["times"], k=20, criterion=crit, folds=folds
            )
            errs[crit, folds] = rmse(res.points[0], s["X"])
            assert (int(res.status[0]) != jt.Status.OK) == flagged, (mode, crit, folds)
        if not flagged:
            assert errs["gcv", 5] <= 1.15 * errs["kfold", 5], (mode, errs)
            assert errs["kfold", 60] <= 1.15 * errs["kfold", 5], (mode, errs)


def test_fit_collapsed_towards_a_slow_camera_is_flagged_by_its_reprojection_rms():
    """A stiff penalty on a slow camera can pull the fit of the ray constraints towards the
    camera centres, which satisfy every constraint: 1.4 m off at 48 px RMS, with a small
    gain and kappa of the fit (this weight is the 5-fold choice for this track). Two tests
    flag it: the reprojection RMS and the solver's depth test on the fit moved onto its
    rays (which alone still flags it with the first test off). A well-posed track keeps
    its status OK."""
    from jaxtraj.estimators import reconstruct_regularised_points
    from jaxtraj.estimators.regularised import MAX_RMS_PX
    from jaxtraj.solve import MAX_DEPTH_UNCERTAINTY

    rng = np.random.default_rng(102)
    for _ in range(3):  # the third slow scene of this stream
        s = robot_scene(rng, F=150, rate=15.0, mode="slow", noise=0.3)
    uv = np.asarray(s["uv"])[None]
    res, _, _ = reconstruct_regularised_points(s["P"], uv, s["times"], k=60, lam=1e8)
    assert rmse(res.points[0], s["X"]) > 1.0  # metres off ...
    assert float(res.rms_px[0]) > 5 * MAX_RMS_PX and float(res.gain[0]) < 20.0
    assert int(res.status[0]) == jt.Status.DEGENERATE  # ... and flagged
    off, _, _ = reconstruct_regularised_points(
        s["P"], uv, s["times"], k=60, lam=1e8, max_rms_px=np.inf
    )
    # without the reprojection test, the depths on the rays are not determined either
    assert int(off.status[0]) == jt.Status.DEGENERATE
    assert float(off.depth_uncertainty[0]) > MAX_DEPTH_UNCERTAINTY
    good = robot_scene(np.random.default_rng(100), F=150, rate=15.0, mode="random", noise=0.3)
    res, _, _ = reconstruct_regularised_points(
        good["P"], np.asarray(good["uv"])[None], good["times"], k=60, lam=1.0
    )
    assert int(res.status[0]) == jt.Status.OK and float(res.rms_px[0]) < 1.0
    for bad in (0.0, -1.0, True):
        with pytest.raises(ValueError, match="max_rms_px"):
            reconstruct_regularised_points(s["P"], uv, s["times"], k=60, max_rms_px=bad)
        with pytest.raises(ValueError, match="max_rms_px"):
            reconstruct_regularised(s["P"], uv[0], s["times"], k=60, max_rms_px=bad)


def test_regularised_covariance_covers_the_penalty_bias_along_the_rays():
    """A limb-like point (outside any small DCT span) under a 20 deg/frame orbit and a
    fast robot-like camera, k = 60, lam = 1 (the 5-fold choice on both): the posterior
    form of the penalty alone reports 0.5x the error on the orbit's status-OK track
    (error / sd 1.9: the penalty sets the depth along the rays, which the pixels do not
    see); with the along-ray bound ``kappa |x - c| / 2`` the error is 0.36-0.38 sd and the
    mean NEES (3 dof) 1.8-2.2. vmap over tracks equals the loop."""
    from jaxtraj.estimators import dct_covariance, regularised_covariance
    from tests._scenes import limb_scene

    def stats(e, cov):
        sd = np.sqrt(np.trace(cov, axis1=1, axis2=2))
        nees = np.einsum("fi,fij,fj->f", e, np.linalg.pinv(cov, hermitian=True), e)
        return np.mean(np.linalg.norm(e, axis=1) / sd), np.mean(nees)

    @jax.jit
    def cov_of(P, u, t, c):
        basis = jt.DCTBasis.from_times(t, 60)
        return regularised_covariance(P, u, t, basis, c, 1.0, pixel_sigma=0.5).points

    @jax.jit
    def alone(P, u, t, c):  # the posterior form without the along-ray bound
        basis = jt.DCTBasis.from_times(t, 60)
        pen = roughness_penalty(basis, 2)
        return dct_covariance(P, u, basis(t), c, pixel_sigma=0.5, penalty=pen).points

    fit = jax.jit(lambda P, u, t: reconstruct_regularised(P, u, t, lam=1.0)[0])
    for seed, camera in ((1, "orbit"), (9, "fast")):
        t, X, P, uv = limb_scene(np.random.default_rng(seed), camera=camera, deg=20.0)
        res = fit(P, uv, t)
        e = np.asarray(res.points) - X
        ratio, nees = stats(e, np.asarray(cov_of(P, uv, t, res.coeffs)))
        assert ratio < 0.6 and nees < 3.0
        if camera == "orbit":
            assert int(res.status) == jt.Status.OK
            assert stats(e, np.asarray(alone(P, uv, t, res.coeffs)))[0] > 1.5
            # batched over tracks sharing the cameras
            uv2 = np.stack([uv, uv + 0.3])
            second = fit(P, uv2[1], t).coeffs
            coeffs = np.stack([res.coeffs, second])
            batched = jax.jit(jax.vmap(cov_of, (None, 0, None, 0)))(P, uv2, t, coeffs)
            for i in range(2):
                one = np.asarray(cov_of(P, uv2[i], t, coeffs[i]))
                np.testing.assert_allclose(np.asarray(batched[i]), one, rtol=1e-8)
            basis = jt.DCTBasis.from_times(t, 60)
            for bad in (-1.0, np.nan, np.inf):
                with pytest.raises(ValueError, match="lam"):
                    regularised_covariance(P, uv, t, basis, res.coeffs, bad)

"""Kalman filter / RTS smoother from a known start: exactness of the recursions against a
dense Gaussian posterior, the sigma-point moments, agreement with the posterior-mode
smoother where the camera fixes the depth, the slow-camera case it exists for, causality,
missing frames, gating, batching, gradients and bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraj as jt
from jaxtraj.estimators import filter_points, filter_trajectory, predict, smooth_trajectory
from jaxtraj.estimators.filtering import (
    _moments_cubature,
    _moments_extended,
    _process,
    _project,
    kalman_smoother,
)
from tests.test_estimators_scenes import rmse, robot_scene

CUBATURE, EXTENDED = jax.jit(_moments_cubature), jax.jit(_moments_extended)
F = 60  # one size for all scene tests: fewer compiles
START_COV = np.diag([0.05**2] * 3 + [0.2**2] * 3)


def true_start(s):
    v0 = (s["X"][1] - s["X"][0]) / (s["times"][1] - s["times"][0])
    return np.stack([s["X"][0], v0])


def test_recursions_equal_the_dense_gaussian_posterior(rng):
    # a linear measurement z_i = H_i x_i + c_i: filter + RTS must give the exact posterior
    F, s = 12, 6
    times = np.cumsum(rng.uniform(0.005, 0.02, F))
    A, Q = _process(jnp.asarray(np.diff(times)), 2, 0.3)
    A = np.concatenate([np.eye(s)[None], np.asarray(A)])
    Q = np.concatenate([np.zeros((1, s, s)), np.asarray(Q)])
    H = rng.normal(size=(F, 2, s))
    c = rng.normal(size=(F, 2))
    z = rng.normal(size=(F, 2))
    w = rng.uniform(0.5, 2.0, F)
    w[4] = 0.0  # a missing frame
    m0, C0 = rng.normal(size=s), START_COV
    sigma2 = 0.3

    def moments(frame, m, C):
        Hi, ci = frame
        return Hi @ m + ci, Hi @ C @ Hi.T, C @ Hi.T

    args = ((jnp.asarray(H), jnp.asarray(c)), z, w, A, Q, m0, C0, sigma2, jnp.inf)
    ms, Cs, used = kalman_smoother(moments, *args, True)
    mf, Cf, _ = kalman_smoother(moments, *args, False)

    # dense: x = (x_0 .. x_{F-1}); prior x_0 ~ N(m0, C0), x_i = A_i x_{i-1} + N(0, Q_i)
    n = F * s
    T = np.zeros((n, n))  # x = T e, e = (x_0 - m0 offsets, process noises)
    for i in range(F):
        T[i * s : (i + 1) * s, i * s : (i + 1) * s] = np.eye(s)
        for j in range(i):
            Phi = np.eye(s)
            for k in range(j + 1, i + 1):
                Phi = A[k] @ Phi
            T[i * s : (i + 1) * s, j * s : (j + 1) * s] = Phi
    mean = T @ np.concatenate([m0, np.zeros(n - s)])
    cov = T @ np.diag(np.zeros(n)) @ T.T
    noise = np.zeros((n, n))
    noise[:s, :s] = C0
    for i in range(1, F):
        noise[i * s : (i + 1) * s, i * s : (i + 1) * s] = Q[i]
    cov = T @ noise @ T.T

    def condition(frames):
        Hd = np.zeros((2 * len(frames), n))
        for r, i in enumerate(frames):
            Hd[2 * r : 2 * r + 2, i * s : (i + 1) * s] = H[i]
        R = np.diag(np.repeat(sigma2 / w[frames], 2))
        S = Hd @ cov @ Hd.T + R
        K = cov @ Hd.T @ np.linalg.inv(S)
        y = z[frames].ravel() - Hd @ mean - c[frames].ravel()
        return mean + K @ y, cov - K @ S @ K.T

    seen = [i for i in range(F) if w[i] > 0]
    post_m, post_C = condition(seen)
    np.testing.assert_allclose(np.asarray(ms), post_m.reshape(F, s), atol=1e-9)
    for i in (0, 5, F - 1):
        block = post_C[i * s : (i + 1) * s, i * s : (i + 1) * s]
        np.testing.assert_allclose(np.asarray(Cs[i]), block, atol=1e-9)
    # the filtered state at frame i conditions on frames <= i only
    for i in (3, 7):
        fm, fC = condition([j for j in seen if j <= i])
        np.testing.assert_allclose(np.asarray(mf[i]), fm[i * s : (i + 1) * s], atol=1e-9)
        np.testing.assert_allclose(
            np.asarray(Cf[i]), fC[i * s : (i + 1) * s, i * s : (i + 1) * s], atol=1e-9
        )
    assert np.asarray(used).tolist() == [bool(x > 0) for x in w]


def test_cubature_moments(rng):
    s = robot_scene(rng, F=2, mode="smooth", noise=0.0)
    P = jnp.asarray(s["P"][0])
    m = jnp.asarray(np.concatenate([s["X"][0], [0.1, 0.0, 0.0]]))
    # small covariance: the cubature rule and the linearisation agree
    small = jnp.asarray(np.diag([1e-8] * 3 + [1e-6] * 3))
    cub, ext = CUBATURE(P, m, small), EXTENDED(P, m, small)
    for a, b in zip(cub, ext, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(np.asarray(cub[0]), s["clean"][0], atol=1e-9)
    # a wider one (1 cm): the cubature mean has the second-order (curvature) term of
    # E[pi(x)] that the linearisation leaves out; the rest is of fourth order
    wide = jnp.diag(jnp.asarray([0.01**2] * 3 + [0.1**2] * 3))
    hess = jax.jit(jax.hessian(lambda x: _project(P, x)))(m[:3])  # (2, 3, 3)
    second = _project(P, m[:3]) + 0.5 * jnp.einsum("aij,ij->a", hess, wide[:3, :3])
    cub, ext = CUBATURE(P, m, wide), EXTENDED(P, m, wide)
    gap = float(jnp.linalg.norm(ext[0] - second))
    assert gap > 1e-3  # the term is there (px)
    assert float(jnp.linalg.norm(cub[0] - second)) < 0.02 * gap
    # the velocity part of the cross-covariance is zero when uncorrelated with the position
    np.testing.assert_allclose(np.asarray(cub[2])[3:], 0.0, atol=1e-12)


@pytest.mark.parametrize("rule", ["extended", "cubature"])
def test_agrees_with_the_posterior_mode_where_the_camera_fixes_the_depth(rng, rule):
    s = robot_scene(rng, F=F, mode="random", noise=0.4)
    kw = dict(pixel_sigma=0.4, process_psd=0.1, start_mean=true_start(s), start_cov=START_COV)
    filt = filter_trajectory(s["P"], s["uv"], s["times"], rule=rule, **kw)
    mode = smooth_trajectory(s["P"], s["uv"], s["times"], iterations=6, **kw)
    assert int(filt.status) == jt.Status.OK and int(filt.num_observed) == F
    e_filt, e_mode = rmse(filt.points, s["X"]), rmse(mode.points, s["X"])
    assert e_filt < 2e-3  # about 0.5 mm
    assert abs(e_filt - e_mode) < 0.25 * e_mode
    assert rmse(filt.points, mode.points) < 0.6 * e_mode
    # the covariances are those of a posterior on the same data (within a factor of 2)
    ratio = np.trace(np.asarray(filt.cov), axis1=1, axis2=2) / np.trace(
        np.asarray(mode.cov), axis1=1, axis2=2
    )
    assert 0.5 < np.median(ratio) < 2.0


def test_slow_camera_with_a_start_prior_beats_the_posterior_mode():
    # The reason the filter exists: with a slow camera the posterior mode of the same
    # model is drawn towards the camera along the rays, the filter keeps its start's depth.
    rng = np.random.default_rng(11)
    e_filt, e_mode = [], []
    for _ in range(3):
        s = robot_scene(rng, F=F, mode="slow", noise=0.4)
        kw = dict(pixel_sigma=0.4, process_psd=0.1, start_mean=true_start(s), start_cov=START_COV)
        filt = filter_trajectory(s["P"], s["uv"], s["times"], **kw)
        mode = smooth_trajectory(s["P"], s["uv"], s["times"], iterations=6, **kw)
        assert int(filt.status) == jt.Status.OK
        assert float(filt.rms_px) < 1.0  # both explain the pixels ...
        e_filt.append(rmse(filt.points, s["X"]))
        e_mode.append(rmse(mode.points, s["X"]))
    # ... but only one keeps the depth
    assert np.mean(e_filt) < 0.5 * np.mean(e_mode), (e_filt, e_mode)


def test_filtered_states_are_causal_and_end_where_the_smoother_ends(rng):
    s = robot_scene(rng, F=F, mode="fast", noise=0.4)
    kw = dict(pixel_sigma=0.4, process_psd=0.3, start_mean=true_start(s), start_cov=START_COV)
    online = filter_trajectory(s["P"], s["uv"], s["times"], smoother=False, **kw)
    smooth = filter_trajectory(s["P"], s["uv"], s["times"], **kw)
    np.testing.assert_allclose(
        np.asarray(online.states[-1]), np.asarray(smooth.states[-1]), atol=1e-12
    )
    uv = s["uv"].copy()
    uv[25:] += 3.0  # later frames change ...
    changed = filter_trajectory(s["P"], uv, s["times"], smoother=False, **kw)
    np.testing.assert_array_equal(np.asarray(changed.states[:25]), np.asarray(online.states[:25]))
    assert not np.allclose(np.asarray(changed.states[25:]), np.asarray(online.states[25:]))
    # the smoother is more accurate than the filter (it sees the frames after each one)
    assert rmse(smooth.points, s["X"]) < rmse(online.points, s["X"])
    mean, cov = predict(online, 0.03)  # what the robot controller needs
    expect = online.states[-1, 0] + 0.03 * online.states[-1, 1]
    np.testing.assert_allclose(np.asarray(mean[0]), np.asarray(expect), atol=1e-12)
    assert np.all(np.linalg.eigvalsh(np.asarray(cov)) > 0)


def test_missing_frames_are_the_same_as_frames_left_out(rng):
    s = robot_scene(rng, F=F, mode="smooth", noise=0.4, irregular=True)
    kw = dict(pixel_sigma=0.4, process_psd=0.3, start_mean=true_start(s), start_cov=START_COV)
    w = np.ones(F)
    w[[7, 8, 20]] = 0.0
    uv = s["uv"].copy()
    uv[[7, 8, 20]] = np.nan
    miss = filter_trajectory(s["P"], uv, s["times"], w, **kw)
    keep = w > 0
    out = filter_trajectory(s["P"][keep], s["uv"][keep], s["times"][keep], **kw)
    assert int(miss.status) == jt.Status.OK and int(miss.num_observed) == F - 3
    np.testing.assert_allclose(np.asarray(miss.states[keep]), np.asarray(out.states), atol=1e-9)


def test_gate_rejects_outlier_detections(rng):
    s = robot_scene(rng, F=F, mode="fast", noise=0.4)
    kw = dict(pixel_sigma=0.4, process_psd=0.3, start_mean=true_start(s), start_cov=START_COV)
    uv = s["uv"].copy()
    bad = [10, 23, 41]
    uv[bad] += 40.0
    w = np.ones(F)
    w[bad] = 0.0
    plain = filter_trajectory(s["P"], uv, s["times"], **kw)
    gated = filter_trajectory(s["P"], uv, s["times"], gate=13.8, **kw)
    clean = filter_trajectory(s["P"], uv, s["times"], w, **kw)
    assert int(gated.num_observed) == 57 and int(plain.num_observed) == F
    np.testing.assert_allclose(np.asarray(gated.states), np.asarray(clean.states), atol=1e-12)
    assert rmse(gated.points, s["X"]) < 0.3 * rmse(plain.points, s["X"])


def test_batch_jit_vmap_and_gradient(rng):
    s = robot_scene(rng, F=F, mode="fast", noise=0.4)
    uvs = np.stack([s["uv"], s["uv"] + rng.normal(size=(F, 2)) * 0.4])
    starts = np.stack([true_start(s), true_start(s) + 0.01])
    kw = dict(pixel_sigma=0.4, process_psd=0.3, start_cov=START_COV)
    batch = filter_points(s["P"], uvs, s["times"], start_mean=starts, **kw)
    for i in range(2):
        one = filter_trajectory(s["P"], uvs[i], s["times"], start_mean=starts[i], **kw)
        np.testing.assert_allclose(np.asarray(batch.states[i]), np.asarray(one.states), atol=1e-10)
    shared = filter_points(s["P"], uvs, s["times"], start_mean=starts[0], **kw)
    np.testing.assert_array_equal(np.asarray(shared.states[0]), np.asarray(batch.states[0]))
    jit_one = jax.jit(
        lambda u, q: (
            filter_trajectory(
                s["P"], u, s["times"], start_mean=starts[1], start_cov=START_COV, process_psd=q
            ).points
        )
    )
    plain = filter_trajectory(
        s["P"], uvs[1], s["times"], start_mean=starts[1], start_cov=START_COV, process_psd=0.3
    )
    np.testing.assert_allclose(np.asarray(jit_one(uvs[1], 0.3)), plain.points, atol=1e-10)

    def f(uv, q):
        r = filter_trajectory(
            s["P"],
            uv,
            s["times"],
            pixel_sigma=0.4,
            process_psd=q,
            start_mean=starts[0],
            start_cov=START_COV,
        )
        return jnp.sum(r.points[5] + r.points[20])

    uv = jnp.asarray(s["uv"])
    g, gq = jax.grad(f, argnums=(0, 1))(uv, 0.3)
    d = rng.normal(size=uv.shape)
    eps = 1e-4
    fd = (f(uv + eps * d, 0.3) - f(uv - eps * d, 0.3)) / (2 * eps)
    assert float(np.sum(np.asarray(g) * d)) == pytest.approx(float(fd), rel=1e-5)
    fdq = (f(uv, 0.3 * (1 + 1e-5)) - f(uv, 0.3 * (1 - 1e-5))) / (0.6e-5)
    assert float(gq) == pytest.approx(float(fdq), rel=1e-4)


def test_status_and_bad_inputs(rng):
    s = robot_scene(rng, F=F, mode="random", noise=0.4)
    P, uv, t = s["P"], s["uv"], s["times"]
    m0 = true_start(s)
    kw = dict(start_mean=m0, start_cov=START_COV, process_psd=0.1)
    nan = uv.copy()
    nan[4] = np.nan
    jitted = jax.jit(lambda u: filter_trajectory(P, u, t, **kw))
    assert int(jitted(nan).status) == jt.Status.NONFINITE
    with pytest.raises(ValueError, match="uv"):
        filter_trajectory(P, nan, t, **kw)
    with pytest.raises(ValueError, match="process_psd"):
        filter_trajectory(P, uv, t, start_mean=m0, start_cov=START_COV, process_psd=None)
    with pytest.raises(ValueError, match="process_psd"):
        filter_trajectory(P, uv, t, start_mean=m0, start_cov=START_COV, process_psd=-1.0)
    with pytest.raises(ValueError, match="rule"):
        filter_trajectory(P, uv, t, rule="unscented", **kw)
    with pytest.raises(ValueError, match="gate"):
        filter_trajectory(P, uv, t, gate=0.0, **kw)
    with pytest.raises(ValueError, match="start_mean"):
        filter_trajectory(P, uv, t, start_mean=m0[:1], start_cov=START_COV, process_psd=0.1)
    with pytest.raises(ValueError, match="positive definite"):
        filter_trajectory(P, uv, t, start_mean=m0, start_cov=-START_COV, process_psd=0.1)
    with pytest.raises(ValueError, match="times"):
        filter_trajectory(P, uv, t[::-1], **kw)
    with pytest.raises(ValueError, match="order"):
        filter_trajectory(P, uv, t, order=4, **kw)
    with pytest.raises(ValueError, match="uv"):
        filter_points(P, uv, t, **kw)
    with pytest.raises(ValueError, match="start_mean"):
        filter_points(P, np.stack([uv, uv]), t, **{**kw, "start_mean": np.stack([m0] * 3)})
    with pytest.raises(TypeError, match="iterations"):
        filter_points(P, np.stack([uv, uv]), t, iterations=3, **kw)

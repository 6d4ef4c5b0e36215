"""Simulation: workpiece curves, camera paths, detector model, scenes, mocap curves.

Compilation dominates the run time, so the tests share a few shapes (F = 40 for scenes
and curves, 400 for camera geometry, 150 for the paper set-up) and pass numbers as
arrays where a function is jit-compiled, so that the compiled programs are reused.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxtraj import (
    Status,
    camera_centre,
    dct_basis,
    fit_rigid,
    normal_equations,
    project,
    reconstruct,
)
from jaxtraj.io import Y_UP_TO_Z_UP, load_bvh
from jaxtraj.sim import (
    CAMERA_KINDS,
    DEFAULT_MARKERS,
    IMAGE_SIZE,
    bvh_curve,
    default_intrinsics,
    following_camera,
    make_rigid_scene,
    make_scene,
    observe,
    orbit_camera,
    paper_experiment,
    random_discontinuous_camera,
    rigid_motion,
    sample_smooth_curve,
    sample_times,
    smooth_random_camera,
    smooth_random_curve,
    static_camera,
    transform_points,
)

KEY = jax.random.key(7)
_reconstruct = jax.jit(reconstruct)
EYE = np.eye(3)


def _times(F=40, duration=6.0):
    return sample_times(jax.random.key(1), F, duration)


def _assert_trees_equal(a, b, atol=0.0):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), atol=atol, rtol=0)


def _check_jit_vmap(f, keys, atol=1e-12):
    """``jit(vmap(f))`` over keys equals a Python loop of (library-jitted) calls."""
    loop = jax.tree.map(lambda *a: jnp.stack(a), *(f(k) for k in keys))
    _assert_trees_equal(jax.jit(jax.vmap(f))(keys), loop, atol=atol)


def _np(tree):
    """NumPy copies of a result's arrays (test arithmetic in NumPy compiles nothing)."""
    return jax.tree.map(np.asarray, tree)


def _pixels(path, points, K):
    """Noise-free pixels and depths of (F, 3) points for a CameraPath (NumPy)."""
    R, t, points, K = (
        np.asarray(path.R_c_w),
        np.asarray(path.t_c_w),
        np.asarray(points),
        np.asarray(K),
    )
    pc = np.einsum("fij,fj->fi", R, points) + t
    return pc[:, :2] / pc[:, 2:] @ K[:2, :2].T + K[:2, 2], pc[:, 2]


def _project_all(s):
    """Noise-free pixels (F, 2) or (F, M, 2) of a scene's true points (NumPy reference)."""
    pts = s.points if s.points.ndim == 3 else s.points[:, None]
    pc = np.einsum("fij,fmj->fmi", s.R_c_w, pts) + s.t_c_w[:, None]
    uv = pc[..., :2] / pc[..., 2:] @ s.K[:2, :2].T + s.K[:2, 2]
    return uv if s.points.ndim == 3 else uv[:, 0]


def _assert_rotations(R):
    R = np.asarray(R)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(EYE, R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)


@pytest.fixture(scope="module")
def paper_scenes():
    """Four seeds of the paper's set-up, stacked (a loop compiles less than a vmap)."""
    keys = jax.random.split(jax.random.key(2026), 4)
    return _np(jax.tree.map(lambda *a: jnp.stack(a), *(paper_experiment(k) for k in keys)))


# ---------------------------------------------------------------- trajectories


def test_smooth_curve_extent_centre_dtype():
    times = _times()
    x = smooth_random_curve(KEY, times, centre=(1.0, -2.0, 0.5), extent=0.25)
    assert x.shape == (40, 3) and x.dtype == jnp.float64
    x = np.asarray(x)
    lo, hi = x.min(axis=0), x.max(axis=0)
    assert np.max(hi - lo) == pytest.approx(0.25, abs=1e-12)
    np.testing.assert_allclose(0.5 * (lo + hi), [1.0, -2.0, 0.5], atol=1e-12)
    x32 = smooth_random_curve(KEY, times.astype(jnp.float32))
    assert x32.dtype == jnp.float32
    x32 = np.asarray(x32)
    assert np.max(x32.max(0) - x32.min(0)) == pytest.approx(0.3, abs=1e-6)


def test_smooth_curve_has_small_nonzero_dct_basis_error(paper_scenes):
    errs = []
    for k in (6, 12, 20):
        for times, x in zip(paper_scenes.times, paper_scenes.points, strict=True):
            Qb, _ = np.linalg.qr(np.asarray(dct_basis(times, k)))
            errs.append(np.linalg.norm(x - Qb @ (Qb.T @ x), axis=1).mean())
    errs = np.array(errs).reshape(3, -1)
    assert np.all(errs[1] > 1e-4)  # not in the span: a realistic basis error ...
    assert np.all(errs[1] < 4e-3)  # ... of a few millimetres at most with k = 12
    assert np.all(errs[0] > errs[1]) and np.all(errs[1] > errs[2])


def test_smooth_curve_derivatives_are_analytic():
    times = _times()
    curve = sample_smooth_curve(KEY, times)
    np.testing.assert_allclose(curve(times), smooth_random_curve(KEY, times), atol=1e-15)
    ones = jnp.ones_like(times)
    _, vel = jax.jvp(curve, (times,), (ones,))
    _, acc = jax.jvp(lambda t: curve(t, 1), (times,), (ones,))
    np.testing.assert_allclose(curve(times, 1), vel, atol=1e-13)
    np.testing.assert_allclose(curve(times, 2), acc, atol=1e-13)
    with pytest.raises(ValueError, match="derivative"):
        curve(times, 3)


def test_smooth_curve_jit_vmap_seeds():
    times = _times()
    f = lambda k: smooth_random_curve(k, times)  # noqa: E731
    keys = jax.random.split(KEY, 3)
    _check_jit_vmap(f, keys, atol=1e-14)
    np.testing.assert_array_equal(f(KEY), f(jax.random.key(7)))
    assert np.abs(np.asarray(f(keys[0])) - np.asarray(f(keys[1]))).max() > 1e-3


def test_smooth_curve_gradient():
    times = _times()
    check_grads(
        jax.jit(lambda c, e: smooth_random_curve(KEY, times, centre=c, extent=e)),
        (jnp.array([0.1, 0.2, 0.3]), jnp.asarray(0.3)),
        order=1,
    )


def test_smooth_curve_bad_inputs():
    times = _times()
    with pytest.raises(ValueError, match=r"times: expected shape \(\?,\)"):
        smooth_random_curve(KEY, times[:, None])
    with pytest.raises(ValueError, match="times: expected at least 2"):
        smooth_random_curve(KEY, times[:1])
    with pytest.raises(ValueError, match=r"centre: expected shape \(3,\)"):
        smooth_random_curve(KEY, times, centre=(0.0, 0.0))
    with pytest.raises(ValueError, match="n_terms"):
        sample_smooth_curve(KEY, times, n_terms=0)
    with pytest.raises(ValueError, match="extent"):
        smooth_random_curve(KEY, times, extent=-0.1)


def test_rigid_motion_and_transform_points():
    times = _times()
    f = lambda k: rigid_motion(k, times, centre=(0.0, 0.0, 1.0), extent=0.2, max_angle=0.4)  # noqa: E731
    R, p = _np(f(KEY))
    assert R.shape == (40, 3, 3) and p.shape == (40, 3)
    _assert_rotations(R)
    angles = np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1))
    assert angles.max() == pytest.approx(0.4, abs=1e-6)
    assert np.max(p.max(0) - p.min(0)) == pytest.approx(0.2, abs=1e-12)
    np.testing.assert_allclose(0.5 * (p.max(0) + p.min(0)), [0, 0, 1], atol=1e-12)
    # Reference: a NumPy loop; and the rigid fit recovers the pose.
    model = np.array(DEFAULT_MARKERS)
    X = transform_points(R, p, model)
    ref = np.stack([R[i] @ model.T + p[i][:, None] for i in range(40)])
    np.testing.assert_allclose(X, ref.transpose(0, 2, 1), atol=1e-14)
    R_fit, p_fit = jax.vmap(fit_rigid, in_axes=(None, 0))(model, X)
    np.testing.assert_allclose(R_fit, R, atol=1e-10)
    np.testing.assert_allclose(p_fit, p, atol=1e-10)
    _check_jit_vmap(f, jax.random.split(KEY, 2), atol=1e-13)
    check_grads(jax.jit(transform_points), (R[:3], p[:3], model), order=1)
    with pytest.raises(ValueError, match=r"p_w_o: expected shape \(40, 3\)"):
        transform_points(R, p[:-1], model)
    with pytest.raises(ValueError, match="model_points"):
        transform_points(R, p, model[:, :2])
    with pytest.raises(ValueError, match="max_angle"):
        rigid_motion(KEY, times, max_angle=-1.0)


def test_bvh_curve(shared_data):
    path = shared_data / "cmu_bvh" / "scaled_131_01.bvh"
    m = load_bvh(path)
    root = m.motion[:, :3] @ Y_UP_TO_Z_UP.T
    # Default: the root at the file's own frames, Z-up.
    x = bvh_curve(path)
    assert x.shape == (995, 3)
    np.testing.assert_allclose(x, root, atol=1e-12)
    np.testing.assert_allclose(bvh_curve(path, z_up=False), m.motion[:, :3], atol=1e-12)
    # Mid-points between frames are the averages (linear interpolation).
    mid = (np.arange(10) + 0.5) * m.frame_time
    np.testing.assert_allclose(bvh_curve(path, times=mid), 0.5 * (root[:10] + root[1:11]), 1e-12)
    # Uniform resampling over a given duration, several joints, re-centring.
    y = bvh_curve(path, joint=["Hips", "Head", 5], duration=2.0, n_frames=50, centre=(0, 0, 1))
    assert y.shape == (50, 3, 3)
    np.testing.assert_allclose(y.reshape(-1, 3).mean(axis=0), [0, 0, 1], atol=1e-12)
    t = np.linspace(0, 2.0, 50)
    head, hips = bvh_curve(path, joint="Head", times=t), bvh_curve(path, times=t)
    np.testing.assert_allclose(y[:, 1] - y[:, 0], head - hips, atol=1e-12)
    assert bvh_curve(path, duration=1.0).shape == (121, 3)
    with pytest.raises(ValueError, match="times: must lie in"):
        bvh_curve(path, times=[0.0, 100.0])
    with pytest.raises(ValueError, match="duration"):
        bvh_curve(path, duration=1e3)
    with pytest.raises(ValueError, match="joint: 'Tail'"):
        bvh_curve(path, joint="Tail")


# ---------------------------------------------------------------- camera paths


@pytest.fixture(scope="module")
def workpiece():
    times = _times(F=400, duration=20.0)
    return times, smooth_random_curve(jax.random.key(3), times, centre=(0.5, 0.0, 0.3))


def test_random_camera_geometry(workpiece):
    _, pts = workpiece
    K = default_intrinsics()
    path = random_discontinuous_camera(KEY, pts, standoff=(0.5, 1.5), cone_angle=1.0, max_aim=0.1)
    assert path.R_c_w.shape == (400, 3, 3) and path.t_c_w.shape == (400, 3)
    _assert_rotations(path.R_c_w)
    centres = np.asarray(path.centres)
    P = path.projection_matrices(K)
    np.testing.assert_allclose(jax.vmap(camera_centre)(P), centres, atol=1e-12)
    d = centres - np.asarray(pts)
    r = np.linalg.norm(d, axis=1)
    assert 0.5 <= float(r.min()) < 0.52 and 1.48 < float(r.max()) <= 1.5
    cos_axis = d[:, 2] / r  # viewpoints inside the cone around +z, filling it
    assert float(cos_axis.min()) >= np.cos(1.0) - 1e-12 and float(cos_axis.min()) < np.cos(0.9)
    uv, depth = _pixels(path, pts, K)
    assert float(depth.min()) > 0.4
    off = np.linalg.norm(uv - [319.5, 239.5], axis=1)  # at most f tan(max_aim) off centre
    assert float(off.max()) <= 700 * np.tan(0.1) + 1e-9 and float(off.max()) > 50
    _check_jit_vmap(lambda k: random_discontinuous_camera(k, pts), jax.random.split(KEY, 2))
    with pytest.raises(ValueError, match="standoff"):
        random_discontinuous_camera(KEY, pts, standoff=(1.0, 0.5))
    with pytest.raises(ValueError, match="max_aim"):
        random_discontinuous_camera(KEY, pts, max_aim=2.0)
    with pytest.raises(ValueError, match=r"points: expected shape \(\?, 3\)"):
        random_discontinuous_camera(KEY, pts[:, :2])


def test_static_and_following_cameras(workpiece):
    _, pts = workpiece
    K = default_intrinsics()
    target = jnp.array([0.5, 0.0, 0.3])
    cam = static_camera(jnp.array([1.0, 1.0, 1.5]), target, 400)
    np.testing.assert_allclose(cam.centres, np.broadcast_to([1.0, 1.0, 1.5], (400, 3)), atol=1e-12)
    uv, _ = _pixels(cam, np.broadcast_to(target, (400, 3)), K)
    np.testing.assert_allclose(uv, np.broadcast_to(K[:2, 2], (400, 2)), atol=1e-9)
    assert np.all(np.isfinite(static_camera(jnp.array([0.0, 0, 2]), jnp.zeros(3), 2).R_c_w))
    offset = jnp.array([0.3, -0.6, 0.5])
    fol = following_camera(pts, offset)
    _assert_rotations(fol.R_c_w)
    np.testing.assert_allclose(fol.centres - pts, np.broadcast_to(offset, (400, 3)), atol=1e-12)
    uv, depth = _pixels(fol, pts, K)
    np.testing.assert_allclose(uv, np.broadcast_to(K[:2, 2], (400, 2)), atol=1e-9)
    np.testing.assert_allclose(depth, np.linalg.norm(offset), atol=1e-12)
    with pytest.raises(ValueError, match="F: expected a positive int"):
        static_camera(jnp.ones(3), jnp.zeros(3), 0)
    with pytest.raises(ValueError, match=r"offset: expected shape \(3,\)"):
        following_camera(pts, jnp.ones(2))


def test_orbit_camera(workpiece):
    times, pts = workpiece
    cam = orbit_camera(pts, radius=0.8, angular_speed=0.3, height=0.6, times=times, phase=0.2)
    _assert_rotations(cam.R_c_w)
    c = np.asarray(cam.centres) - np.asarray(pts).mean(axis=0)
    np.testing.assert_allclose(np.linalg.norm(c[:, :2], axis=1), 0.8, atol=1e-12)
    np.testing.assert_allclose(c[:, 2], 0.6, atol=1e-12)
    angle = np.angle(np.exp(1j * (0.3 * np.asarray(times) + 0.2)))
    np.testing.assert_allclose(np.arctan2(c[:, 1], c[:, 0]), angle, atol=1e-9)
    uv, depth = _pixels(cam, pts, default_intrinsics())
    np.testing.assert_allclose(uv, np.broadcast_to([319.5, 239.5], (400, 2)), atol=1e-9)
    assert float(depth.min()) > 0.5
    centres = jax.jit(
        lambda r, w: orbit_camera(pts, radius=r, angular_speed=w, height=0.6, times=times).centres
    )
    check_grads(
        centres,
        (0.8, 0.3),
        order=1,
        modes=("rev",),
    )
    with pytest.raises(ValueError, match=r"times: expected shape \(400,\)"):
        orbit_camera(pts, radius=1.0, angular_speed=0.1, height=0.5, times=times[:-1])


@pytest.mark.parametrize("speed", [0.0, 0.05, 0.5])
def test_smooth_camera_speed_and_shell(workpiece, speed):
    _, pts = workpiece
    dense = np.linspace(0.0, 20.0, 400)
    cam = smooth_random_camera(
        KEY, pts, dense, speed=jnp.asarray(speed), standoff=(0.8, 1.2), elevation=(0.4, 1.0)
    )
    _assert_rotations(cam.R_c_w)
    C = np.asarray(cam.centres)
    v = np.linalg.norm(np.diff(C, axis=0), axis=1) / np.diff(dense)
    np.testing.assert_allclose(v, speed, atol=2e-3 * max(speed, 1e-3))
    rel = C - np.asarray(pts).mean(axis=0)
    dist = np.linalg.norm(rel, axis=1)
    assert float(dist.min()) >= 0.8 - 1e-9 and float(dist.max()) <= 1.2 + 1e-9
    el = np.arcsin(rel[:, 2] / dist)
    assert float(el.min()) >= 0.4 - 1e-9 and float(el.max()) <= 1.0 + 1e-9
    uv, depth = _pixels(cam, pts, default_intrinsics())
    np.testing.assert_allclose(uv, np.broadcast_to([319.5, 239.5], (400, 2)), atol=1e-9)
    assert float(depth.min()) > 0.3


def test_smooth_camera_jit_vmap_grad_and_errors(workpiece):
    times, pts = workpiece
    f = lambda k, s: smooth_random_camera(k, pts, times, speed=s)  # noqa: E731
    _check_jit_vmap(lambda k: f(k, jnp.asarray(0.2)), jax.random.split(KEY, 2), atol=1e-10)
    # The centre path is differentiable in the speed (for design studies).
    end = lambda s: jnp.sum(f(KEY, s).centres[-1])  # noqa: E731
    fd = (end(jnp.asarray(0.2 + 1e-5)) - end(jnp.asarray(0.2 - 1e-5))) / 2e-5
    assert float(jax.grad(end)(jnp.asarray(0.2))) == pytest.approx(float(fd), rel=1e-3)
    with pytest.raises(ValueError, match="speed"):
        f(KEY, -1.0)
    with pytest.raises(ValueError, match="elevation"):
        smooth_random_camera(KEY, pts, times, speed=0.1, elevation=(0.5, 1.6))


# ---------------------------------------------------------------- detector model


def test_default_intrinsics():
    K = default_intrinsics()
    assert IMAGE_SIZE == (640, 480)
    np.testing.assert_array_equal(K, [[700, 0, 319.5], [0, 700, 239.5], [0, 0, 1]])
    assert default_intrinsics(dtype=jnp.float32).dtype == jnp.float32


def _one_camera(F):
    """Identity pose, default K, repeated F times."""
    P = default_intrinsics() @ jnp.concatenate([jnp.eye(3), jnp.zeros((3, 1))], axis=1)
    return jnp.eye(3), jnp.zeros(3), jnp.broadcast_to(P, (F, 3, 4))


def test_observe_noise_free_equals_projection():
    pts = jax.random.uniform(KEY, (40, 3), minval=-0.2, maxval=0.2) + jnp.array([0, 0, 1.0])
    R, t, P = _one_camera(40)
    obs = observe(KEY, P, pts, noise_px=0.0)
    np.testing.assert_allclose(obs.uv, project(default_intrinsics(), R, t, pts), atol=1e-9)
    np.testing.assert_array_equal(obs.weights, 1.0)
    assert not obs.outliers.any() and obs.weights.dtype == jnp.float64
    # A projection matrix scaled by -2 describes the same camera.
    np.testing.assert_allclose(observe(KEY, -2 * P, pts, noise_px=0.0).uv, obs.uv, atol=1e-9)


def test_observe_noise_statistics():
    n = 20000
    pts = jnp.broadcast_to(jnp.array([0.01, -0.02, 1.0]), (n, 3))
    _, _, P = _one_camera(n)
    obs = observe(KEY, P, pts, noise_px=0.3)
    res = np.asarray(obs.uv - observe(KEY, P, pts, noise_px=0.0).uv)
    # Sample std within 5 standard errors (std error of a std: sigma / sqrt(2 n)).
    np.testing.assert_allclose(res.std(axis=0), 0.3, atol=5 * 0.3 / np.sqrt(2 * n))
    np.testing.assert_allclose(res.mean(axis=0), 0.0, atol=5 * 0.3 / np.sqrt(n))


def test_observe_drop_and_outlier_rates():
    n = 20000
    pts = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0]), (n, 3))
    _, _, P = _one_camera(n)
    obs = observe(KEY, P, pts, noise_px=0.5, drop_rate=0.2, outlier_rate=0.1, outlier_px=20.0)
    kept = np.asarray(obs.weights) > 0
    assert abs((~kept).sum() - 0.2 * n) < 5 * np.sqrt(n * 0.2 * 0.8)
    assert np.all(np.isnan(obs.uv[~kept])) and np.all(np.isfinite(obs.uv[kept]))
    out = np.asarray(obs.outliers)
    assert not np.any(out & ~kept)
    m = kept.sum()
    assert abs(out.sum() - 0.1 * m) < 5 * np.sqrt(m * 0.1 * 0.9)
    jump = np.linalg.norm(np.asarray(obs.uv) - [319.5, 239.5], axis=1)
    assert jump[out].min() >= 10.0 - 1e-9 and jump[out].max() <= 20.0 + 1e-9
    assert jump[kept & ~out].max() < 6 * 0.5 * np.sqrt(2)


def test_observe_visibility_multi_point_jit_vmap_grad():
    # Behind the camera, just outside/inside the left and right borders, below the image.
    f = 700.0
    pts = jnp.array(
        [
            [0.0, 0.0, -1.0],
            [(-0.6 - 319.5) / f, 0.0, 1.0],
            [(-0.4 - 319.5) / f, 0.0, 1.0],
            [(639.6 - 319.5) / f, 0.0, 1.0],
            [(639.4 - 319.5) / f, 0.0, 1.0],
            [0.0, (480.0 - 239.5) / f, 1.0],
        ]
    )
    _, _, P = _one_camera(6)
    obs = observe(KEY, P, pts, noise_px=0.0)
    np.testing.assert_array_equal(obs.weights, [0, 0, 1, 0, 1, 0])
    assert np.isnan(obs.uv[0]).all() and np.isfinite(obs.uv[2]).all()
    # (F, M, 3) points: the same as one call per point when noise-free.
    mo = observe(KEY, P, jnp.stack([pts, pts[::-1]], axis=1), noise_px=0.0)
    assert mo.uv.shape == (6, 2, 2) and mo.weights.shape == (6, 2)
    np.testing.assert_array_equal(mo.weights[:, 1], obs.weights[::-1])
    np.testing.assert_allclose(mo.uv[2:5:2, 0], obs.uv[2:5:2], atol=1e-12)
    _check_jit_vmap(lambda k: observe(k, P, pts), jax.random.split(KEY, 2))
    # Differentiable in the points (the noise is fixed by the key).
    inside = jnp.array([[0.01, 0.02, 1.0], [-0.05, 0.03, 1.2]])
    check_grads(jax.jit(lambda x: observe(KEY, P[:2], x).uv), (inside,), order=1, modes=("rev",))


def test_observe_bad_inputs():
    _, _, P = _one_camera(4)
    pts = jnp.ones((4, 3))
    with pytest.raises(ValueError, match=r"P: expected shape \(\?, 3, 4\)"):
        observe(KEY, P[:, :2], pts)
    with pytest.raises(ValueError, match=r"points: expected shape \(4, 3\) or \(4, M, 3\)"):
        observe(KEY, P, pts[:3])
    with pytest.raises(ValueError, match="drop_rate"):
        observe(KEY, P, pts, drop_rate=1.5)
    with pytest.raises(ValueError, match="outlier_rate"):
        observe(KEY, P, pts, outlier_rate=-0.1)
    with pytest.raises(ValueError, match="noise_px"):
        observe(KEY, P, pts, noise_px=-1.0)


# ---------------------------------------------------------------- scenes


def test_sample_times():
    t = sample_times(KEY, 100, 5.0)
    dt = np.diff(t)
    assert t.shape == (100,) and float(t[0]) > 0 and float(t[-1]) < 5.0
    assert dt.min() >= 0.2 * 0.05 - 1e-12 and dt.std() > 0.005  # irregular, increasing
    np.testing.assert_allclose(sample_times(KEY, 11, 5.0, irregular=False), np.linspace(0, 5, 11))
    with pytest.raises(ValueError, match="n_frames"):
        sample_times(KEY, 1)


@pytest.mark.parametrize("camera", CAMERA_KINDS)
def test_make_scene_kinds(camera):
    F, dtype, given = 40, np.float64, {}
    if camera == "orbit":  # a given float32 trajectory (e.g. mocap) is used as is
        dtype, t = np.float32, np.linspace(0.0, 4.0, F, dtype=np.float32)
        given = dict(times=t, points=np.stack([0.1 * t, np.sin(t), 0 * t + 1], axis=1))
    tol = max(1e-10, 1e4 * np.finfo(dtype).eps)  # 1e-10 in float64, 1e-3 in float32
    s = _np(make_scene(KEY, camera=camera, n_frames=F, duration=4.0, noise_px=0.0, **given))
    for name, value in given.items():
        np.testing.assert_array_equal(getattr(s, name), value)
    shapes = dict(times=(F,), points=(F, 3), K=(3, 3), R_c_w=(F, 3, 3), t_c_w=(F, 3), P=(F, 3, 4))
    shapes.update(camera_centres=(F, 3), uv=(F, 2), weights=(F,), outliers=(F,))
    for name, shape in shapes.items():
        assert getattr(s, name).shape == shape, name
    assert s.P.dtype == s.uv.dtype == s.camera_centres.dtype == dtype
    assert s.outliers.dtype == np.bool_
    assert np.all(np.diff(s.times) > 0) and 0 <= float(s.times[0]) and float(s.times[-1]) <= 4.0
    P = s.K @ np.concatenate([s.R_c_w, s.t_c_w[:, :, None]], axis=2)
    np.testing.assert_allclose(s.P, P, atol=tol, rtol=tol)
    centres = -np.linalg.solve(s.P[:, :, :3], s.P[:, :, 3:])[..., 0]
    np.testing.assert_allclose(s.camera_centres, centres, atol=tol)
    # Noise-free pixels are the projections; every point is in front and inside the image.
    np.testing.assert_allclose(s.uv, _project_all(s), atol=tol)
    np.testing.assert_array_equal(s.weights, 1.0)
    depth = np.einsum("fj,fj->f", s.R_c_w[:, 2], s.points) + s.t_c_w[:, 2]
    assert float(depth.min()) > 0.2
    assert float(s.uv[:, 0].min()) > 0 and float(s.uv[:, 0].max()) < 639
    assert float(s.uv[:, 1].min()) > 0 and float(s.uv[:, 1].max()) < 479
    assert s.basis(5).shape == (F, 5)


def test_make_scene_jit_vmap_seeds_and_errors():
    f = lambda k: make_scene(k, camera="random", n_frames=40, drop_rate=0.1)  # noqa: E731
    keys = jax.random.split(KEY, 3)
    _check_jit_vmap(f, keys, atol=1e-10)
    _assert_trees_equal(f(keys[0]), f(keys[0]))
    assert np.abs(np.asarray(f(keys[0]).points - f(keys[1]).points)).max() > 1e-2
    times = np.linspace(0.0, 1.0, 40)
    pts = np.stack([times, 0 * times, 0 * times + 1], axis=1)
    with pytest.raises(ValueError, match="camera: expected one of"):
        make_scene(KEY, camera="drone")
    with pytest.raises(ValueError, match="times: required"):
        make_scene(KEY, points=pts)
    with pytest.raises(ValueError, match=r"points: expected shape \(40, 3\)"):
        make_scene(KEY, times=times, points=pts[:-1])
    with pytest.raises(ValueError, match="standoff"):
        make_scene(KEY, standoff=(1.0, 0.2))
    with pytest.raises(ValueError, match="drop_rate"):
        make_scene(KEY, drop_rate=2.0)


def test_following_camera_is_exactly_degenerate():
    s = make_scene(KEY, camera="following", n_frames=40, duration=4.0, noise_px=0.0)
    basis = dct_basis(s.times, 8)
    rec = _reconstruct(s.P, s.uv, basis, s.weights)
    assert int(rec.status) == Status.DEGENERATE and float(rec.gain) > 1e6
    # Exactly singular: shifting the whole trajectory along the (constant) offset satisfies
    # every ray, so the constant basis vector times the offset is a null vector of N.
    N, _ = normal_equations(s.P, s.uv, basis, s.weights)
    offset = np.asarray(s.camera_centres - s.points)
    np.testing.assert_allclose(offset, np.broadcast_to(offset[0], offset.shape), atol=1e-12)
    v = np.zeros((8, 3))
    v[0] = offset[0] / np.linalg.norm(offset[0])
    N = np.asarray(N)
    assert np.linalg.norm(N @ v.ravel()) < 1e-12 * np.linalg.norm(N, 2)


def test_paper_experiment_setup(paper_scenes):
    s = paper_scenes
    assert s.points.shape == (4, 150, 3) and s.uv.shape == (4, 150, 2)
    r = np.linalg.norm(s.camera_centres - s.points, axis=2)
    assert r.min() >= 0.5 and r.max() <= 1.5
    ext = s.points.max(axis=1) - s.points.min(axis=1)
    np.testing.assert_allclose(ext.max(axis=1), 0.3, atol=1e-12)
    np.testing.assert_array_equal(s.weights, 1.0)
    proj = [_project_all(jax.tree.map(lambda a, i=i: a[i], s)) for i in range(4)]
    res = (s.uv - np.stack(proj)).ravel()
    np.testing.assert_allclose(res.std(), 0.3, atol=5 * 0.3 / np.sqrt(2 * res.size))
    # Consecutive cameras jump (discontinuous): the median step is tens of centimetres.
    steps = np.linalg.norm(np.diff(s.camera_centres, axis=1), axis=2)
    assert np.median(steps) > 0.3


@pytest.mark.parametrize("k", [10, 12])
def test_paper_experiment_reconstructs_to_millimetres(paper_scenes, k):
    s = paper_scenes
    bases = jax.vmap(lambda t: dct_basis(t, k))(s.times)
    rec = jax.vmap(_reconstruct)(s.P, s.uv, bases, s.weights)
    err = np.linalg.norm(np.asarray(rec.points) - s.points, axis=2).mean(axis=1)
    assert np.all(np.asarray(rec.status) == Status.OK) and float(rec.gain.max()) < 10
    assert err.max() < 5e-3


def test_make_rigid_scene():
    s = _np(make_rigid_scene(KEY, n_frames=40, noise_px=0.0))
    model = np.array(DEFAULT_MARKERS)
    assert np.linalg.matrix_rank(model - model.mean(0)) == 3  # non-coplanar
    assert np.linalg.norm(model, axis=1).max() < 0.2
    assert s.points.shape == (40, 5, 3) and s.uv.shape == (40, 5, 2) and s.weights.shape == (40, 5)
    ref = np.einsum("fij,mj->fmi", s.R_w_o, s.model_points) + s.p_w_o[:, None]
    np.testing.assert_allclose(s.points, ref, atol=1e-15)
    np.testing.assert_allclose(s.uv, _project_all(s), atol=1e-9)
    np.testing.assert_array_equal(s.weights, 1.0)  # all markers visible
    r = np.linalg.norm(s.camera_centres - s.p_w_o, axis=1)
    assert r.min() >= 0.7 and r.max() <= 1.5
    R_fit, p_fit = jax.vmap(fit_rigid, in_axes=(None, 0))(s.model_points, s.points)
    np.testing.assert_allclose(R_fit, s.R_w_o, atol=1e-10)
    np.testing.assert_allclose(p_fit, s.p_w_o, atol=1e-10)
    half = _np(make_rigid_scene(KEY, model * 0.5, n_frames=40, noise_px=0.0))
    rel = lambda sc: sc.points - sc.p_w_o[:, None]  # noqa: E731
    np.testing.assert_allclose(rel(half), 0.5 * rel(s), atol=1e-12)
    with pytest.raises(ValueError, match=r"model_points: expected shape \(\?, 3\)"):
        make_rigid_scene(KEY, jnp.ones((4, 2)))

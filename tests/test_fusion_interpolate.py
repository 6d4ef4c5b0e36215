"""Poses at arbitrary times on SE(3), camera poses and projection matrices; event streams."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxtraj.camera import project, projection_matrix
from jaxtraj.fusion import (
    FusionResult,
    ImuData,
    NominalState,
    RobotNoise,
    RobotPoses,
    build_events,
    camera_poses_at,
    interpolate_poses,
    projection_matrices,
)
from jaxtraj.fusion.events import IMAGE, IMU, POSE, flange_to_imu

XI = jnp.array([0.3, -0.2, 0.1, 0.4, 0.2, -0.5])  # screw: (translation, rotation) per second
T0 = jaxlie.SE3.from_rotation_and_translation(
    jaxlie.SO3.from_rpy_radians(0.1, 0.2, 0.3), jnp.array([1.0, 2.0, 0.5])
)
T_I_C = jaxlie.SE3.from_rotation_and_translation(
    jaxlie.SO3.from_rpy_radians(-1.5, 0.0, 0.1), jnp.array([0.02, 0.05, -0.01])
)
K = jnp.array([[700.0, 0, 320], [0, 700, 240], [0, 0, 1]])


@jax.jit
def _screw(t):
    T = jax.vmap(lambda s: T0 @ jaxlie.SE3.exp(s * XI))(jnp.asarray(t))
    return T.translation(), T.rotation().wxyz


def _result(t):
    p, q = _screw(t)
    n = len(t)
    z = jnp.zeros((n, 3))
    return FusionResult(
        t=jnp.asarray(t),
        kind=jnp.zeros(n, jnp.int32),
        index=jnp.arange(n),
        x=NominalState(p=p, v=z, q=q, b_a=z, b_g=z),
        P=jnp.zeros((n, 15)),
        u=jnp.zeros((n, 6)),
        dt=jnp.zeros(n),
        nis=jnp.zeros(n),
        nll=jnp.zeros(n),
        updated=jnp.zeros(n, bool),
    )


def test_interpolation_is_exact_on_a_screw_motion():
    t_known = jnp.array([0.0, 0.3, 0.5, 1.1])
    times = jnp.array([-0.2, 0.0, 0.1, 0.3, 0.45, 0.8, 1.1, 1.5])
    p, q = interpolate_poses(t_known, *_screw(t_known), times)
    p_ref, q_ref = _screw(jnp.clip(times, 0.0, 1.1))  # clamped outside the span
    np.testing.assert_allclose(p, p_ref, atol=1e-12)
    np.testing.assert_allclose(q * jnp.sign(q[:, :1]), q_ref * jnp.sign(q_ref[:, :1]), atol=1e-12)


def test_interpolation_jit_vmap_grad():
    t_known = jnp.array([0.0, 0.3, 0.5, 1.1])
    known = _screw(t_known)
    times = jnp.array([[0.1, 0.7], [0.2, 0.9], [0.35, 1.0]])
    f = lambda ts: interpolate_poses(t_known, *known, ts)[0]  # noqa: E731
    loop = jnp.stack([f(ts) for ts in times])
    np.testing.assert_allclose(jax.jit(jax.vmap(f))(times), loop, atol=1e-14)
    check_grads(jax.jit(f), (times[0],), order=1, modes=("rev",))
    # the time derivative on a screw motion is its velocity
    v = jax.jacfwd(lambda s: f(jnp.array([s]))[0])(0.4)
    v_ref = jax.jacfwd(lambda s: _screw(jnp.array([s]))[0][0])(0.4)
    np.testing.assert_allclose(v, v_ref, atol=1e-12)


def test_camera_poses_and_projection_matrices():
    t = jnp.linspace(0.0, 1.0, 11)
    res = _result(t)
    times = jnp.array([0.05, 0.5, 0.93])
    R_c_w, t_c_w = camera_poses_at(res, times, T_I_C)
    p, q = _screw(times)
    T_w_c = jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3(q), p) @ T_I_C
    np.testing.assert_allclose(R_c_w, T_w_c.inverse().rotation().as_matrix(), atol=1e-12)
    np.testing.assert_allclose(t_c_w, T_w_c.inverse().translation(), atol=1e-12)
    P = projection_matrices(res, times, K, T_I_C)
    assert P.shape == (3, 3, 4)
    X = T_w_c.translation() + T_w_c.rotation().apply(jnp.array([0.1, -0.05, 2.0]))  # in front
    for i in range(3):
        np.testing.assert_allclose(P[i], projection_matrix(K, R_c_w[i], t_c_w[i]), atol=1e-12)
        uvw = P[i] @ jnp.append(X[i], 1.0)
        np.testing.assert_allclose(
            uvw[:2] / uvw[2], project(K, R_c_w[i], t_c_w[i], X[i]), atol=1e-9
        )
    # identity T_i_c: the camera is the IMU
    R0, _ = camera_poses_at(res, times)
    np.testing.assert_allclose(R0, jaxlie.SO3(q).inverse().as_matrix(), atol=1e-12)
    # vmap over recordings equals a loop
    both = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), res)
    Pb = jax.vmap(lambda r: projection_matrices(r, times, K, T_I_C))(both)
    np.testing.assert_allclose(Pb[1], P, atol=1e-14)


def test_interpolation_bad_inputs():
    t_known = jnp.array([0.0, 0.3])
    p, q = _screw(t_known)
    with pytest.raises(ValueError, match=r"p: expected shape \(2, 3\)"):
        interpolate_poses(t_known, p[:1], q, jnp.array([0.1]))
    with pytest.raises(ValueError, match="times: 1 non-finite"):
        interpolate_poses(t_known, p, q, jnp.array([jnp.nan, 0.1]))
    res = _result(t_known)
    with pytest.raises(ValueError, match=r"K: expected shape \(3, 3\)"):
        projection_matrices(res, jnp.array([0.1]), K[:2])
    batched = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), res)
    with pytest.raises(ValueError, match="result: expected one stream"):
        camera_poses_at(batched, jnp.array([0.1]))


# --------------------------------------------------------------------------- events
def _imu(n=6):
    t = jnp.arange(n) * 0.01
    return ImuData(t=t, gyro=jnp.ones((n, 3)) * jnp.arange(n)[:, None], accel=jnp.zeros((n, 3)))


def _robot(t):
    m = len(t)
    return RobotPoses(
        t=jnp.asarray(t), p=jnp.zeros((m, 3)), q=jnp.tile(jnp.array([1.0, 0, 0, 0]), (m, 1))
    )


def test_events_sorted_at_valid_times():
    noise = RobotNoise(1e-4, 1e-4)
    ev = build_events(
        _imu(), _robot([0.0135, 0.027, 0.06]), jnp.array([0.02, 0.035]), noise=noise, latency=0.003
    )
    np.testing.assert_allclose(
        ev.t, [0, 0.01, 0.0105, 0.02, 0.02, 0.024, 0.03, 0.035, 0.04, 0.05, 0.057], atol=1e-12
    )
    assert list(np.asarray(ev.kind)) == [
        IMU,
        IMU,
        POSE,
        IMU,
        IMAGE,
        POSE,
        IMU,
        IMAGE,
        IMU,
        IMU,
        POSE,
    ]
    # the pose valid at 0.057 lies after the last IMU sample: inactive
    assert list(np.asarray(ev.active)[np.asarray(ev.kind) == POSE]) == [True, True, False]
    assert list(np.asarray(ev.index)[np.asarray(ev.kind) == POSE]) == [0, 1, 2]
    # exact ties: IMU sample, then pose, then image
    tie = build_events(_imu(), _robot([0.02]), jnp.array([0.02]), noise=noise)
    assert list(np.asarray(tie.kind)[2:5]) == [IMU, POSE, IMAGE]
    # IMU events carry the next sample for interpolation
    i = int(np.flatnonzero(np.asarray(ev.kind) == IMU)[2])
    np.testing.assert_allclose(ev.u1[i, :3], 3.0) and np.testing.assert_allclose(ev.t1[i], 0.03)
    # jit/vmap over candidate latencies equals separate builds
    lats = jnp.array([0.0, 0.003])
    many = jax.jit(
        jax.vmap(
            lambda L: build_events(_imu(), _robot([0.013, 0.027, 0.06]), noise=noise, latency=L)
        )
    )(lats)
    one = build_events(_imu(), _robot([0.013, 0.027, 0.06]), noise=noise, latency=0.0)
    np.testing.assert_allclose(many.t[0], one.t)


def test_flange_to_imu_covariance_matches_monte_carlo(rng):
    noise = RobotNoise(1e-4, 2e-3)
    T_f_c = jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.from_rpy_radians(0.3, 0.1, 0.0), jnp.array([0.0, 0.1, 0.2])
    )
    p_f, q_f = jnp.array([0.5, 0.1, 1.0]), jaxlie.SO3.from_rpy_radians(0.2, -0.4, 1.0).wxyz
    p_i, q_i, cov = flange_to_imu(p_f, q_f, noise, T_f_c, T_I_C)
    n = 20000
    dp = rng.normal(0, 1e-4, (n, 3))
    dphi = rng.normal(0, 2e-3, (n, 3))
    q_noisy = jax.vmap(lambda d: (jaxlie.SO3(q_f) @ jaxlie.SO3.exp(d)).wxyz)(jnp.asarray(dphi))
    pi, qi, _ = jax.vmap(lambda p, q: flange_to_imu(p, q, noise, T_f_c, T_I_C))(p_f + dp, q_noisy)
    err = np.concatenate(
        [
            np.asarray(pi - p_i),
            np.asarray(jax.vmap(lambda q: (jaxlie.SO3(q_i).inverse() @ jaxlie.SO3(q)).log())(qi)),
        ],
        1,
    )
    emp = np.cov(err.T)
    np.testing.assert_allclose(emp, cov, atol=0.05 * np.max(np.abs(cov)))


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        (
            "imu_t",
            [0.0, 0.02, 0.01, 0.03, 0.04, 0.05],
            "imu.t: timestamps must be strictly increasing",
        ),
        ("imu_t", [0.0, np.nan, 0.02, 0.03, 0.04, 0.05], "imu.t: 1 non-finite"),
        ("accel", np.full((6, 3), np.inf), "imu.accel: 6 non-finite"),
        ("gyro", np.zeros((5, 3)), r"imu.gyro: expected shape \(6, 3\)"),
        ("robot_t", [0.02, 0.01], "robot.t: timestamps must be strictly increasing"),
        ("robot_p", np.array([[0.0, np.nan, 0.0], [0, 0, 0]]), "robot.p: 1 non-finite"),
        ("robot_q", np.array([[2.0, 0, 0, 0], [1, 0, 0, 0]]), "robot.q: quaternion at index 0"),
        ("images", [0.03, 0.02], "image_times: timestamps must be non-decreasing"),
    ],
)
def test_build_events_bad_inputs(field, value, match):
    imu = _imu()
    robot = _robot([0.01, 0.02])
    images = None
    if field == "imu_t":
        imu = ImuData(t=jnp.asarray(value), gyro=imu.gyro, accel=imu.accel)
    elif field in ("accel", "gyro"):
        imu = ImuData(
            t=imu.t,
            gyro=jnp.asarray(value) if field == "gyro" else imu.gyro,
            accel=jnp.asarray(value) if field == "accel" else imu.accel,
        )
    elif field == "robot_t":
        robot = _robot(value)
    elif field == "robot_p":
        robot = RobotPoses(t=robot.t, p=jnp.asarray(value), q=robot.q)
    elif field == "robot_q":
        robot = RobotPoses(t=robot.t, p=robot.p, q=jnp.asarray(value))
    else:
        images = jnp.asarray(value)
    with pytest.raises(ValueError, match=match):
        build_events(imu, robot, images, noise=RobotNoise(1e-4, 1e-4))

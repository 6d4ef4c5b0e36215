"""Real data: fuse the EuRoC V1_02 excerpt's IMU with decimated, noised ground-truth poses
standing in for robot data, and score at the held-back ground-truth times."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from jaxtraj.fusion import (
    ImuData,
    ImuNoise,
    RobotNoise,
    build_events,
    eskf,
    initial_covariance,
    initial_state,
    interpolate_poses,
    rts_smoother,
)
from jaxtraj.io.euroc import ground_truth_as_robot, read_euroc, read_euroc_csv

#: The ADIS16448's datasheet white noise describes a sensor at rest; on the flying MAV
#: (propeller vibration) the innovations need about 20x (accel) and 12x (gyro), similar
#: to the inflation used by visual-inertial systems on EuRoC. With these the mean NIS is
#: about 5 for 6 degrees of freedom. Bias random walks are the datasheet's.
IMU_NOISE_IN_FLIGHT = ImuNoise(
    accel_noise_density=0.04,
    gyro_noise_density=0.002,
    accel_random_walk=3.0e-3,
    gyro_random_walk=1.9393e-5,
)
ROBOT_NOISE = RobotNoise(position=1e-3, orientation=2e-3)


def _rmse(p, q, p_ref, q_ref):
    e_p = np.sqrt(np.mean(np.sum((np.asarray(p) - p_ref) ** 2, 1)))
    rv = jax.vmap(lambda a, b: (jaxlie.SO3(a).inverse() @ jaxlie.SO3(b)).log())(
        jnp.asarray(q), jnp.asarray(q_ref)
    )
    return e_p, np.sqrt(np.mean(np.sum(np.asarray(rv) ** 2, 1)))


@functools.lru_cache(maxsize=1)
def _load(folder: str):
    return read_euroc(folder)


@pytest.fixture
def euroc(shared_data):
    return _load(str(shared_data / "euroc_v1_02_excerpt"))


def test_reader(euroc):
    rec = euroc
    assert rec.imu_t.shape == (7999,) and rec.gyro.shape == (7999, 3)
    assert rec.imu_t[0] == 0.0 and np.all(np.diff(rec.imu_t) > 0)
    np.testing.assert_allclose(np.diff(rec.imu_t), 0.005, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(rec.gt_q, axis=1), 1.0, atol=1e-12)
    # first data row of groundtruth.csv
    np.testing.assert_allclose(rec.gt_p[0], [0.515292, 1.996597, 0.971028])
    assert rec.t0_ns == 1403715523912140000
    # gravity: at rest the accelerometer reads about g in the body frame
    assert abs(np.linalg.norm(rec.accel[:50].mean(0)) - 9.81) < 0.1


def test_reader_errors(tmp_path):
    bad = tmp_path / "imu0.csv"
    bad.write_text("#header\n1,2,3,4,5,6,7\n2,2,3,4,5,6\n")
    with pytest.raises(ValueError, match=r"imu0.csv:3: expected 7 comma-separated columns"):
        read_euroc_csv(bad, 7)
    bad.write_text("1,2,3,4,5,6,x\n")
    with pytest.raises(ValueError, match=r"imu0.csv:1: cannot parse"):
        read_euroc_csv(bad, 7)
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "imu0.csv").write_text("1,2,3,4,5,6,7\n2,2,3,4,5,6,7\n")
    with pytest.raises(FileNotFoundError, match=r"groundtruth\.csv"):
        read_euroc(empty)


def test_fusion_beats_robot_interpolation_and_finds_biases(euroc):
    rec = euroc
    robot, held = ground_truth_as_robot(rec, every=2, position_noise=1e-3, orientation_noise=2e-3)
    imu = ImuData(
        t=jnp.asarray(rec.imu_t), gyro=jnp.asarray(rec.gyro), accel=jnp.asarray(rec.accel)
    )
    t_held = rec.gt_t[held]
    ev = build_events(imu, robot, t_held, noise=ROBOT_NOISE)
    P0 = initial_covariance(0.05, 0.5, 0.1, 0.3, 0.05)
    res = eskf(ev, initial_state(ev), P0, IMU_NOISE_IN_FLIGHT)
    sm = rts_smoother(res, IMU_NOISE_IN_FLIGHT)
    assert bool(sm.ok)

    ref = (rec.gt_p[held], rec.gt_q[held])
    base_p, base_r = _rmse(*interpolate_poses(robot.t, robot.p, robot.q, t_held), *ref)
    filt_p, filt_r = _rmse(*interpolate_poses(res.t, res.x.p, res.x.q, t_held), *ref)
    smo_p, smo_r = _rmse(*interpolate_poses(sm.t, sm.x.p, sm.x.q, t_held), *ref)
    print(
        f"\nEuRoC held-back RMSE: robot interpolation {base_p * 1e3:.2f} mm "
        f"{np.degrees(base_r):.3f} deg | filter {filt_p * 1e3:.2f} mm {np.degrees(filt_r):.3f} "
        f"deg | smoother {smo_p * 1e3:.2f} mm {np.degrees(smo_r):.3f} deg"
    )
    # the smoothed (offline) pose is clearly better than the robot poses alone
    assert smo_p < 0.7 * base_p
    assert smo_r < 0.5 * base_r
    # the causal filter already wins on orientation (position at mid-interval is predicted)
    assert filt_r < 0.7 * base_r
    assert filt_p < 1.5 * base_p

    # innovation statistics match the model (6 dof)
    nis = np.asarray(res.nis)[np.asarray(res.updated)]
    assert 3.0 < nis.mean() < 9.0

    # biases close to the ground-truth columns (themselves estimates) at the end
    i_end = held[-1]
    np.testing.assert_allclose(sm.x.b_g[-1], rec.gt_b_g[i_end], atol=1e-3)
    np.testing.assert_allclose(sm.x.b_a[-1], rec.gt_b_a[i_end], atol=0.03)

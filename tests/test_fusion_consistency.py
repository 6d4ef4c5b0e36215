"""Monte-Carlo consistency (50 runs under vmap): NEES and NIS against chi-square bounds,
and the latency estimate on simulated data."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import chi2

from jaxtraj.fusion import (
    ImuNoise,
    RobotNoise,
    build_events,
    eskf,
    initial_covariance,
    nees,
)
from jaxtraj.fusion.imu import boxplus
from jaxtraj.fusion.latency import estimate_latency, latency_nll
from jaxtraj.fusion.simulate import LissajousTrajectory, simulate_recording, true_states

RUNS = 50
LATENCY = 0.004
TRAJ = LissajousTrajectory()
IMU_NOISE = ImuNoise.xsens_mti()
ROBOT_NOISE = RobotNoise.kuka_class()
P0 = initial_covariance(1e-3, 0.02, 0.02, 0.05, 0.005)


@functools.partial(jax.jit, static_argnames="reset")
def _runs(keys, filter_latency, reset):
    L = jnp.linalg.cholesky(P0)

    def one(key):
        k1, k2 = jax.random.split(key)
        rec = simulate_recording(
            k1, TRAJ, duration=2.0, imu_noise=IMU_NOISE, robot_noise=ROBOT_NOISE, latency=LATENCY
        )
        ev = build_events(
            rec.imu, rec.robot, rec.image_times, noise=ROBOT_NOISE, latency=filter_latency
        )
        truth = true_states(TRAJ, ev.t, rec.imu.t, rec.b_a, rec.b_g)
        x_true0 = jax.tree_util.tree_map(lambda a: a[0], truth)
        x0 = boxplus(x_true0, L @ jax.random.normal(k2, (15,)))  # x0 ~ N(truth, P0)
        res = eskf(ev, x0, P0, IMU_NOISE, reset=reset)
        return nees(res, truth), res.nis, res.updated

    return jax.vmap(one)(keys)


def _monte_carlo(reset: str, filter_latency: float):
    """Average NEES per event and average NIS per update over RUNS recordings."""
    keys = jax.random.split(jax.random.PRNGKey(2026), RUNS)
    e, nis, upd = _runs(keys, jnp.asarray(filter_latency), reset)
    upd = np.asarray(upd)
    assert np.all(upd == upd[0])  # same event layout in every run
    return np.asarray(e).mean(0), np.asarray(nis)[:, upd[0]].mean(0)


def _bounds(dof):
    return chi2.ppf([0.025, 0.975], dof * RUNS) / RUNS


def _consistent(avg, dof, min_fraction):
    lo, hi = _bounds(dof)
    return lo < avg.mean() < hi and np.mean((avg > lo) & (avg < hi)) >= min_fraction


@pytest.fixture(scope="module")
def correct():
    return _monte_carlo("full", LATENCY)


def test_nees_nis_inside_chi_square_bounds(correct):
    e, nis = correct
    lo, hi = _bounds(15)
    assert lo < e.mean() < hi, e.mean()
    assert np.mean((e > lo) & (e < hi)) > 0.85  # 95% expected; samples are correlated in time
    lo6, hi6 = _bounds(6)
    assert lo6 < nis.mean() < hi6, nis.mean()
    assert np.mean((nis > lo6) & (nis < hi6)) > 0.9
    assert _consistent(e, 15, 0.85) and _consistent(nis, 6, 0.9)


def test_filter_without_reset_is_inconsistent(correct):
    e, _nis = _monte_carlo("none", LATENCY)
    assert not _consistent(e, 15, 0.85)
    assert e.mean() > 5 * correct[0].mean()


@pytest.mark.parametrize("wrong", [0.0, LATENCY + 0.001])
def test_wrong_latency_is_inconsistent(wrong):
    e, nis = _monte_carlo("full", wrong)
    assert not _consistent(e, 15, 0.85)
    assert e.mean() > 10 * 15
    if wrong == 0.0:
        assert not _consistent(nis, 6, 0.9)


def test_latency_estimate_recovers_simulated_latency():
    rec = simulate_recording(
        jax.random.PRNGKey(7),
        TRAJ,
        duration=2.0,
        imu_noise=IMU_NOISE,
        robot_noise=ROBOT_NOISE,
        latency=0.0073,
        robot_period=0.012,
    )
    P0w = initial_covariance(5e-3, 0.1, 0.05, 0.05, 0.005)
    est = estimate_latency(rec.imu, rec.robot, P0w, IMU_NOISE, ROBOT_NOISE, bracket=(-0.01, 0.03))
    assert abs(float(est.latency) - 0.0073) < 1e-3
    assert est.num_poses > 50
    # the likelihood is lowest next to the truth and rises away from it
    nll = latency_nll(rec.imu, rec.robot, [0.0, 0.0073, 0.015], P0w, IMU_NOISE, ROBOT_NOISE)
    assert nll[1] < nll[0] and nll[1] < nll[2]
    # jit/vmap path equals a loop of single evaluations
    singles = [
        float(
            latency_nll(
                rec.imu, rec.robot, [tau], P0w, IMU_NOISE, ROBOT_NOISE, scored_range=(0.0, 0.015)
            )[0]
        )
        for tau in (0.0, 0.0073, 0.015)
    ]
    np.testing.assert_allclose(nll, singles, rtol=1e-10)


def test_latency_bad_inputs():
    rec = simulate_recording(
        jax.random.PRNGKey(7), TRAJ, duration=0.3, imu_noise=IMU_NOISE, robot_noise=ROBOT_NOISE
    )
    with pytest.raises(ValueError, match="bracket"):
        estimate_latency(rec.imu, rec.robot, P0, IMU_NOISE, ROBOT_NOISE, bracket=(0.01, 0.0))
    with pytest.raises(ValueError, match="latencies"):
        latency_nll(rec.imu, rec.robot, [np.nan], P0, IMU_NOISE, ROBOT_NOISE)
    with pytest.raises(ValueError, match="robot: fewer than 2 poses"):
        latency_nll(rec.imu, rec.robot, [0.0], P0, IMU_NOISE, ROBOT_NOISE, burn_in=1.0)

"""IMU model: analytic Jacobians against jax.jacfwd, kinematics, units, SO(3) helpers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxtraj.fusion import ImuNoise, NominalState
from jaxtraj.fusion.eskf import _inv_spd6, _select
from jaxtraj.fusion.imu import (
    apply_transition,
    boxminus,
    boxplus,
    error_transition,
    measurement_jacobian,
    process_noise,
    propagate_covariance,
    propagate_nominal,
    quat_multiply,
    quat_to_matrix,
    reset_jacobian,
    right_jacobian,
)
from jaxtraj.fusion.simulate import LissajousTrajectory, simulate_imu, true_states

G = jnp.array([0.0, 0.0, -9.81])


def _random_state(rng) -> NominalState:
    q = rng.normal(size=4)
    return NominalState.create(
        rng.normal(size=3),
        q / np.linalg.norm(q),
        v=rng.normal(size=3),
        b_a=rng.normal(0, 0.1, 3),
        b_g=rng.normal(0, 0.05, 3),
    )


@jax.jit  # one compilation for every case below (the cases differ in values only)
def _numeric_transition(x, gyro, accel, dt):
    def f(dx):
        return boxminus(
            propagate_nominal(boxplus(x, dx), gyro, accel, dt, G),
            propagate_nominal(x, gyro, accel, dt, G),
        )

    return jax.jacfwd(f)(jnp.zeros(15))


@pytest.mark.parametrize("rate_scale", [0.0, 1e-6, 0.05, 3.0])
def test_error_transition_equals_jacfwd(rng, rate_scale):
    x = _random_state(rng)
    gyro = jnp.asarray(x.b_g + rate_scale * rng.normal(size=3))  # scale 0: rates == bias
    accel = jnp.asarray(rng.normal(0, 3, 3))
    dt = 0.1
    J = _numeric_transition(x, gyro, accel, dt)
    F = error_transition(x, gyro, accel, dt)
    np.testing.assert_allclose(F, J, atol=1e-10)


def test_reset_jacobian_equals_jacfwd(rng):
    x = _random_state(rng)
    dx_hat = jnp.asarray(rng.normal(0, 0.3, 15))
    x_new = boxplus(x, dx_hat)
    J = jax.jacfwd(lambda dx: boxminus(boxplus(x, dx), x_new))(dx_hat)
    np.testing.assert_allclose(reset_jacobian(dx_hat[6:9]), J, atol=1e-10)
    # its first-order form is Sola's I - [dtheta/2]x
    small = jnp.asarray([1e-4, -2e-4, 3e-4])
    G = reset_jacobian(small)[6:9, 6:9]
    from jaxtraj.fusion.imu import skew

    np.testing.assert_allclose(G, np.eye(3) - skew(small / 2), atol=1e-7)


def test_measurement_jacobian_equals_jacfwd(rng):
    x = _random_state(rng)

    def h(dx):
        y = boxplus(x, dx)
        return jnp.concatenate([y.p - x.p, (jaxlie.SO3(x.q).inverse() @ jaxlie.SO3(y.q)).log()])

    H = measurement_jacobian()
    np.testing.assert_allclose(jax.jacfwd(h)(jnp.zeros(15)), H, atol=1e-12)
    M = jnp.asarray(rng.normal(size=(15, 7)))
    np.testing.assert_allclose(_select(M), H @ M, atol=0)


@pytest.mark.parametrize("scale", [0.0, 1e-7, 0.05, 0.15, 0.3, 2.5])
def test_right_jacobian(rng, scale):
    phi = jnp.asarray(rng.normal(size=3)) * scale
    J = jax.jacfwd(lambda d: (jaxlie.SO3.exp(phi).inverse() @ jaxlie.SO3.exp(phi + d)).log())(
        jnp.zeros(3)
    )
    np.testing.assert_allclose(right_jacobian(phi), J, atol=1e-11)


def test_structured_covariance_equals_dense(rng):
    x = _random_state(rng)
    gyro, accel = jnp.asarray(rng.normal(size=3)), jnp.asarray(rng.normal(0, 3, 3))
    A = rng.normal(size=(15, 15))
    P = jnp.asarray(A @ A.T)
    from jaxtraj.fusion.imu import propagate

    noise = ImuNoise.xsens_mti()
    _, step = propagate(x, gyro, accel, 0.01, G)
    F = error_transition(x, gyro, accel, 0.01)
    Q = process_noise(noise, 0.01)
    np.testing.assert_allclose(apply_transition(step, P), F @ P, atol=1e-12)
    np.testing.assert_allclose(
        propagate_covariance(P, step, jnp.diagonal(Q)), F @ P @ F.T + Q, atol=1e-11
    )


def test_inverse_of_innovation_covariance(rng):
    A = rng.normal(size=(6, 6)) * np.array([1e-3] * 3 + [1e-4] * 3)
    S = jnp.asarray(A @ A.T + np.diag([1e-8] * 3 + [1e-9] * 3))
    inv, logdet = _inv_spd6(S)
    np.testing.assert_allclose(inv @ S, np.eye(6), atol=1e-9)
    np.testing.assert_allclose(logdet, np.linalg.slogdet(np.asarray(S))[1], rtol=1e-12)


def test_quaternion_helpers_match_jaxlie(rng):
    a, b = rng.normal(size=4), rng.normal(size=4)
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    np.testing.assert_allclose(
        quat_multiply(a, b), (jaxlie.SO3(a) @ jaxlie.SO3(b)).wxyz, atol=1e-15
    )
    np.testing.assert_allclose(quat_to_matrix(a), jaxlie.SO3(a).as_matrix(), atol=1e-15)


def test_noise_units_from_datasheet():
    n = ImuNoise.from_datasheet(
        accel_noise_ug_per_rthz=60.0,
        gyro_noise_deg_s_per_rthz=0.01,
        accel_random_walk=1e-4,
        gyro_random_walk=1e-5,
    )
    assert n.accel_noise_density == pytest.approx(60e-6 * 9.80665)
    assert n.gyro_noise_density == pytest.approx(0.01 * np.pi / 180)
    Q = process_noise(n, 0.004)
    assert Q[3, 3] == pytest.approx((60e-6 * 9.80665) ** 2 * 0.004)
    assert Q[0, 0] == 0.0 and Q[14, 14] == pytest.approx(1e-10 * 0.004)


def test_noise_free_integration_matches_truth():
    """Midpoint integration of exact IMU samples reproduces the trajectory (second order)."""
    traj = LissajousTrajectory()
    zero = ImuNoise(0.0, 0.0, 0.0, 0.0)
    errs = []
    for rate in (100.0, 200.0):
        t = jnp.arange(int(2.0 * rate) + 1) / rate
        imu, b_a, b_g = simulate_imu(jax.random.PRNGKey(0), traj, t, zero, G)
        truth = true_states(traj, t, t, b_a, b_g)
        x = jax.tree_util.tree_map(lambda a: a[0], truth)
        u = jnp.concatenate([imu.gyro, imu.accel], 1)
        mid = 0.5 * (u[1:] + u[:-1])

        def step(x, um, dt=1.0 / rate):
            x = propagate_nominal(x, um[:3], um[3:], dt, G)
            return x, x.p

        _, p = jax.lax.scan(step, x, mid)
        errs.append(float(jnp.max(jnp.abs(p - truth.p[1:]))))
    assert errs[0] < 5e-4  # metres after 2 s of pure integration at 100 Hz
    assert errs[1] < errs[0] / 3.5  # converges at second order


def test_simulated_noise_statistics():
    """Per-sample std is density / sqrt(dt); bias walk increments random_walk * sqrt(dt)."""
    noise = ImuNoise(2e-3, 1e-3, 5e-3, 1e-4)
    still = lambda t: (jnp.zeros(3, t.dtype) + t * 0, jnp.array([1.0, 0.0, 0.0, 0.0]))  # noqa: E731
    t = jnp.arange(20000) / 200.0
    imu, b_a, b_g = simulate_imu(jax.random.PRNGKey(1), still, t, noise, G)
    n_a = np.asarray(imu.accel - b_a - jnp.array([0.0, 0.0, 9.81]))
    n_g = np.asarray(imu.gyro - b_g)
    assert np.std(n_a) == pytest.approx(2e-3 * np.sqrt(200), rel=0.03)
    assert np.std(n_g) == pytest.approx(1e-3 * np.sqrt(200), rel=0.03)
    assert np.std(np.diff(np.asarray(b_a), axis=0)) == pytest.approx(5e-3 / np.sqrt(200), rel=0.03)


def test_propagation_jit_vmap_grad(rng):
    x = _random_state(rng)
    gyro = jnp.asarray(rng.normal(size=(4, 3)))
    accel = jnp.asarray(rng.normal(size=(4, 3)))
    f = lambda g, a: propagate_nominal(x, g, a, 0.01, G).p  # noqa: E731
    eager = jnp.stack([f(g, a) for g, a in zip(gyro, accel, strict=True)])
    np.testing.assert_allclose(jax.jit(jax.vmap(f))(gyro, accel), eager, atol=1e-14)
    v = jax.jit(lambda a: propagate_nominal(x, gyro[0], a, 0.01, G).v)
    q = jax.jit(lambda g: propagate_nominal(x, g, accel[0], 0.01, G).q)
    check_grads(v, (accel[0],), order=1)
    check_grads(q, (gyro[0],), order=1)

"""IMU and robot controller data from a known IMU (or camera) trajectory.

A trajectory is any JAX-traceable callable ``traj(t) -> (p_w_i (3,), q_w_i (4,))`` of a
scalar time [s]; velocity, acceleration and body angular rate come from ``jax.jacfwd``, so
the synthetic IMU is exact up to the noise. :func:`trajectory_from_samples` turns sampled
poses (arrays, e.g. from ``jaxtraj.sim``) into such a callable with a DCT basis fit, and
:func:`imu_trajectory` turns a camera trajectory ``T_w_c(t)`` into the IMU's.

The noise follows the filter's model: per-sample white noise ``density / sqrt(dt)``,
bias random walks ``random_walk * sqrt(dt)`` per sample, robot flange noise in position
(world) and local orientation, poses stamped ``latency`` seconds after they were valid.
All functions are pure and take a PRNG key, so Monte-Carlo runs are a ``vmap`` over keys.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from ..basis import DCTBasis
from .events import ImuData, RobotNoise, RobotPoses, identity_se3
from .imu import ImuNoise, NominalState

__all__ = [
    "LissajousTrajectory",
    "SimulatedRecording",
    "imu_trajectory",
    "simulate_imu",
    "simulate_recording",
    "simulate_robot",
    "trajectory_from_samples",
    "true_states",
]

Trajectory = Callable[[Array], tuple[Array, Array]]


class LissajousTrajectory(eqx.Module):
    """A smooth robot-like IMU motion: sinusoids in position and rotation vector.

    ``p(t) = centre + amplitude * sin(2 pi freq t + phase)`` and
    ``q(t) = q_base * Exp(rot_amplitude * sin(2 pi rot_freq t + rot_phase))``.
    """

    centre: Array = eqx.field(converter=jnp.asarray, default=(0.5, 0.0, 0.8))
    amplitude: Array = eqx.field(converter=jnp.asarray, default=(0.25, 0.2, 0.1))
    freq: Array = eqx.field(converter=jnp.asarray, default=(0.31, 0.43, 0.23))
    phase: Array = eqx.field(converter=jnp.asarray, default=(0.0, 1.0, 2.0))
    q_base: Array = eqx.field(converter=jnp.asarray, default=(0.0, 1.0, 0.0, 0.0))
    rot_amplitude: Array = eqx.field(converter=jnp.asarray, default=(0.3, 0.25, 0.4))
    rot_freq: Array = eqx.field(converter=jnp.asarray, default=(0.27, 0.19, 0.35))
    rot_phase: Array = eqx.field(converter=jnp.asarray, default=(0.5, 1.5, 2.5))

    def __call__(self, t):
        dt = jnp.result_type(jnp.asarray(t).dtype, jnp.float32)
        t = jnp.asarray(t, dt)
        c = lambda a: jnp.asarray(a, dt)  # noqa: E731
        p = c(self.centre) + c(self.amplitude) * jnp.sin(2 * jnp.pi * c(self.freq) * t + self.phase)
        r = c(self.rot_amplitude) * jnp.sin(2 * jnp.pi * c(self.rot_freq) * t + self.rot_phase)
        q = (jaxlie.SO3(c(self.q_base)) @ jaxlie.SO3.exp(r)).wxyz
        return p, q


def imu_trajectory(camera: Trajectory, T_i_c: jaxlie.SE3) -> Trajectory:
    """The IMU trajectory ``T_w_i(t) = T_w_c(t) T_i_c^-1`` of a camera trajectory."""

    def traj(t):
        p, q = camera(t)
        T = jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3(q), p) @ T_i_c.inverse()
        return T.translation(), T.rotation().wxyz

    return traj


def trajectory_from_samples(
    t: Float[ArrayLike, " N"], p: Float[ArrayLike, "N 3"], q: Float[ArrayLike, "N 4"], k: int
) -> Trajectory:
    """A smooth callable through sampled poses: DCT fits (k terms) of the position and
    of the rotation vector relative to the first sample (keep rotations within pi of it)."""
    t = jnp.asarray(t)
    basis = DCTBasis.from_times(t, k)
    A = basis(t)
    q0 = jaxlie.SO3(jnp.asarray(q)[0])
    rv = jax.vmap(lambda qq: (q0.inverse() @ jaxlie.SO3(qq)).log())(jnp.asarray(q))
    coef_p = jnp.linalg.lstsq(A, jnp.asarray(p))[0]
    coef_r = jnp.linalg.lstsq(A, rv)[0]

    def traj(s):
        phi = basis(jnp.reshape(s, (1,)))[0]
        return phi @ coef_p, (q0 @ jaxlie.SO3.exp(phi @ coef_r)).wxyz

    return traj


def _kinematics(traj: Trajectory, t):
    """Position, velocity, acceleration, orientation and body rate at scalar time t."""
    pos = lambda s: traj(s)[0]  # noqa: E731
    rot = lambda s: jaxlie.SO3(traj(s)[1]).as_matrix()  # noqa: E731
    p, q = traj(t)
    v = jax.jacfwd(pos)(t)
    a = jax.jacfwd(jax.jacfwd(pos))(t)
    R = rot(t)
    W = R.T @ jax.jacfwd(rot)(t)
    w = jnp.stack([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]]) * 0.5
    return p, v, a, q, w


def _walk(key, sigma, dt, x0):
    """Random walk samples ``x_k`` (N, 3) starting at ``x0`` with steps ``sigma sqrt(dt)``."""
    steps = jax.random.normal(key, (dt.shape[0], 3), dt.dtype) * (sigma * jnp.sqrt(dt))[:, None]
    steps = steps.at[0].set(0.0)
    return x0 + jnp.cumsum(steps, axis=0)


@eqx.filter_jit
def simulate_imu(
    key: PRNGKeyArray,
    traj: Trajectory,
    t: Float[ArrayLike, " N"],
    noise: ImuNoise,
    gravity_w: Float[ArrayLike, " 3"] = (0.0, 0.0, -9.81),
    b_a0: Float[ArrayLike, " 3"] = (0.0, 0.0, 0.0),
    b_g0: Float[ArrayLike, " 3"] = (0.0, 0.0, 0.0),
) -> tuple[ImuData, Float[Array, "N 3"], Float[Array, "N 3"]]:
    """IMU samples at times ``t`` (N,) [s] with white noise and random-walk biases.

    Returns:
        ``(imu, b_a, b_g)``: the samples and the true biases at each sample.
    """
    t = jnp.asarray(t)
    dtype = t.dtype
    _, _, a, q, w = jax.vmap(lambda s: _kinematics(traj, s))(t)
    g = jnp.asarray(gravity_w, dtype)
    f = jax.vmap(lambda qq, aa: jaxlie.SO3(qq).inverse().apply(aa - g))(q, a)
    dt = jnp.diff(t, append=t[-1:] + (t[-1] - t[-2]))
    dt_prev = jnp.concatenate([dt[:1], dt[:-1]])
    k1, k2, k3, k4 = jax.random.split(key, 4)
    b_a = _walk(k1, noise.accel_random_walk, dt_prev, jnp.asarray(b_a0, dtype))
    b_g = _walk(k2, noise.gyro_random_walk, dt_prev, jnp.asarray(b_g0, dtype))
    # per-sample white noise density / sqrt(sample interval)
    sd = 1.0 / jnp.sqrt(0.5 * (dt + dt_prev))[:, None]
    n_a = jax.random.normal(k3, f.shape, dtype) * noise.accel_noise_density * sd
    n_g = jax.random.normal(k4, w.shape, dtype) * noise.gyro_noise_density * sd
    return ImuData(t=t, gyro=w + b_g + n_g, accel=f + b_a + n_a), b_a, b_g


@eqx.filter_jit
def simulate_robot(
    key: PRNGKeyArray,
    traj: Trajectory,
    t_valid: Float[ArrayLike, " M"],
    noise: RobotNoise,
    *,
    latency: Float[ArrayLike, ""] = 0.0,
    T_f_c: jaxlie.SE3 | None = None,
    T_i_c: jaxlie.SE3 | None = None,
) -> RobotPoses:
    """Noisy flange poses ``T_w_f = T_w_i T_i_c T_f_c^-1`` valid at ``t_valid`` and
    stamped ``t_valid + latency`` (robot clock)."""
    t_valid = jnp.asarray(t_valid)
    dtype = t_valid.dtype
    ident = identity_se3(dtype)
    T_f_c = ident if T_f_c is None else T_f_c
    T_i_c = ident if T_i_c is None else T_i_c
    p_i, q_i = jax.vmap(traj)(t_valid)
    T_w_i = jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3(q_i), p_i)
    T_w_f = T_w_i @ T_i_c @ T_f_c.inverse()
    k1, k2 = jax.random.split(key)
    n_p = jax.random.normal(k1, p_i.shape, dtype) * noise.position
    n_r = jax.random.normal(k2, p_i.shape, dtype) * noise.orientation
    q = (T_w_f.rotation() @ jaxlie.SO3.exp(n_r)).wxyz
    return RobotPoses(t=t_valid + latency, p=T_w_f.translation() + n_p, q=q)


@eqx.filter_jit
def true_states(
    traj: Trajectory,
    t: Float[ArrayLike, " E"],
    imu_t: Float[ArrayLike, " N"],
    b_a: Float[ArrayLike, "N 3"],
    b_g: Float[ArrayLike, "N 3"],
) -> NominalState:
    """True nominal states at times ``t`` (biases held from the latest IMU sample)."""
    t = jnp.asarray(t)
    p, v, _, q, _ = jax.vmap(lambda s: _kinematics(traj, s))(t)
    k = jnp.clip(jnp.searchsorted(jnp.asarray(imu_t), t, side="right") - 1, 0, None)
    return NominalState(p=p, v=v, q=q, b_a=jnp.asarray(b_a)[k], b_g=jnp.asarray(b_g)[k])


class SimulatedRecording(eqx.Module):
    """A synthetic recording: sensor data and the truth behind it.

    Attributes:
        imu: IMU samples; robot: flange poses stamped on the robot clock;
        image_times: (F,) image times [s];
        b_a, b_g: (N, 3) true biases at the IMU samples;
        latency: the true robot latency [s].
    """

    imu: ImuData
    robot: RobotPoses
    image_times: Array
    b_a: Array
    b_g: Array
    latency: Array


@eqx.filter_jit
def simulate_recording(
    key: PRNGKeyArray,
    traj: Trajectory,
    *,
    duration: float,
    imu_noise: ImuNoise,
    robot_noise: RobotNoise,
    imu_rate: float = 250.0,
    robot_period: float = 0.012,
    image_rate: float = 30.0,
    latency: float = 0.004,
    imu_jitter: float = 0.0,
    b_a0: Float[ArrayLike, " 3"] = (0.02, -0.03, 0.05),
    b_g0: Float[ArrayLike, " 3"] = (0.002, -0.001, 0.003),
    T_f_c: jaxlie.SE3 | None = None,
    T_i_c: jaxlie.SE3 | None = None,
    gravity_w: Float[ArrayLike, " 3"] = (0.0, 0.0, -9.81),
    dtype=jnp.float64,
) -> SimulatedRecording:
    """IMU at ``imu_rate`` [Hz] (optional uniform jitter, a fraction of the period),
    robot poses every ``robot_period`` [s] arriving ``latency`` [s] late, and image times
    at ``image_rate`` [Hz], over ``[0, duration]``. Sizes are static; vmap over ``key``."""
    n = round(duration * imu_rate) + 1
    m = int(duration / robot_period)
    f = int(duration * image_rate)
    k_t, k_imu, k_rob = jax.random.split(key, 3)
    t = jnp.arange(n, dtype=dtype) / imu_rate
    if imu_jitter:
        jit = jax.random.uniform(k_t, (n,), dtype, -0.5, 0.5) * (imu_jitter / imu_rate)
        t = t + jit.at[0].set(0.0)
    imu, b_a, b_g = simulate_imu(k_imu, traj, t, imu_noise, gravity_w, b_a0, b_g0)
    t_valid = (jnp.arange(m, dtype=dtype) + 0.5) * robot_period
    robot = simulate_robot(
        k_rob, traj, t_valid, robot_noise, latency=latency, T_f_c=T_f_c, T_i_c=T_i_c
    )
    images = (jnp.arange(f, dtype=dtype) + 0.25) / image_rate
    return SimulatedRecording(
        imu=imu,
        robot=robot,
        image_times=images,
        b_a=b_a,
        b_g=b_g,
        latency=jnp.asarray(latency, dtype),
    )

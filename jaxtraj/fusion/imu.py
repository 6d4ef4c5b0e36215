"""IMU model for the error-state filter: noise in datasheet units, nominal kinematics,
error-state Jacobians, injection and reset.

State (Sola, "Quaternion kinematics for the error-state Kalman filter", 2017):

* nominal ``x = (p_w_i, v_w, q_w_i, b_a, b_g)``: IMU position and velocity in the world,
  orientation ``q_w_i`` (w, x, y, z; maps IMU vectors into the world), accelerometer and
  gyroscope biases in the IMU frame;
* error ``dx = (dp, dv, dtheta, db_a, db_g)`` (15,), with the orientation error *local*
  (right): ``R_true = R Exp(dtheta)``.

The IMU measures ``omega_m = omega + b_g + n_g`` and ``a_m = R^T (a_w - g_w) + b_a + n_a``.
Over an interval ``dt`` with bias-corrected rates ``omega = omega_m - b_g``, ``a = a_m -
b_a`` (taken at the interval's midpoint) the nominal state moves by the midpoint rule::

    R_h = R Exp(omega dt / 2),  acc = R_h a + g_w
    p' = p + v dt + acc dt^2 / 2,  v' = v + acc dt,  R' = R Exp(omega dt)

which is second-order accurate; :func:`error_transition` is its exact Jacobian with
respect to the error state (the tests compare it with ``jax.jacfwd``).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import jaxlie
from jaxtyping import Array, ArrayLike, Float

__all__ = [
    "ImuNoise",
    "NominalState",
    "boxminus",
    "boxplus",
    "error_transition",
    "process_noise",
    "propagate_nominal",
    "reset_jacobian",
    "right_jacobian",
    "skew",
]

STANDARD_GRAVITY = 9.80665


class ImuNoise(eqx.Module):
    """IMU noise in datasheet units (continuous-time densities).

    Attributes:
        accel_noise_density: white accelerometer noise [m/s^2/sqrt(Hz)] (velocity random
            walk). A datasheet's ``ug/sqrt(Hz)`` times ``9.80665e-6``.
        gyro_noise_density: white gyroscope noise [rad/s/sqrt(Hz)] (angle random walk).
            A datasheet's ``deg/s/sqrt(Hz)`` times ``pi/180``.
        accel_random_walk: accelerometer bias random walk [m/s^3/sqrt(Hz)].
        gyro_random_walk: gyroscope bias random walk [rad/s^2/sqrt(Hz)].

    Samples taken every ``dt`` seconds have a per-sample standard deviation of
    ``density / sqrt(dt)``; a bias moves by ``random_walk * sqrt(dt)`` per sample.
    """

    accel_noise_density: Float[ArrayLike, ""]
    gyro_noise_density: Float[ArrayLike, ""]
    accel_random_walk: Float[ArrayLike, ""]
    gyro_random_walk: Float[ArrayLike, ""]

    @classmethod
    def from_datasheet(
        cls,
        *,
        accel_noise_ug_per_rthz: float,
        gyro_noise_deg_s_per_rthz: float,
        accel_random_walk: float,
        gyro_random_walk: float,
    ) -> ImuNoise:
        """Noise from the units printed on IMU datasheets (ug/sqrt(Hz), deg/s/sqrt(Hz)).

        The bias random walks are given in SI units ([m/s^3/sqrt(Hz)], [rad/s^2/sqrt(Hz)])
        because datasheets quote bias *instability*, which needs a modelling choice.
        """
        return cls(
            accel_noise_density=accel_noise_ug_per_rthz * 1e-6 * STANDARD_GRAVITY,
            gyro_noise_density=gyro_noise_deg_s_per_rthz * jnp.pi / 180.0,
            accel_random_walk=accel_random_walk,
            gyro_random_walk=gyro_random_walk,
        )

    @classmethod
    def xsens_mti(cls) -> ImuNoise:
        """An Xsens MTi-300-class MEMS IMU: 60 ug/sqrt(Hz), 0.01 deg/s/sqrt(Hz).

        Bias random walks (4e-5 m/s^3/sqrt(Hz), 1e-6 rad/s^2/sqrt(Hz)) are chosen so that
        the bias drifts by about the datasheet's in-run bias stability within ~100 s.
        """
        return cls.from_datasheet(
            accel_noise_ug_per_rthz=60.0,
            gyro_noise_deg_s_per_rthz=0.01,
            accel_random_walk=4e-5,
            gyro_random_walk=1e-6,
        )

    @classmethod
    def adis16448(cls) -> ImuNoise:
        """The ADIS16448 of the EuRoC MAV dataset, values of its ``sensor.yaml``."""
        return cls(
            accel_noise_density=2.0e-3,
            gyro_noise_density=1.6968e-4,
            accel_random_walk=3.0e-3,
            gyro_random_walk=1.9393e-5,
        )


class NominalState(eqx.Module):
    """Nominal IMU state (one time; leading axes come from ``vmap`` or stacking).

    Attributes:
        p: (3,) position of the IMU in the world ``p_w_i`` [m].
        v: (3,) velocity in the world [m/s].
        q: (4,) orientation ``q_w_i`` (w, x, y, z).
        b_a: (3,) accelerometer bias [m/s^2].
        b_g: (3,) gyroscope bias [rad/s].
    """

    p: Float[Array, "*b 3"]
    v: Float[Array, "*b 3"]
    q: Float[Array, "*b 4"]
    b_a: Float[Array, "*b 3"]
    b_g: Float[Array, "*b 3"]

    @classmethod
    def create(cls, p, q, v=None, b_a=None, b_g=None, dtype=None) -> NominalState:
        """A state from arrays; missing velocity and biases are zero."""
        p = jnp.asarray(p, dtype)
        dtype = jnp.result_type(p.dtype, jnp.float32)
        z = jnp.zeros_like(p, dtype)
        return cls(
            p=p.astype(dtype),
            v=z if v is None else jnp.asarray(v, dtype),
            q=jnp.asarray(q, dtype),
            b_a=z if b_a is None else jnp.asarray(b_a, dtype),
            b_g=z if b_g is None else jnp.asarray(b_g, dtype),
        )

    @property
    def R(self) -> Array:
        """(3, 3) rotation matrix ``R_w_i``."""
        return jaxlie.SO3(self.q).as_matrix()

    @property
    def pose(self) -> jaxlie.SE3:
        """The IMU pose ``T_w_i`` as a jaxlie ``SE3``."""
        return jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3(self.q), self.p)


def skew(w: Float[ArrayLike, "*b 3"]) -> Float[Array, "*b 3 3"]:
    """The cross-product matrix ``[w]x`` with ``[w]x u = w x u``."""
    w = jnp.asarray(w)
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack(
        [jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1), jnp.stack([-y, x, o], -1)], -2
    )


def right_jacobian(phi: Float[ArrayLike, " 3"]) -> Float[Array, "3 3"]:
    """Right Jacobian of SO(3): ``Exp(phi + d) ~ Exp(phi) Exp(J_r(phi) d)``.

    ``J_r = I - (1 - cos t)/t^2 [phi]x + (t - sin t)/t^3 [phi]x^2`` with ``t = |phi|``;
    the series is used near zero (double ``where``, finite gradients).
    """
    phi = jnp.asarray(phi)
    t2 = jnp.sum(phi * phi)
    small = t2 < 1e-8
    t2s = jnp.where(small, 1.0, t2)
    t = jnp.sqrt(t2s)
    a = jnp.where(small, 0.5 - t2 / 24.0, (1.0 - jnp.cos(t)) / t2s)
    b = jnp.where(small, 1.0 / 6.0 - t2 / 120.0, (t - jnp.sin(t)) / (t2s * t))
    S = skew(phi)
    return jnp.eye(3, dtype=phi.dtype) - a * S + b * (S @ S)


def _exp_matrix(phi: Array) -> Array:
    return jaxlie.SO3.exp(phi).as_matrix()


def propagate_nominal(
    x: NominalState,
    gyro: Float[ArrayLike, " 3"],
    accel: Float[ArrayLike, " 3"],
    dt: Float[ArrayLike, ""],
    gravity_w: Float[ArrayLike, " 3"],
) -> NominalState:
    """Move the nominal state over ``dt`` [s] with IMU rates taken at the midpoint.

    Args:
        x: nominal state at the start of the interval.
        gyro: (3,) measured angular rate [rad/s] (bias not removed).
        accel: (3,) measured specific force [m/s^2] (bias not removed).
        dt: interval length [s], >= 0.
        gravity_w: (3,) gravity in the world, e.g. ``(0, 0, -9.81)``.
    """
    dt = jnp.asarray(dt, x.p.dtype)
    w = jnp.asarray(gyro, x.p.dtype) - x.b_g
    a = jnp.asarray(accel, x.p.dtype) - x.b_a
    rot = jaxlie.SO3(x.q)
    half = rot @ jaxlie.SO3.exp(0.5 * dt * w)
    acc = half.apply(a) + jnp.asarray(gravity_w, x.p.dtype)
    q = (rot @ jaxlie.SO3.exp(dt * w)).normalize().wxyz
    return NominalState(
        p=x.p + x.v * dt + 0.5 * dt * dt * acc, v=x.v + acc * dt, q=q, b_a=x.b_a, b_g=x.b_g
    )


def error_transition(
    x: NominalState, gyro: Float[ArrayLike, " 3"], accel: Float[ArrayLike, " 3"], dt
) -> Float[Array, "15 15"]:
    """Error-state transition ``F`` (15, 15) of :func:`propagate_nominal`: ``dx' = F dx``.

    Blocks (``E = Exp(omega dt)``, ``E_h = Exp(omega dt / 2)``, ``J = J_r``)::

        d acc / d dtheta = -R_h [a]x E_h^T,  d acc / d db_a = -R_h,
        d acc / d db_g   =  R_h [a]x J(omega dt/2) dt/2,
        dp' = dp + dv dt + d acc dt^2/2,   dv' = dv + d acc dt,
        dtheta' = E^T dtheta - J(omega dt) dt db_g.
    """
    dtype = x.p.dtype
    dt = jnp.asarray(dt, dtype)
    w = jnp.asarray(gyro, dtype) - x.b_g
    a = jnp.asarray(accel, dtype) - x.b_a
    R = x.R
    E_h = _exp_matrix(0.5 * dt * w)
    R_h = R @ E_h
    Ra = R_h @ skew(a)
    A_th = -Ra @ E_h.T
    A_ba = -R_h
    A_bg = Ra @ right_jacobian(0.5 * dt * w) * (0.5 * dt)
    I3 = jnp.eye(3, dtype=dtype)
    Z = jnp.zeros((3, 3), dtype)
    h = 0.5 * dt * dt
    rows = [
        [I3, dt * I3, h * A_th, h * A_ba, h * A_bg],
        [Z, I3, dt * A_th, dt * A_ba, dt * A_bg],
        [Z, Z, _exp_matrix(dt * w).T, Z, -dt * right_jacobian(dt * w)],
        [Z, Z, Z, I3, Z],
        [Z, Z, Z, Z, I3],
    ]
    return jnp.block(rows)


def process_noise(noise: ImuNoise, dt, dtype=None) -> Float[Array, "15 15"]:
    """Discrete process noise ``Q`` (15, 15) over ``dt`` [s]: velocity ``s_a^2 dt``,
    angle ``s_g^2 dt``, biases ``s_aw^2 dt`` and ``s_gw^2 dt`` (diagonal)."""
    dt = jnp.asarray(dt, dtype)
    one = jnp.ones(3, dt.dtype)
    d = jnp.concatenate(
        [
            0.0 * one,
            jnp.square(noise.accel_noise_density) * one,
            jnp.square(noise.gyro_noise_density) * one,
            jnp.square(noise.accel_random_walk) * one,
            jnp.square(noise.gyro_random_walk) * one,
        ]
    )
    return jnp.diag(d * dt)


def boxplus(x: NominalState, dx: Float[ArrayLike, " 15"]) -> NominalState:
    """Inject an error into the nominal state: ``x (+) dx`` (right orientation error)."""
    dx = jnp.asarray(dx, x.p.dtype)
    q = (jaxlie.SO3(x.q) @ jaxlie.SO3.exp(dx[6:9])).normalize().wxyz
    return NominalState(
        p=x.p + dx[0:3], v=x.v + dx[3:6], q=q, b_a=x.b_a + dx[9:12], b_g=x.b_g + dx[12:15]
    )


def boxminus(x: NominalState, y: NominalState) -> Float[Array, " 15"]:
    """The error ``dx = x (-) y`` with ``y (+) dx = x``; orientation ``Log(R_y^T R_x)``."""
    dth = (jaxlie.SO3(y.q).inverse() @ jaxlie.SO3(x.q)).log()
    return jnp.concatenate([x.p - y.p, x.v - y.v, dth, x.b_a - y.b_a, x.b_g - y.b_g])


def reset_jacobian(dtheta: Float[ArrayLike, " 3"]) -> Float[Array, "15 15"]:
    """Reset Jacobian ``G`` (15, 15) applied as ``P <- G P G^T`` after injecting ``dx``.

    The error after the reset is ``(x (+) dx) (-) (x (+) dx_hat)``; its Jacobian at
    ``dx = dx_hat`` is identity except the orientation block ``J_r(dtheta_hat)``, whose
    first-order form is Sola's (2017, eq. 287) ``I - [dtheta_hat / 2]x``.
    """
    dtheta = jnp.asarray(dtheta)
    G = jnp.eye(15, dtype=dtheta.dtype)
    return G.at[6:9, 6:9].set(right_jacobian(dtheta))

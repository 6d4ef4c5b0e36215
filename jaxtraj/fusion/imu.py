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

from typing import NamedTuple

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
    "measurement_jacobian",
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


def _mm(A: Array, B: Array) -> Array:
    """Small matrix product as a fusible multiply-sum (cheaper than a dot call for tiny
    matrices on CPU)."""
    return jnp.sum(A[..., :, :, None] * B[..., None, :, :], axis=-2)


def _x_minus_sin_over_x3(x: Array) -> Array:
    """``(x - sin x) / x^3``, with its series below 0.2 (no cancellation)."""
    x2 = x * x
    small = x < 0.2
    xs = jnp.where(small, 1.0, x)
    series = 1.0 / 6.0 - x2 / 120.0 + x2 * x2 / 5040.0 - x2 * x2 * x2 / 362880.0
    return jnp.where(small, series, (xs - jnp.sin(xs)) / (xs * xs * xs))


def _so3_terms(phi: Array):
    """``Exp(phi)`` as a quaternion and matrix, ``Exp(phi/2)``, ``J_r(phi)``, ``J_r(phi/2)``
    from one sine/cosine pair (Rodrigues' formulas with safe small-angle limits)."""
    t2 = jnp.sum(phi * phi)
    tiny = t2 < 1e-12
    t2s = jnp.where(tiny, 1.0, t2)
    t = jnp.where(tiny, 0.0, jnp.sqrt(t2s))
    ts = jnp.where(tiny, 1.0, t)
    s, c = jnp.sin(0.5 * t), jnp.cos(0.5 * t)
    a = jnp.where(tiny, 0.5 - t2 / 48.0, s / ts)  # sin(t/2) / t
    S = skew(phi)
    S2 = _mm(S, S)
    eye = jnp.eye(3, dtype=phi.dtype)
    q = jnp.concatenate([c[None], a * phi])
    E = eye + 2.0 * c * a * S + 2.0 * a * a * S2
    E_h = eye + a * S + (a * a / (1.0 + c)) * S2
    J = eye - 2.0 * a * a * S + _x_minus_sin_over_x3(t) * S2
    J_h = eye - (2.0 * a * a / (1.0 + c)) * S + 0.25 * _x_minus_sin_over_x3(0.5 * t) * S2
    return q, E, E_h, J, J_h


def quat_multiply(a: Float[ArrayLike, " 4"], b: Float[ArrayLike, " 4"]) -> Float[Array, " 4"]:
    """Hamilton product ``a * b`` of (w, x, y, z) quaternions."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    w = a[0] * b[0] - jnp.dot(a[1:], b[1:])
    v = a[0] * b[1:] + b[0] * a[1:] + jnp.cross(a[1:], b[1:])
    return jnp.concatenate([w[None], v])


def quat_to_matrix(q: Float[ArrayLike, " 4"]) -> Float[Array, "3 3"]:
    """Rotation matrix of a unit (w, x, y, z) quaternion."""
    w, x, y, z = jnp.asarray(q)
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]),
            jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]),
            jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]),
        ]
    )


def right_jacobian(phi: Float[ArrayLike, " 3"]) -> Float[Array, "3 3"]:
    """Right Jacobian of SO(3): ``Exp(phi + d) ~ Exp(phi) Exp(J_r(phi) d)``.

    ``J_r = I - (1 - cos t)/t^2 [phi]x + (t - sin t)/t^3 [phi]x^2`` with ``t = |phi|``;
    series near zero (double ``where``, finite gradients).
    """
    return _so3_terms(jnp.asarray(phi))[3]


class ImuStep(NamedTuple):
    """The non-trivial 3x3 blocks of the error transition ``F`` of one IMU step."""

    dt: Array
    A_th: Array  # d acc / d dtheta
    A_ba: Array  # d acc / d db_a
    A_bg: Array  # d acc / d db_g
    Et: Array  # Exp(omega dt)^T
    Jdt: Array  # J_r(omega dt) dt


def propagate(
    x: NominalState,
    gyro: Float[ArrayLike, " 3"],
    accel: Float[ArrayLike, " 3"],
    dt: Float[ArrayLike, ""],
    gravity_w: Float[ArrayLike, " 3"],
) -> tuple[NominalState, ImuStep]:
    """Move the nominal state over ``dt`` [s] (midpoint rule) and return the blocks of the
    error transition; see :func:`propagate_nominal` and :func:`error_transition`."""
    dtype = x.p.dtype
    dt = jnp.asarray(dt, dtype)
    w = jnp.asarray(gyro, dtype) - x.b_g
    a = jnp.asarray(accel, dtype) - x.b_a
    q_step, E, E_h, J, J_h = _so3_terms(w * dt)
    R_h = _mm(quat_to_matrix(x.q), E_h)
    acc = R_h @ a + jnp.asarray(gravity_w, dtype)
    q = quat_multiply(x.q, q_step)
    q = q / jnp.sqrt(jnp.sum(q * q))
    x_new = NominalState(
        p=x.p + x.v * dt + 0.5 * dt * dt * acc, v=x.v + acc * dt, q=q, b_a=x.b_a, b_g=x.b_g
    )
    Ra = _mm(R_h, skew(a))
    step = ImuStep(
        dt=dt,
        A_th=-_mm(Ra, E_h.T),
        A_ba=-R_h,
        A_bg=_mm(Ra, J_h) * (0.5 * dt),
        Et=E.T,
        Jdt=J * dt,
    )
    return x_new, step


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
    return propagate(x, gyro, accel, dt, gravity_w)[0]


def apply_transition(step: ImuStep, M: Float[Array, "15 n"]) -> Float[Array, "15 n"]:
    """``F @ M`` using the block structure of ``F`` (about a fifth of a dense product)."""
    dt = step.dt
    Mp, Mv, Mt, Ma, Mg = M[0:3], M[3:6], M[6:9], M[9:12], M[12:15]
    C = _mm(step.A_th, Mt) + _mm(step.A_ba, Ma) + _mm(step.A_bg, Mg)
    return jnp.concatenate(
        [
            Mp + dt * Mv + (0.5 * dt * dt) * C,
            Mv + dt * C,
            _mm(step.Et, Mt) - _mm(step.Jdt, Mg),
            Ma,
            Mg,
        ]
    )


def propagate_covariance(
    P: Float[Array, "15 15"], step: ImuStep, q_diag: Float[Array, " 15"]
) -> Float[Array, "15 15"]:
    """``F P F^T + Q`` (symmetrised) for a diagonal ``Q``, with the structured product."""
    P = apply_transition(step, apply_transition(step, P).T)
    return 0.5 * (P + P.T) + jnp.diag(q_diag)


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
    step = propagate(x, gyro, accel, dt, jnp.zeros(3, x.p.dtype))[1]
    return apply_transition(step, jnp.eye(15, dtype=x.p.dtype))


def process_noise_diag(noise: ImuNoise, dt, dtype=None) -> Float[Array, " 15"]:
    """Diagonal of :func:`process_noise`."""
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
    return d * dt


def process_noise(noise: ImuNoise, dt, dtype=None) -> Float[Array, "15 15"]:
    """Discrete process noise ``Q`` (15, 15) over ``dt`` [s]: velocity ``s_a^2 dt``,
    angle ``s_g^2 dt``, biases ``s_aw^2 dt`` and ``s_gw^2 dt`` (diagonal)."""
    return jnp.diag(process_noise_diag(noise, dt, dtype))


def boxplus(x: NominalState, dx: Float[ArrayLike, " 15"]) -> NominalState:
    """Inject an error into the nominal state: ``x (+) dx`` (right orientation error)."""
    dx = jnp.asarray(dx, x.p.dtype)
    q = quat_multiply(x.q, _so3_terms(dx[6:9])[0])
    q = q / jnp.sqrt(jnp.sum(q * q))
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


def measurement_jacobian(dtype=jnp.float64) -> Float[Array, "6 15"]:
    """Jacobian ``H`` (6, 15) of a pose measurement ``(p, Log(R_0^T R))`` with respect to
    the error state: ``[I 0 0 0 0; 0 0 I 0 0]``."""
    H = jnp.zeros((6, 15), dtype)
    return H.at[0:3, 0:3].set(jnp.eye(3, dtype=dtype)).at[3:6, 6:9].set(jnp.eye(3, dtype=dtype))

"""One time-ordered stream of events for the filter: IMU samples, robot poses, image times.

Robot controller poses are stamped on the robot's clock when they arrive; with a
``latency`` [s] the pose stamped ``t_r`` was valid at ``t_r - latency`` on the IMU clock
(a positive latency is a pose that arrives late; a negative one absorbs a clock offset).
:func:`build_events` places every pose at the time it was valid, so the filter applies
it there (an offline or fixed-lag filter; a causal one would buffer the IMU for
``latency`` seconds, with the same result). The stream is built with ``jnp.lexsort``, so
it can be rebuilt inside ``jit``/``vmap`` for many candidate latencies.

Each IMU event carries the sample and the next one: the filter interpolates the rates
linearly between samples, so irregular sample times are handled exactly.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._checks import check_finite, check_shape, is_concrete
from .imu import skew

__all__ = [
    "IMAGE",
    "IMU",
    "POSE",
    "EventStream",
    "ImuData",
    "RobotNoise",
    "RobotPoses",
    "build_events",
    "flange_to_imu",
]

#: event kinds stored in ``EventStream.kind``
IMU, POSE, IMAGE = 0, 1, 2


class ImuData(eqx.Module):
    """IMU samples on the IMU clock.

    Attributes:
        t: (N,) sample times [s], strictly increasing (irregular spacing is fine). Use
            times relative to the recording start for float32.
        gyro: (N, 3) angular rate in the IMU frame [rad/s].
        accel: (N, 3) specific force in the IMU frame [m/s^2].
    """

    t: Float[Array, " N"]
    gyro: Float[Array, "N 3"]
    accel: Float[Array, "N 3"]


class RobotPoses(eqx.Module):
    """Flange poses ``T_w_f`` from the robot controller, stamped on the robot clock.

    Attributes:
        t: (M,) stamps [s], strictly increasing.
        p: (M, 3) flange position in the world (robot base) frame [m].
        q: (M, 4) flange orientation ``q_w_f`` (w, x, y, z).
    """

    t: Float[Array, " M"]
    p: Float[Array, "M 3"]
    q: Float[Array, "M 4"]


class RobotNoise(eqx.Module):
    """Robot pose noise: isotropic flange position [m] and local orientation [rad] sigmas."""

    position: Float[ArrayLike, ""]
    orientation: Float[ArrayLike, ""]

    @classmethod
    def kuka_class(cls) -> RobotNoise:
        """A KUKA-class industrial robot: 0.03 mm (about 0.1 mm at 3 sigma), 0.1 mrad."""
        return cls(position=3e-5, orientation=1e-4)


class EventStream(eqx.Module):
    """Events sorted by time (ties: IMU, then pose, then image). Shapes for one stream.

    Attributes:
        t: (E,) event times on the IMU clock [s].
        kind: (E,) ``IMU``, ``POSE`` or ``IMAGE``.
        active: (E,) whether a pose event updates the filter (poses outside the IMU span
            are inactive).
        index: (E,) position of the event in its own input array.
        u0, u1: (E, 6) for IMU events: this and the next sample (gyro, accel).
        t1: (E,) for IMU events: the time of the next sample.
        z_p, z_q: (E, 3), (E, 4) for pose events: the measured IMU pose ``T_w_i``.
        R: (E, 6, 6) for pose events: its covariance (position, local orientation).
    """

    t: Float[Array, " E"]
    kind: Int[Array, " E"]
    active: Bool[Array, " E"]
    index: Int[Array, " E"]
    u0: Float[Array, "E 6"]
    u1: Float[Array, "E 6"]
    t1: Float[Array, " E"]
    z_p: Float[Array, "E 3"]
    z_q: Float[Array, "E 4"]
    R: Float[Array, "E 6 6"]


def identity_se3(dtype) -> jaxlie.SE3:
    """The identity pose in the given dtype."""
    return jaxlie.SE3(jnp.zeros(7, dtype).at[0].set(1.0))


def _check_times(name: str, t, strict: bool = True) -> None:
    check_shape(name, t, (None,), "one timestamp per sample [s]")
    if not is_concrete(t):
        return
    arr = np.asarray(t)
    check_finite(name, arr)
    d = np.diff(arr)
    bad = np.flatnonzero(d <= 0 if strict else d < 0)
    if bad.size:
        what = "strictly increasing" if strict else "non-decreasing"
        raise ValueError(
            f"{name}: timestamps must be {what}; first violation at index {bad[0] + 1} "
            f"({arr[bad[0]]!r} -> {arr[bad[0] + 1]!r})"
        )


def validate_imu(imu: ImuData) -> None:
    """Raise ``ValueError`` for bad shapes, unsorted or non-finite times or samples."""
    _check_times("imu.t", imu.t)
    n = np.shape(imu.t)[0]
    if n < 2:
        raise ValueError(f"imu.t: need at least 2 IMU samples, got {n}")
    check_shape("imu.gyro", imu.gyro, (n, 3), "angular rate per sample [rad/s]")
    check_shape("imu.accel", imu.accel, (n, 3), "specific force per sample [m/s^2]")
    check_finite("imu.gyro", imu.gyro)
    check_finite("imu.accel", imu.accel)


def validate_robot(robot: RobotPoses) -> None:
    """Raise ``ValueError`` for bad shapes, unsorted or non-finite stamps or poses."""
    _check_times("robot.t", robot.t)
    m = np.shape(robot.t)[0]
    check_shape("robot.p", robot.p, (m, 3), "flange position per pose [m]")
    check_shape("robot.q", robot.q, (m, 4), "flange quaternion (w, x, y, z) per pose")
    check_finite("robot.p", robot.p)
    check_finite("robot.q", robot.q)
    if is_concrete(robot.q):
        norms = np.linalg.norm(np.asarray(robot.q), axis=-1)
        bad = np.flatnonzero(np.abs(norms - 1) > 1e-3)
        if bad.size:
            raise ValueError(f"robot.q: quaternion at index {bad[0]} has norm {norms[bad[0]]}")


def flange_to_imu(
    p_w_f, q_w_f, noise: RobotNoise, T_f_c: jaxlie.SE3, T_i_c: jaxlie.SE3
) -> tuple[Array, Array, Array]:
    """Map one flange pose to the IMU pose ``T_w_i = T_w_f T_f_c T_c_i`` and its (6, 6)
    covariance (position, local orientation) from the flange noise and the lever arm.

    With ``T_w_f <- (p + n_p, R Exp(phi))`` the IMU pose error is
    ``dp = n_p - R [t_f_i]x phi`` and ``dtheta = R_f_i^T phi``.
    """
    T_w_f = jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3(q_w_f), p_w_f)
    T_f_i = T_f_c @ T_i_c.inverse()
    T_w_i = T_w_f @ T_f_i
    R_w_f = jaxlie.SO3(q_w_f).as_matrix()
    dtype = R_w_f.dtype
    J = jnp.block(
        [
            [jnp.eye(3, dtype=dtype), -R_w_f @ skew(T_f_i.translation())],
            [jnp.zeros((3, 3), dtype), T_f_i.rotation().as_matrix().T],
        ]
    )
    sig = jnp.concatenate(
        [
            jnp.full(3, jnp.square(noise.position), dtype),
            jnp.full(3, jnp.square(noise.orientation), dtype),
        ]
    )
    cov = (J * sig) @ J.T
    return T_w_i.translation(), T_w_i.rotation().wxyz, 0.5 * (cov + cov.T)


def build_events(
    imu: ImuData,
    robot: RobotPoses,
    image_times: Float[ArrayLike, " F"] | None = None,
    *,
    noise: RobotNoise,
    latency: Float[ArrayLike, ""] = 0.0,
    T_f_c: jaxlie.SE3 | None = None,
    T_i_c: jaxlie.SE3 | None = None,
) -> EventStream:
    """Merge IMU samples, robot poses (at their valid times) and image times into one
    sorted :class:`EventStream`. Pure JAX: works under ``jit`` and ``vmap`` (e.g. over
    candidate latencies); value checks run only on concrete inputs.

    Args:
        imu: IMU samples (N).
        robot: flange poses (M), stamped on the robot clock.
        image_times: (F,) image times on the IMU clock [s], non-decreasing, or None.
        noise: robot pose noise.
        latency: [s]; the pose stamped ``t`` was valid at ``t - latency``.
        T_f_c: hand-eye transform (camera in the flange frame); identity if None.
        T_i_c: camera in the IMU frame; identity if None.

    Returns:
        an :class:`EventStream` with ``E = N + M + F`` events.
    """
    validate_imu(imu)
    validate_robot(robot)
    t_imu = jnp.asarray(imu.t)
    dtype = jnp.result_type(t_imu.dtype, jnp.float32)
    t_imu = t_imu.astype(dtype)
    n, m = t_imu.shape[0], np.shape(robot.t)[0]
    if image_times is None:
        image_times = jnp.zeros((0,), dtype)
    _check_times("image_times", image_times, strict=False)
    t_img = jnp.asarray(image_times, dtype)
    f = t_img.shape[0]
    ident = identity_se3(dtype)
    T_f_c = ident if T_f_c is None else T_f_c
    T_i_c = ident if T_i_c is None else T_i_c

    u = jnp.concatenate([jnp.asarray(imu.gyro, dtype), jnp.asarray(imu.accel, dtype)], -1)
    u1 = jnp.concatenate([u[1:], u[-1:]], 0)
    t1 = jnp.concatenate([t_imu[1:], t_imu[-1:] + (t_imu[-1] - t_imu[-2])])
    t_pose = jnp.asarray(robot.t, dtype) - jnp.asarray(latency, dtype)
    z_p, z_q, R = _flange_all(robot, noise, T_f_c, T_i_c, dtype)
    active = (t_pose >= t_imu[0]) & (t_pose <= t_imu[-1])

    def pad(x, before, after):
        widths = [(before, after)] + [(0, 0)] * (x.ndim - 1)
        return jnp.pad(x, widths)

    t = jnp.concatenate([t_imu, t_pose, t_img])
    kind = jnp.concatenate(
        [jnp.full(n, IMU, jnp.int32), jnp.full(m, POSE, jnp.int32), jnp.full(f, IMAGE, jnp.int32)]
    )
    index = jnp.concatenate([jnp.arange(k, dtype=jnp.int32) for k in (n, m, f)])
    unit_q = jnp.zeros((n + m + f, 4), dtype).at[:, 0].set(1.0)
    ev = EventStream(
        t=t,
        kind=kind,
        active=jnp.concatenate([jnp.zeros(n, bool), active, jnp.zeros(f, bool)]),
        index=index,
        u0=pad(u, 0, m + f),
        u1=pad(u1, 0, m + f),
        t1=pad(t1, 0, m + f),
        z_p=pad(z_p, n, f),
        z_q=unit_q.at[n : n + m].set(z_q),
        R=pad(R, n, f),
    )
    order = jnp.lexsort((kind, t))
    return jax.tree_util.tree_map(lambda x: jnp.take(x, order, axis=0), ev)


def _flange_all(robot: RobotPoses, noise, T_f_c, T_i_c, dtype):
    return jax.vmap(lambda p, q: flange_to_imu(p, q, noise, T_f_c, T_i_c))(
        jnp.asarray(robot.p, dtype), jnp.asarray(robot.q, dtype)
    )

"""Workpiece motion for simulated robot cells: smooth random curves, rigid motions, mocap.

The random curves are sums of a few sinusoids per axis with random, non-integer
frequencies (in cycles over the sampled time span) and phases, plus a linear drift. They
are smooth but never exactly inside a DCT span, so a trajectory-basis reconstruction has
a realistic, small basis error. All random functions take an explicit ``jax.random`` key,
are jit-compiled and vmap over keys; numbers (extent, angles) are traced, integer options
(``n_terms``) are static. :func:`bvh_curve` is a host-side helper that returns real
motion-capture paths.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._checks import check_shape
from ..io.bvh import load_bvh

__all__ = [
    "SmoothCurve",
    "bvh_curve",
    "rigid_motion",
    "sample_smooth_curve",
    "sample_times",
    "smooth_random_curve",
    "transform_points",
]


class SmoothCurve(eqx.Module):
    """A smooth 3D curve ``x(t) = offset + sum_j a_j sin(2 pi f_j (t - t0) + phi_j) + v (t - t0)``.

    Each axis has its own ``n`` terms. Evaluate with ``curve(times, derivative)``; the
    velocity and acceleration are analytic.

    Attributes:
        t0: reference time [s].
        freqs: (n, 3) frequencies [Hz].
        phases: (n, 3) phases [rad].
        amps: (n, 3) amplitudes [m].
        drift: (3,) linear velocity [m/s].
        offset: (3,) constant part [m].
    """

    t0: Float[Array, ""]
    freqs: Float[Array, "n 3"]
    phases: Float[Array, "n 3"]
    amps: Float[Array, "n 3"]
    drift: Float[Array, " 3"]
    offset: Float[Array, " 3"]

    def __call__(self, times: Float[ArrayLike, " F"], derivative: int = 0) -> Float[Array, "F 3"]:
        """Position (``derivative=0``, m), velocity (1, m/s) or acceleration (2, m/s^2)."""
        if derivative not in (0, 1, 2):
            raise ValueError(f"derivative: expected 0, 1 or 2, got {derivative}")
        dt = jnp.asarray(times, self.t0.dtype)[:, None, None] - self.t0
        w = 2 * jnp.pi * self.freqs
        arg = w * dt + self.phases
        if derivative == 0:
            waves = self.amps * jnp.sin(arg)
            return self.offset + jnp.sum(waves, axis=1) + self.drift * dt[:, 0]
        if derivative == 1:
            return jnp.sum(self.amps * w * jnp.cos(arg), axis=1) + self.drift
        return -jnp.sum(self.amps * w**2 * jnp.sin(arg), axis=1)


def _times_dtype(times) -> jnp.dtype:
    return jnp.result_type(jnp.asarray(times).dtype, jnp.float32)


def _check_curve_args(times, centre, extent, n_terms) -> None:
    check_shape("times", times, (None,), "(F,) sample times")
    if jnp.shape(times)[0] < 2:
        raise ValueError(f"times: expected at least 2 samples, got shape {jnp.shape(times)}")
    check_shape("centre", centre, (3,), "a 3D point")
    if not isinstance(n_terms, int) or isinstance(n_terms, bool) or n_terms < 1:
        raise ValueError(f"n_terms: expected a positive int, got {n_terms!r}")
    if isinstance(extent, (int, float)) and not extent > 0:
        raise ValueError(f"extent: expected a positive length in metres, got {extent}")


def _draw_curve(key, times, centre, extent, n_terms, max_freq) -> SmoothCurve:
    dtype = _times_dtype(times)
    times = jnp.asarray(times, dtype)
    t0 = times[0]
    span = times[-1] - t0
    f_max = 1.0 / span if max_freq is None else jnp.asarray(max_freq, dtype)
    u = jax.random.uniform(key, (3 * n_terms + 1, 3), dtype)  # one draw: cheap to compile
    freqs = f_max * (0.2 + 0.8 * u[:n_terms])
    phases = 2 * jnp.pi * u[n_terms : 2 * n_terms]
    amps = 0.3 + 0.7 * u[2 * n_terms : 3 * n_terms]
    drift = (u[-1] - 0.5) * jnp.sum(amps, axis=0) / span
    raw = SmoothCurve(t0, freqs, phases, amps, drift, jnp.zeros(3, dtype))(times)
    lo, hi = jnp.min(raw, axis=0), jnp.max(raw, axis=0)
    scale = jnp.asarray(extent, dtype) / jnp.max(hi - lo)
    offset = jnp.asarray(centre, dtype) - scale * 0.5 * (lo + hi)
    return SmoothCurve(t0, freqs, phases, scale * amps, scale * drift, offset)


_draw_curve_jit = eqx.filter_jit(_draw_curve)


@eqx.filter_jit
def _curve_points(key, times, centre, extent, n_terms, max_freq):
    return _draw_curve(key, times, centre, extent, n_terms, max_freq)(times)


def _num(x):
    """Python numbers as weakly typed arrays, so that jit traces them (no recompiles)."""
    return None if x is None else jnp.asarray(x)


def sample_smooth_curve(
    key: PRNGKeyArray,
    times: Float[ArrayLike, " F"],
    *,
    centre: Float[ArrayLike, " 3"] = (0.0, 0.0, 0.0),
    extent: float = 0.3,
    n_terms: int = 4,
    max_freq: float | None = None,
) -> SmoothCurve:
    """Draw a random :class:`SmoothCurve` fitted to the sample ``times`` (jit-compiled).

    Frequencies are uniform in ``[0.2, 1] * max_freq`` (default ``max_freq`` = one cycle
    over ``times[-1] - times[0]``), phases uniform, amplitudes uniform in ``[0.3, 1]``, and
    a drift of up to half the sinusoids' size over the span. The curve is then scaled so
    that its largest per-axis range over ``times`` is exactly ``extent`` and shifted so
    that the midpoint of its bounding box is ``centre``.

    Args:
        key: a ``jax.random`` key.
        times: (F,) sample times [s], increasing, ``F >= 2``.
        centre: (3,) bounding-box centre of the sampled curve [m].
        extent: largest per-axis range of the sampled curve [m], > 0.
        n_terms: sinusoids per axis (static), >= 1.
        max_freq: highest frequency [Hz]; default 1 / (time span), one cycle.
    """
    _check_curve_args(times, centre, extent, n_terms)
    return _draw_curve_jit(key, times, _num(centre), _num(extent), n_terms, _num(max_freq))


def smooth_random_curve(
    key: PRNGKeyArray,
    times: Float[ArrayLike, " F"],
    *,
    centre: Float[ArrayLike, " 3"] = (0.0, 0.0, 0.0),
    extent: float = 0.3,
    n_terms: int = 4,
    max_freq: float | None = None,
) -> Float[Array, "F 3"]:
    """(F, 3) positions [m] of a random smooth curve at ``times`` (jit-compiled).

    Same arguments and curve as :func:`sample_smooth_curve`, which returns the curve
    itself (for velocities or evaluation at other times).
    """
    _check_curve_args(times, centre, extent, n_terms)
    return _curve_points(key, times, _num(centre), _num(extent), n_terms, _num(max_freq))


@eqx.filter_jit
def _rigid_motion(key, times, centre, extent, max_angle, n_terms):
    unit = jax.vmap(lambda k: _draw_curve(k, times, jnp.zeros(3), 1.0, n_terms, None)(times))
    curves = unit(jax.random.split(key))
    p_w_o = jnp.asarray(centre, curves.dtype) + extent * curves[0]
    omega = curves[1] * (max_angle / jnp.max(jnp.linalg.norm(curves[1], axis=1)))
    R_w_o = jax.vmap(lambda w: jaxlie.SO3.exp(w).as_matrix())(omega)
    return R_w_o, p_w_o


def rigid_motion(
    key: PRNGKeyArray,
    times: Float[ArrayLike, " F"],
    *,
    centre: Float[ArrayLike, " 3"] = (0.0, 0.0, 0.0),
    extent: float = 0.3,
    max_angle: float = 0.3,
    n_terms: int = 4,
) -> tuple[Float[Array, "F 3 3"], Float[Array, "F 3"]]:
    """A smooth random 6-DoF workpiece motion ``(R_w_o, p_w_o)`` (jit-compiled).

    The origin follows a random smooth curve (as :func:`smooth_random_curve`); the
    orientation is ``R_w_o(t) = SO3.exp(omega(t))`` with ``omega`` a second smooth random
    curve of rotation vectors, scaled so that ``max_t |omega(t)| = max_angle`` (so the
    rotation angle from the identity never exceeds ``max_angle``).

    Args:
        key: a ``jax.random`` key.
        times: (F,) sample times [s].
        centre, extent: bounding-box centre and size of the origin's path [m].
        max_angle: largest rotation angle from the identity [rad], >= 0.
        n_terms: sinusoids per axis (static).

    Returns:
        ``R_w_o`` (F, 3, 3) object-to-world rotations and ``p_w_o`` (F, 3) origins [m].
    """
    _check_curve_args(times, centre, extent, n_terms)
    if isinstance(max_angle, (int, float)) and max_angle < 0:
        raise ValueError(f"max_angle: expected an angle >= 0 in radians, got {max_angle}")
    return _rigid_motion(key, times, _num(centre), _num(extent), _num(max_angle), n_terms)


def sample_times(
    key: PRNGKeyArray, n_frames: int, duration: float = 10.0, *, irregular: bool = True
) -> Float[Array, " F"]:
    """(F,) increasing image times in ``[0, duration]`` [s].

    Regular: ``linspace(0, duration, F)``. Irregular: a jittered grid,
    ``t_i = duration (i + 0.5 + u_i) / F`` with ``u_i`` uniform in ``[-0.4, 0.4]``, so
    consecutive times are at least ``0.2 duration / F`` apart.
    """
    if not isinstance(n_frames, int) or n_frames < 2:
        raise ValueError(f"n_frames: expected an int >= 2, got {n_frames!r}")
    duration = jnp.asarray(duration, float)
    if not irregular:
        return jnp.linspace(0.0, 1.0, n_frames, dtype=duration.dtype) * duration
    jitter = jax.random.uniform(key, (n_frames,), duration.dtype, -0.4, 0.4)
    return duration * (jnp.arange(n_frames, dtype=duration.dtype) + 0.5 + jitter) / n_frames


def transform_points(
    R_w_o: Float[ArrayLike, "F 3 3"],
    p_w_o: Float[ArrayLike, "F 3"],
    model_points: Float[ArrayLike, "M 3"],
) -> Float[Array, "F M 3"]:
    """World positions ``R_w_o x_o + p_w_o`` of rigid-object points, (F, M, 3) [m]."""
    check_shape("R_w_o", R_w_o, (None, 3, 3), "one rotation per frame")
    F = jnp.shape(R_w_o)[0]
    check_shape("p_w_o", p_w_o, (F, 3), "one origin per frame of R_w_o")
    check_shape("model_points", model_points, (None, 3), "(M, 3) points in the object frame")
    R_w_o = jnp.asarray(R_w_o)
    return (
        jnp.einsum("fij,mj->fmi", R_w_o, jnp.asarray(model_points, R_w_o.dtype))
        + jnp.asarray(p_w_o, R_w_o.dtype)[:, None, :]
    )


def bvh_curve(
    path: str | os.PathLike,
    *,
    joint: str | int | Sequence[str | int] | None = None,
    duration: float | None = None,
    n_frames: int | None = None,
    times: ArrayLike | None = None,
    centre: ArrayLike | None = None,
    z_up: bool = True,
) -> np.ndarray:
    """A real motion-capture trajectory from a BVH file, resampled at given times (host).

    Positions come from forward kinematics (:meth:`jaxtraj.io.BVHMotion.positions`) and
    are linearly interpolated between the file's frames.

    Args:
        path: the ``.bvh`` file.
        joint: a joint name or index (default: the root, whose path is its position
            channels), or a sequence of them.
        duration: seconds from the start of the take when ``times`` is not given
            (default: the whole take).
        n_frames: number of uniform samples over ``[0, duration]`` when ``times`` is not
            given (default: the file's own frames in that interval).
        times: (F,) sample times in seconds from the first frame; overrides the above.
        centre: (3,) if given, shift the result so that its mean is ``centre`` [m].
        z_up: express in a Z-up world, ``(x, y, z)_bvh -> (x, -z, y)`` (default), or keep
            the file's Y-up axes.

    Returns:
        (F, 3) positions, or (F, J, 3) when ``joint`` is a sequence [file units, metres
        for the CMU takes]. Without ``times`` the samples are at
        ``numpy.linspace(0, duration, n_frames)``.
    """
    motion = load_bvh(path)
    many = isinstance(joint, Sequence) and not isinstance(joint, str)
    joints = [motion.joint_index(j) for j in joint] if many else [motion.joint_index(joint or 0)]
    if times is None:
        duration = motion.duration if duration is None else float(duration)
        if not 0 < duration <= motion.duration + 1e-9:
            raise ValueError(
                f"duration: expected a value in (0, {motion.duration:.6g}] s for {path}, "
                f"got {duration}"
            )
        if n_frames is None:
            n_frames = int(np.floor(duration / motion.frame_time + 1e-9)) + 1
        if not isinstance(n_frames, int) or n_frames < 2:
            raise ValueError(f"n_frames: expected an int >= 2, got {n_frames!r}")
        times = np.linspace(0.0, duration, n_frames)
    times = np.asarray(times, dtype=float)
    if times.ndim != 1 or times.size == 0:
        raise ValueError(f"times: expected shape (F,), got {times.shape}")
    if times.min() < -1e-9 or times.max() > motion.duration + 1e-9:
        raise ValueError(
            f"times: must lie in [0, {motion.duration:.6g}] s (the take {path}), got "
            f"[{times.min():.6g}, {times.max():.6g}]"
        )
    pos = motion.positions(z_up=z_up)[:, joints]  # (T, J, 3)
    T, J = pos.shape[:2]
    flat = pos.reshape(T, J * 3)
    out = np.stack([np.interp(times, motion.times, flat[:, c]) for c in range(J * 3)], axis=1)
    out = out.reshape(times.size, J, 3)
    if centre is not None:
        check_shape("centre", centre, (3,), "a 3D point")
        out = out - out.reshape(-1, 3).mean(axis=0) + np.asarray(centre, dtype=float)
    return out if many else out[:, 0]

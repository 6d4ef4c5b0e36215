"""Robot-to-IMU latency from data: maximum likelihood over candidate time offsets.

For a candidate latency ``tau`` the pose stamped ``t`` enters the filter at ``t - tau``;
the filter's innovations give the exact Gaussian log-likelihood of the robot poses given
the IMU and ``tau`` (prediction-error decomposition). :func:`latency_nll` evaluates it for
many candidates at once (``vmap`` over the candidates, each with its own sorted event
stream); :func:`estimate_latency` searches a bracket with successively finer vmapped grids
and ends with a parabola through the best three points.

A latency shifts each pose by ``v tau``, so it is observable whenever the robot moves:
about 1 ms is recovered with a KUKA-class robot moving at a few cm/s or more. Only poses
whose valid time lies inside the IMU span (after a burn-in) for *every* candidate are
scored, so all candidates see the same data.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .eskf import eskf, initial_state
from .events import (
    POSE,
    ImuData,
    RobotNoise,
    RobotPoses,
    build_events,
    validate_imu,
    validate_robot,
)
from .imu import ImuNoise

__all__ = ["LatencyEstimate", "estimate_latency", "latency_nll"]


class LatencyEstimate(eqx.Module):
    """Result of :func:`estimate_latency`.

    Attributes:
        latency: the estimate [s].
        candidates: (C,) all latencies evaluated [s] (all grids, in evaluation order).
        nll: (C,) negative log-likelihood of the scored robot poses at each candidate.
        num_poses: number of robot poses scored.
    """

    latency: Float[Array, ""]
    candidates: Float[Array, " C"]
    nll: Float[Array, " C"]
    num_poses: int = eqx.field(static=True)


def _scored(robot_t, imu_t, lat_min, lat_max, burn_in):
    t = np.asarray(robot_t)
    t0, t1 = float(np.asarray(imu_t)[0]), float(np.asarray(imu_t)[-1])
    return (t - lat_max >= t0 + burn_in) & (t - lat_min <= t1)


@eqx.filter_jit
def _nll_many(imu, robot, latencies, scored, P0, noise, robot_noise, T_f_c, T_i_c, gravity_w):
    def one(tau):
        ev = build_events(imu, robot, noise=robot_noise, latency=tau, T_f_c=T_f_c, T_i_c=T_i_c)
        res = eskf(ev, initial_state(ev), P0, noise, gravity_w, store="diag")
        use = (res.kind == POSE) & scored[jnp.clip(res.index, 0, scored.shape[0] - 1)]
        return jnp.sum(jnp.where(use, res.nll, 0.0))

    return jax.vmap(one)(latencies)


def latency_nll(
    imu: ImuData,
    robot: RobotPoses,
    latencies: Float[ArrayLike, " C"],
    P0: Float[ArrayLike, "15 15"],
    noise: ImuNoise,
    robot_noise: RobotNoise,
    *,
    T_f_c: jaxlie.SE3 | None = None,
    T_i_c: jaxlie.SE3 | None = None,
    gravity_w: Float[ArrayLike, " 3"] = (0.0, 0.0, -9.81),
    burn_in: float = 0.5,
    scored_range: tuple[float, float] | None = None,
) -> Float[Array, " C"]:
    """Negative log-likelihood of the robot poses for each candidate latency.

    Args:
        imu, robot: the recording (robot stamps on the robot clock).
        latencies: (C,) candidate latencies [s].
        P0: (15, 15) prior covariance of the starting state (taken from the first poses).
        noise, robot_noise: IMU and robot noise models.
        T_f_c, T_i_c: hand-eye and IMU-camera transforms (identity if None).
        gravity_w: (3,) gravity in the world [m/s^2].
        burn_in: seconds after the first IMU sample whose poses are not scored.
        scored_range: ``(min, max)`` latency range that decides which poses are scored
            (default: the candidates' range), so that several calls are comparable.

    Returns:
        (C,) negative log-likelihoods (lower is better).
    """
    validate_imu(imu)
    validate_robot(robot)
    lat = np.asarray(latencies, float).reshape(-1)
    if not np.all(np.isfinite(lat)):
        raise ValueError("latencies: all candidates must be finite")
    lo, hi = (lat.min(), lat.max()) if scored_range is None else scored_range
    scored = _scored(robot.t, imu.t, lo, hi, burn_in)
    if scored.sum() < 2:
        raise ValueError(
            "robot: fewer than 2 poses fall inside the IMU span after the burn-in for all "
            f"candidate latencies in [{lo}, {hi}] s"
        )
    dtype = jnp.asarray(imu.t).dtype
    return _nll_many(
        imu,
        robot,
        jnp.asarray(lat, dtype),
        jnp.asarray(scored),
        jnp.asarray(P0, dtype),
        noise,
        robot_noise,
        T_f_c,
        T_i_c,
        jnp.asarray(gravity_w, dtype),
    )


def estimate_latency(
    imu: ImuData,
    robot: RobotPoses,
    P0: Float[ArrayLike, "15 15"],
    noise: ImuNoise,
    robot_noise: RobotNoise,
    *,
    bracket: tuple[float, float] = (-0.02, 0.05),
    grid: int = 15,
    rounds: int = 3,
    **kwargs,
) -> LatencyEstimate:
    """Maximum-likelihood latency in ``bracket`` [s] by nested vmapped grid searches.

    Each round evaluates ``grid`` candidates (one ``vmap``) and narrows the bracket to
    the two grid steps around the best; a parabola through the final best three points
    gives the estimate. Keyword arguments go to :func:`latency_nll`.
    """
    if grid < 3 or rounds < 1:
        raise ValueError(f"grid: need grid >= 3 and rounds >= 1, got {grid}, {rounds}")
    lo, hi = map(float, bracket)
    if not hi > lo:
        raise ValueError(f"bracket: expected (low, high) with high > low, got {bracket}")
    full = (lo, hi)
    cands, nlls = [], []
    for _ in range(rounds):
        c = np.linspace(lo, hi, grid)
        n = np.asarray(
            latency_nll(imu, robot, c, P0, noise, robot_noise, scored_range=full, **kwargs)
        )
        cands.append(c)
        nlls.append(n)
        k = int(np.argmin(n))
        step = c[1] - c[0]
        lo, hi = max(full[0], c[k] - step), min(full[1], c[k] + step)
    c, n = cands[-1], nlls[-1]
    k = int(np.clip(np.argmin(n), 1, grid - 2))
    y0, y1, y2 = n[k - 1], n[k], n[k + 1]
    den = y0 - 2 * y1 + y2
    shift = 0.5 * (y0 - y2) / den if den > 0 else 0.0
    est = c[k] + np.clip(shift, -1.0, 1.0) * (c[1] - c[0])
    all_c, all_n = np.concatenate(cands), np.concatenate(nlls)
    scored = _scored(robot.t, imu.t, full[0], full[1], kwargs.get("burn_in", 0.5))
    return LatencyEstimate(
        latency=jnp.asarray(est),
        candidates=jnp.asarray(all_c),
        nll=jnp.asarray(all_n),
        num_poses=int(scored.sum()),
    )

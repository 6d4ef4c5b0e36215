"""A straightforward NumPy implementation of the same error-state filter, one event at a
time with dense matrices. It is the reference the tests compare :func:`eskf` with and the
baseline of ``benchmarks/bench_fusion.py``; it is not meant for production use.
"""

from __future__ import annotations

import math

import numpy as np

from .events import IMU, POSE, EventStream
from .imu import ImuNoise, NominalState

__all__ = ["eskf_numpy"]


def _skew(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _exp(phi):
    t = math.sqrt(phi @ phi)
    S = _skew(phi)
    if t < 1e-8:
        return np.eye(3) + S + 0.5 * S @ S
    return np.eye(3) + math.sin(t) / t * S + (1 - math.cos(t)) / t**2 * S @ S


def _jr(phi):
    t = math.sqrt(phi @ phi)
    S = _skew(phi)
    if t < 1e-3:
        return np.eye(3) - 0.5 * S + S @ S / 6.0
    return np.eye(3) - (1 - math.cos(t)) / t**2 * S + (t - math.sin(t)) / t**3 * S @ S


def _log(R):
    c = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    t = math.acos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if t < 1e-6:
        return 0.5 * v
    return t / (2 * math.sin(t)) * v


def _quat_to_matrix(q):
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _matrix_to_quat(R):
    w = math.sqrt(max(0.0, 1 + np.trace(R))) / 2
    if w > 0.1:
        return np.array(
            [
                w,
                (R[2, 1] - R[1, 2]) / (4 * w),
                (R[0, 2] - R[2, 0]) / (4 * w),
                (R[1, 0] - R[0, 1]) / (4 * w),
            ]
        )
    i = int(np.argmax(np.diag(R)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = math.sqrt(max(0.0, 1 + R[i, i] - R[j, j] - R[k, k])) * 2
    q = np.zeros(4)
    q[0] = (R[k, j] - R[j, k]) / s
    q[1 + i] = s / 4
    q[1 + j] = (R[j, i] + R[i, j]) / s
    q[1 + k] = (R[k, i] + R[i, k]) / s
    return q * np.sign(q[0]) if q[0] != 0 else q


def eskf_numpy(
    events: EventStream,
    x0: NominalState,
    P0,
    noise: ImuNoise,
    gravity_w=(0.0, 0.0, -9.81),
) -> tuple[dict, np.ndarray]:
    """Run the filter event by event in NumPy (float64).

    Returns:
        ``(states, P)``: a dict of (E, .) arrays ``p, v, q, b_a, b_g`` and the (E, 15, 15)
        covariances after every event.
    """
    ev = {k: np.asarray(getattr(events, k)) for k in ("t", "kind", "active", "t1", "u0", "u1")}
    z_p, z_q, Rs = np.asarray(events.z_p), np.asarray(events.z_q), np.asarray(events.R)
    g = np.asarray(gravity_w, float)
    p, v = np.array(x0.p, float), np.array(x0.v, float)
    R = _quat_to_matrix(np.asarray(x0.q, float))
    b_a, b_g = np.array(x0.b_a, float), np.array(x0.b_g, float)
    P = np.array(P0, float)
    q_density = np.repeat(
        [
            0.0,
            float(noise.accel_noise_density) ** 2,
            float(noise.gyro_noise_density) ** 2,
            float(noise.accel_random_walk) ** 2,
            float(noise.gyro_random_walk) ** 2,
        ],
        3,
    )
    first = int(np.argmax(ev["kind"] == IMU))
    t_last = ev["t"][first]
    seg = (ev["t"][first], ev["t1"][first], ev["u0"][first], ev["u1"][first])
    E = len(ev["t"])
    out = {k: np.zeros((E, 4 if k == "q" else 3)) for k in ("p", "v", "q", "b_a", "b_g")}
    Ps = np.zeros((E, 15, 15))
    I3 = np.eye(3)
    for e in range(E):
        t = max(ev["t"][e], t_last)
        dt = t - t_last
        span = seg[1] - seg[0] if seg[1] > seg[0] else 1.0
        w_i = min(max((t_last + 0.5 * dt - seg[0]) / span, 0.0), 1.0)
        u = seg[2] + w_i * (seg[3] - seg[2])
        w, a = u[:3] - b_g, u[3:] - b_a
        E_h, E_f = _exp(0.5 * dt * w), _exp(dt * w)
        R_h = R @ E_h
        acc = R_h @ a + g
        Ra = R_h @ _skew(a)
        F = np.eye(15)
        A = {"th": -Ra @ E_h.T, "ba": -R_h, "bg": Ra @ _jr(0.5 * dt * w) * (0.5 * dt)}
        F[0:3, 3:6] = dt * I3
        for cols, key in ((slice(6, 9), "th"), (slice(9, 12), "ba"), (slice(12, 15), "bg")):
            F[0:3, cols] = 0.5 * dt * dt * A[key]
            F[3:6, cols] = dt * A[key]
        F[6:9, 6:9] = E_f.T
        F[6:9, 12:15] = -dt * _jr(dt * w)
        p = p + v * dt + 0.5 * dt * dt * acc
        v = v + acc * dt
        R = R @ E_f
        P = F @ P @ F.T + np.diag(q_density * dt)
        P = 0.5 * (P + P.T)
        if ev["kind"][e] == POSE and ev["active"][e]:
            H = np.zeros((6, 15))
            H[0:3, 0:3] = I3
            H[3:6, 6:9] = I3
            r = np.concatenate([z_p[e] - p, _log(R.T @ _quat_to_matrix(z_q[e]))])
            S = H @ P @ H.T + Rs[e]
            K = np.linalg.solve(S, H @ P).T
            IKH = np.eye(15) - K @ H
            P = IKH @ P @ IKH.T + K @ Rs[e] @ K.T
            d = K @ r
            p, v, b_a, b_g = p + d[0:3], v + d[3:6], b_a + d[9:12], b_g + d[12:15]
            R = R @ _exp(d[6:9])
            G = np.eye(15)
            G[6:9, 6:9] = _jr(d[6:9])
            P = G @ P @ G.T
            P = 0.5 * (P + P.T)
        if ev["kind"][e] == IMU:
            seg = (ev["t"][e], ev["t1"][e], ev["u0"][e], ev["u1"][e])
        t_last = t
        for k, val in (("p", p), ("v", v), ("q", _matrix_to_quat(R)), ("b_a", b_a), ("b_g", b_g)):
            out[k][e] = val
        Ps[e] = P
    return out, Ps

"""Tiny, self-contained scenes for the core tests (independent of ``jaxtraj.sim``)."""

from __future__ import annotations

import numpy as np

import jaxtraj as jt

K640 = np.array([[700.0, 0.0, 319.5], [0.0, 700.0, 239.5], [0.0, 0.0, 1.0]])


def random_cameras(rng, targets, standoff=(0.5, 1.5), aim_jitter=0.02):
    """One random camera per target, on a shell in front of (below, -z) the target."""
    Ps, Rs, ts, Cs = [], [], [], []
    for x in targets:
        d = rng.normal(size=3)
        d[2] = -abs(d[2]) - 0.5
        d /= np.linalg.norm(d)
        c = x + d * rng.uniform(*standoff)
        R, t = jt.look_at(c, x + rng.normal(size=3) * aim_jitter, up_w=(0.0, 1.0, 0.0))
        R, t = np.asarray(R), np.asarray(t)
        Ps.append(K640 @ np.hstack([R, t[:, None]]))
        Rs.append(R)
        ts.append(t)
        Cs.append(c)
    return np.array(Ps), np.array(Rs), np.array(ts), np.array(Cs)


def project_np(P, X):
    h = np.einsum("fij,fj->fi", P, np.hstack([X, np.ones((len(X), 1))]))
    return h[:, :2] / h[:, 2:]


def smooth_curve(rng, times, extent=0.3):
    """Sum of sinusoids with non-integer frequencies: smooth but not in any DCT span."""
    T = times[-1] - times[0]
    out = np.zeros((len(times), 3))
    for a in range(3):
        for _ in range(3):
            f = rng.uniform(0.1, 0.8) / T
            out[:, a] += extent / 3 * np.sin(2 * np.pi * f * times * T / 1.0 + rng.uniform(0, 6.3))
    return out


def scene(rng, F=40, k=6, noise=0.0, in_span=True, irregular=True):
    """Random well-posed scene: returns dict with times, basis, X, P, uv, C."""
    times = np.sort(rng.uniform(0.0, 2.0, F)) if irregular else np.linspace(0.0, 2.0, F)
    basis = np.asarray(jt.dct_basis(times, k))
    if in_span:
        X = basis @ (rng.normal(size=(k, 3)) * 0.15)
    else:
        X = smooth_curve(rng, times)
    P, R, t, C = random_cameras(rng, X)
    uv = project_np(P, X) + noise * rng.normal(size=(F, 2))
    return dict(times=times, basis=basis, X=X, P=P, R=R, t=t, C=C, uv=uv, k=k)


def dense_lstsq(P, uv, basis, weights=None):
    """Dense NumPy reference: build Q (2F x 3F), Theta (3F x 3k), solve by lstsq."""
    F, k = basis.shape
    Q = np.zeros((2 * F, 3 * F))
    q = np.zeros(2 * F)
    w = np.ones(F) if weights is None else np.asarray(weights)
    for i in range(F):
        if w[i] == 0:
            continue
        p1, p2, p3 = P[i]
        x, y = uv[i]
        s = np.sqrt(w[i])
        Q[2 * i, 3 * i : 3 * i + 3] = s * (p1[:3] - x * p3[:3])
        Q[2 * i + 1, 3 * i : 3 * i + 3] = s * (p2[:3] - y * p3[:3])
        q[2 * i] = s * (x * p3[3] - p1[3])
        q[2 * i + 1] = s * (y * p3[3] - p2[3])
    Theta = np.kron(basis, np.eye(3))
    beta = np.linalg.lstsq(Q @ Theta, q, rcond=None)[0]
    return beta.reshape(k, 3)


def limb_scene(rng, F=150, camera="orbit", deg=2.0, noise=0.5, rate=30.0):
    """A point moving like a limb (four sinusoids of 0.2-2 Hz per axis, 0.15 m each, not in
    a small DCT span) seen from 3 m (f = 800, 640x480) by a camera orbiting it at ``deg``
    per frame, 20 deg up (``camera="orbit"``), or moving like a fast robot (the robot
    scenes' ``"fast"`` wobble pushed out to 3 m): returns times, X, P, uv."""
    from tests.test_estimators_scenes import camera_centres

    K = np.array([[800.0, 0.0, 319.5], [0.0, 800.0, 239.5], [0.0, 0.0, 1.0]])
    t = np.arange(F) / rate
    X = np.zeros((F, 3))
    for a in range(3):
        for _ in range(4):
            X[:, a] += 0.15 * np.sin(2 * np.pi * rng.uniform(0.2, 2.0) * t + rng.uniform(0, 6.3))
    X[:, 2] += 1.0
    centre = X.mean(axis=0)
    if camera == "orbit":
        ang = rng.uniform(0, 2 * np.pi) + np.deg2rad(deg) * np.arange(F)
        el = np.deg2rad(20.0)
        C = np.stack([np.cos(ang) * np.cos(el), np.sin(ang) * np.cos(el), np.full(F, np.sin(el))])
        C = C.T
    else:
        C = camera_centres(rng, t, X, camera) - centre
        C /= np.linalg.norm(C, axis=1, keepdims=True)
    P = []
    for c in centre + 3.0 * C:
        R, tc = jt.look_at(c, centre, up_w=(0.0, 0.0, 1.0))
        P.append(K @ np.hstack([np.asarray(R), np.asarray(tc)[:, None]]))
    P = np.array(P)
    return t, X, P, project_np(P, X) + noise * rng.normal(size=(F, 2))

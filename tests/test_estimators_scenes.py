"""Small robot-cell scenes for the estimator tests (independent of ``jaxtraj.sim``).

A workpiece point moves on a conveyor-like path with smooth random wobble; a robot-held
camera 0.5-1.5 m away looks at it while moving in one of several modes, from a slow,
smooth drift (real robots; hard for a DCT basis) to an independent random position per
frame (the paper's experiment). Pixels of a 640x480 camera with Gaussian noise.
"""

from __future__ import annotations

import numpy as np

import jaxtraj as jt

K640 = np.array([[700.0, 0.0, 319.5], [0.0, 700.0, 239.5], [0.0, 0.0, 1.0]])
CAMERA_MODES = ("slow", "smooth", "fast", "random")


def _wobble(rng, times, amplitude, fmin, fmax, n=3):
    out = np.zeros((len(times), 3))
    for a in range(3):
        for _ in range(n):
            f = rng.uniform(fmin, fmax)
            out[:, a] += amplitude / n * np.sin(2 * np.pi * f * times + rng.uniform(0, 2 * np.pi))
    return out


def workpiece_path(rng, times):
    """Conveyor motion (0.1-0.3 m/s) plus a smooth wobble of a few cm (0.2-2 Hz)."""
    speed = rng.uniform(0.1, 0.3)
    heading = rng.uniform(0, 2 * np.pi)
    v = speed * np.array([np.cos(heading), np.sin(heading), 0.0])
    return np.array([0.0, 0.0, 0.8]) + times[:, None] * v + _wobble(rng, times, 0.06, 0.2, 2.0)


def camera_centres(rng, times, X, mode):
    """Camera centres for a mode, 0.5-1.5 m from the point (mostly above it)."""
    F = len(times)
    d = rng.normal(size=3)
    d[2] = abs(d[2]) + 1.0
    d /= np.linalg.norm(d)
    base = X.mean(axis=0) + d * rng.uniform(0.7, 1.1)
    if mode == "slow":
        v = rng.normal(size=3)
        v *= rng.uniform(0.03, 0.08) / np.linalg.norm(v)
        return base + (times - times.mean())[:, None] * v + _wobble(rng, times, 0.01, 0.1, 0.4)
    if mode == "smooth":
        return base + _wobble(rng, times, 0.25, 0.3, 1.0)
    if mode == "fast":
        return base + _wobble(rng, times, 0.25, 2.0, 6.0)
    if mode == "random":
        dirs = rng.normal(size=(F, 3))
        dirs[:, 2] = np.abs(dirs[:, 2]) + 0.5
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        return X + dirs * rng.uniform(0.5, 1.5, (F, 1))
    raise ValueError(f"mode: expected one of {CAMERA_MODES}, got {mode!r}")


def cameras_looking_at(rng, C, X, aim_jitter=0.02):
    Ps = []
    for c, x in zip(C, X, strict=True):
        R, t = jt.look_at(c, x + rng.normal(size=3) * aim_jitter, up_w=(0.0, 1.0, 0.0))
        Ps.append(K640 @ np.hstack([np.asarray(R), np.asarray(t)[:, None]]))
    return np.array(Ps)


def project_np(P, X):
    h = np.einsum("fij,fj->fi", P, np.hstack([X, np.ones((len(X), 1))]))
    return h[:, :2] / h[:, 2:]


def robot_scene(rng, F=100, rate=100.0, mode="smooth", noise=0.3, irregular=False):
    """A dict with times (F,), true points X (F, 3), centres C, P (F, 3, 4), uv (F, 2)."""
    times = np.arange(F) / rate
    if irregular:
        times = times + rng.uniform(-0.3, 0.3, F) / rate
    X = workpiece_path(rng, times)
    C = camera_centres(rng, times, X, mode)
    P = cameras_looking_at(rng, C, X)
    clean = project_np(P, X)
    uv = clean + noise * rng.normal(size=(F, 2))
    return dict(times=times, X=X, C=C, P=P, uv=uv, clean=clean, noise=noise)


def dct_fit(P, uv, basis, weights=None):
    """(F, 3) plain DCT fit of one track by dense least squares in NumPy: the baseline the
    estimators are compared with, without compiling the solver's unrolled factorisation for
    every k (about 3 s per k at F = 60, where this takes a millisecond). The same
    minimiser as ``jt.reconstruct(P, uv, basis, weights).points`` (eq. 6, squared
    residuals weighted by ``weights``): the 3D errors of the tests' fits agree to 1.3e-12
    (relative, largest measured)."""
    P, uv, basis = (np.asarray(a, np.float64) for a in (P, uv, basis))
    F, k = basis.shape
    w = np.ones(F) if weights is None else np.asarray(weights, np.float64)
    uv = np.where((w > 0)[:, None], uv, 0.0)
    rows = P[:, :2, :] - uv[:, :, None] * P[:, 2, None, :]  # (F, 2, 4)
    sw = np.sqrt(np.repeat(w, 2))
    A = np.einsum("fri,fk->frki", rows[:, :, :3], basis).reshape(2 * F, 3 * k) * sw[:, None]
    beta = np.linalg.lstsq(A, -rows[:, :, 3].reshape(-1) * sw, rcond=None)[0]
    return basis @ beta.reshape(k, 3)


def rmse(a, b):
    return float(np.sqrt(np.mean(np.sum((np.asarray(a) - np.asarray(b)) ** 2, axis=-1))))


def test_scene_pixels_in_image_and_depths_positive(rng):
    for mode in CAMERA_MODES:
        s = robot_scene(rng, mode=mode, noise=0.0)
        assert np.all((s["clean"] > 0) & (s["clean"] < [640, 480]))
        depth = np.einsum("fj,fj->f", s["P"][:, 2, :3], s["X"]) + s["P"][:, 2, 3]
        dist = np.linalg.norm(s["X"] - s["C"], axis=1)
        assert np.all(depth > 0.3) and np.all(dist < 1.8) and np.all(dist > 0.4)


def test_scene_modes_order_camera_speed(rng):
    speeds = {}
    for mode in CAMERA_MODES:
        s = robot_scene(rng, mode=mode)
        speeds[mode] = np.mean(np.linalg.norm(np.diff(s["C"], axis=0), axis=1)) * 100.0
    assert speeds["slow"] < 0.15 < speeds["smooth"] < speeds["fast"] < speeds["random"]

"""Stone Soup UKF + unscented RTS smoother on bearings from known camera poses (baseline).

Only for ``bench_estimators.py --stonesoup``; needs ``pip install stonesoup``. Each pixel
becomes an (elevation, bearing) pair of the viewing ray in a world frame rotated so that
the mean ray points along +x (away from the bearing singularity); the sensor position is
the camera centre; the measurement noise is the pixel noise over the focal length.
"""

from __future__ import annotations

from datetime import datetime, timedelta

import numpy as np
from stonesoup.models.measurement.nonlinear import CartesianToElevationBearing
from stonesoup.models.transition.linear import (
    CombinedLinearGaussianTransitionModel,
    ConstantVelocity,
)
from stonesoup.predictor.kalman import UnscentedKalmanPredictor
from stonesoup.smoother.kalman import UnscentedKalmanSmoother
from stonesoup.types.detection import Detection
from stonesoup.types.hypothesis import SingleHypothesis
from stonesoup.types.state import GaussianState
from stonesoup.types.track import Track
from stonesoup.updater.kalman import UnscentedKalmanUpdater


def _rotation_to_x(d):
    d = d / np.linalg.norm(d)
    v, c = np.cross(d, [1.0, 0.0, 0.0]), d[0]
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def stonesoup_smoother(P, uv, times, K, sigma_px, q, x0, v0, pos_sigma=0.05, vel_sigma=0.2):
    """Smoothed positions (F, 3) [m] of one track; q: acceleration PSD [m^2/s^3]."""
    F = len(times)
    M = P[:, :, :3]
    C = -np.linalg.solve(M, P[:, :, 3][..., None])[..., 0]
    d = np.linalg.solve(M, np.concatenate([uv, np.ones((F, 1))], 1)[..., None])[..., 0]
    d = d * np.sign(np.linalg.det(M))[:, None]
    R0 = _rotation_to_x(d.mean(0))
    d, C = d @ R0.T, C @ R0.T
    elev = np.arcsin(d[:, 2] / np.linalg.norm(d, axis=1))
    bear = np.arctan2(d[:, 1], d[:, 0])
    sig = sigma_px / K[0, 0]
    t0 = datetime(2026, 1, 1)
    tm = CombinedLinearGaussianTransitionModel([ConstantVelocity(q)] * 3)
    predictor, updater = UnscentedKalmanPredictor(tm), UnscentedKalmanUpdater(None)
    x, v = R0 @ x0, R0 @ v0
    prior = GaussianState(
        np.array([x[0], v[0], x[1], v[1], x[2], v[2]])[:, None],
        np.diag([pos_sigma**2, vel_sigma**2] * 3),
        timestamp=t0 + timedelta(seconds=float(times[0])),
    )
    track = Track()
    for i in range(F):
        ts = t0 + timedelta(seconds=float(times[i]))
        model = CartesianToElevationBearing(
            ndim_state=6,
            mapping=(0, 2, 4),
            noise_covar=np.diag([sig**2, (sig / max(np.cos(elev[i]), 0.1)) ** 2]),
            translation_offset=C[i][:, None],
        )
        det = Detection(np.array([[elev[i]], [bear[i]]]), timestamp=ts, measurement_model=model)
        post = updater.update(SingleHypothesis(predictor.predict(prior, timestamp=ts), det))
        track.append(post)
        prior = post
    smoothed = UnscentedKalmanSmoother(tm).smooth(track)
    X = np.array([np.asarray(s.state_vector).ravel()[[0, 2, 4]] for s in smoothed])
    return X @ R0

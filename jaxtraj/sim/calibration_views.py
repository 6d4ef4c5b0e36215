"""Simulated hand-eye calibration sets: robot poses, target corners in the images, truth.

A planar target is seen by a camera from ``views`` robot poses. Eye-in-hand: the camera is
on the flange (``T_f_c``) and the target lies in the robot base frame (``T_b_t``);
eye-to-hand: the camera stands in the base frame (``T_b_c``) and the target is on the
flange (``T_f_t``). The robot controller reports the flange poses with noise (position
[m], rotation [rad], isotropic Gaussian), the corners are projected with OpenCV's lens
model and given Gaussian pixel noise. Used by the calibration tests and
``benchmarks/bench_calibration.py``; :func:`render_views` makes images of the same views.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["CalibrationViews", "render_views", "simulate_views"]


@dataclass(frozen=True, eq=False)
class CalibrationViews:
    """A simulated calibration set (NumPy, float64).

    Attributes:
        K, dist, image_size: the true camera ((3, 3), (5,), (width, height)).
        T_x: (4, 4) true hand-eye (``T_f_c`` eye-in-hand, ``T_b_c`` eye-to-hand).
        T_b: (4, 4) true target transform (``T_b_t`` eye-in-hand, ``T_f_t`` eye-to-hand).
        T_b_f: (V, 4, 4) the flange poses as reported (with noise).
        T_b_f_true: (V, 4, 4) the true flange poses.
        T_c_t: (V, 4, 4) true target poses in the camera.
        object_points: (N, 3) target corners [m]; uv: (V, N, 2) noisy pixels [px].
        eye_in_hand: the set-up.
    """

    K: np.ndarray
    dist: np.ndarray
    image_size: tuple[int, int]
    T_x: np.ndarray
    T_b: np.ndarray
    T_b_f: np.ndarray
    T_b_f_true: np.ndarray
    T_c_t: np.ndarray
    object_points: np.ndarray
    uv: np.ndarray
    eye_in_hand: bool


def _exp(w):
    import cv2

    return cv2.Rodrigues(np.asarray(w, float).reshape(3, 1))[0]


def _pose(R, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _look_at(position, aim, roll):
    z = aim - position
    z /= np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_w_c = np.stack([x, y, z], 1) @ _exp([0.0, 0.0, roll])
    return _pose(R_w_c, position)  # T_w_c


def simulate_views(
    object_points,
    *,
    views: int = 15,
    seed: int = 0,
    pixel_sigma: float = 0.2,
    robot_position_sigma: float = 0.2e-3,
    robot_rotation_sigma: float = np.radians(0.02),
    eye_in_hand: bool = True,
    distance: tuple[float, float] = (0.45, 0.7),
    max_tilt: float = 0.6,
    image_size: tuple[int, int] = (640, 480),
    inside: float = 1.0,
) -> CalibrationViews:
    """Draw a calibration set (see the module doc).

    Args:
        object_points: (N, 3) target corners in the target frame (z = 0 plane) [m].
        views: number of robot poses; seed: random seed.
        pixel_sigma: corner noise per coordinate [px].
        robot_position_sigma, robot_rotation_sigma: controller pose noise [m], [rad].
        eye_in_hand: camera on the flange (True) or fixed (False).
        distance: camera-to-target distance range [m]; max_tilt: largest angle between
            the viewing direction and the target normal [rad].
        image_size: (width, height) [px].
        inside: fraction of the target points that must be in the image in every view
            (below 1: partial views; ``uv`` still holds every point's projection).
    """
    import cv2

    P = np.asarray(object_points, np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"object_points: expected shape (N, 3), got {P.shape}")
    if views < 3:
        raise ValueError(f"views: expected >= 3, got {views}")
    rng = np.random.default_rng(seed)
    W, H = image_size
    K = np.array([[0.9 * W * 1.25, 0, W / 2 + 3.2], [0, 0.9 * W * 1.25, H / 2 - 2.1], [0, 0, 1]])
    dist = np.array([-0.12, 0.08, 4e-4, -3e-4, 0.0])
    X = _pose(_exp([0.02, -0.03, 1.5]), [0.012, 0.058, 0.091])
    if eye_in_hand:
        B = _pose(_exp([0.0, 0.0, 0.3]), [0.6, -0.4, 0.05])  # T_b_t: target on the table
    else:
        B = _pose(_exp([0.1, np.pi - 0.2, 0.05]), [0.02, -0.01, 0.12])  # T_f_t
    centre = P.mean(0)
    T_b_f, T_c_t = [], []
    while len(T_c_t) < views:
        az = rng.uniform(0, 2 * np.pi)
        tilt = rng.uniform(0.1, max_tilt)
        d = rng.uniform(*distance)
        direction = [np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)]
        pos_t = centre + d * np.array(direction)
        aim = centre + np.r_[rng.normal(0, 0.02, 2), 0.0]
        T_t_c = _look_at(pos_t, aim, rng.uniform(-0.6, 0.6))  # camera in the target frame
        Tct = np.linalg.inv(T_t_c)
        uv, _ = cv2.projectPoints(P, cv2.Rodrigues(Tct[:3, :3])[0], Tct[:3, 3], K, dist)
        uv = uv.reshape(-1, 2)
        if np.mean(np.all((uv > 10) & (uv < np.array([W - 10, H - 10])), 1)) < inside:
            continue
        if eye_in_hand:  # T_b_c = B T_t_c = T_b_f X
            Tbf = B @ T_t_c @ np.linalg.inv(X)
        else:  # T_b_t = X T_c_t = T_b_f B
            Tbf = X @ Tct @ np.linalg.inv(B)
        T_b_f.append(Tbf)
        T_c_t.append(Tct)
    T_b_f, T_c_t = np.stack(T_b_f), np.stack(T_c_t)
    uv = []
    for Tct in T_c_t:
        u, _ = cv2.projectPoints(P, cv2.Rodrigues(Tct[:3, :3])[0], Tct[:3, 3], K, dist)
        uv.append(u.reshape(-1, 2) + rng.normal(0, pixel_sigma, (len(P), 2)))
    noisy = np.stack(
        [
            _pose(
                _exp(rng.normal(0, robot_rotation_sigma, 3)) @ T[:3, :3],
                T[:3, 3] + rng.normal(0, robot_position_sigma, 3),
            )
            for T in T_b_f
        ]
    )
    return CalibrationViews(
        K=K,
        dist=dist,
        image_size=(int(W), int(H)),
        T_x=X,
        T_b=B,
        T_b_f=noisy,
        T_b_f_true=T_b_f,
        T_c_t=T_c_t,
        object_points=P,
        uv=np.stack(uv),
        eye_in_hand=eye_in_hand,
    )


def render_views(views: CalibrationViews, texture, *, seed: int = 0, **kw) -> list[np.ndarray]:
    """Grey images of the target texture (a :class:`~jaxtraj.sim.render.PlanarTexture` in
    the target frame) at the set's true target poses (``render``'s keyword options)."""
    from .render import render

    rng = np.random.default_rng(seed)
    return [
        render(texture, T[:3, :3], T[:3, 3], views.K, views.dist, views.image_size, rng=rng, **kw)
        for T in views.T_c_t
    ]

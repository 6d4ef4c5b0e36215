"""The design objective for the known-layout pose: per-image PnP error of an object point,
checked against Monte-Carlo runs of OpenCV's PnP (the pipeline's pose estimator)."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtraj import look_at, projection_matrix
from jaxtraj.design import (
    expected_pose_errors_for_cameras,
    gaussian_mean_norm,
    pose_point_covariances,
)
from jaxtraj.io.cell import cell_from_dict
from tests.test_design_cli import _cell

F, SIGMA, DRAWS = 12, 0.4, 150
K = np.array([[700.0, 0.0, 319.5], [0.0, 700.0, 239.5], [0.0, 0.0, 1.0]])
# the simulated workpiece's reference points: four on the plate, two on posts
LAYOUT = np.array(
    [
        [-0.06, 0.06, 0.0],
        [0.06, 0.06, 0.0],
        [-0.06, -0.06, 0.0],
        [0.06, -0.06, 0.0],
        [0.185, 0.0, 0.1],
        [-0.185, 0.0, 0.06],
    ]
)
POINT = np.array([0.05, -0.02, 0.0])


def _cameras(seed, x, distance, cone):
    """Cameras at ``distance`` from each point, directions within ``cone`` of the z axis."""
    rng = np.random.default_rng(seed)
    P = []
    for xf in x:
        d = rng.normal(size=3)
        d[2] = abs(d[2]) / cone
        c = xf + distance * d / np.linalg.norm(d)
        R, t = look_at(c, xf, (0.0, 1.0, 0.0))
        P.append(np.asarray(projection_matrix(K, R, t)))
    return np.stack(P)


def _pnp_errors(P, x, R_w_o, rng):
    """Euclidean error of the object point from SQPnP + LM on noisy pixels, (DRAWS, F)."""
    Kinv = np.linalg.inv(K)
    out = np.empty((DRAWS, len(x)))
    for f, Pf in enumerate(P):
        R_c_w, t_c_w = Kinv @ Pf[:, :3], Kinv @ Pf[:, 3]
        X = LAYOUT @ R_w_o.T + (x[f] - R_w_o @ POINT)
        h = X @ Pf[:, :3].T + Pf[:, 3]
        clean = h[:, :2] / h[:, 2:]
        for d in range(DRAWS):
            uv = clean + SIGMA * rng.normal(size=clean.shape)
            _, rvec, tvec = cv2.solvePnP(LAYOUT, uv, K, None, flags=cv2.SOLVEPNP_SQPNP)
            rvec, tvec = cv2.solvePnPRefineLM(LAYOUT, uv, K, None, rvec, tvec)
            a_c = cv2.Rodrigues(rvec)[0] @ POINT + tvec.ravel()
            out[d, f] = np.linalg.norm(R_c_w.T @ (a_c - t_c_w) - x[f])
    return out


@pytest.mark.parametrize("distance, cone", [(0.8, 0.3), (1.4, 1.0)])
def test_predicted_error_matches_monte_carlo_pnp(distance, cone):
    t = np.linspace(0.0, 1.0, F)
    x = np.stack([0.3 * np.sin(3 * t), 0.2 * t, 0.1 * np.cos(2 * t)], 1)
    R_w_o = cv2.Rodrigues(np.array([0.2, -0.1, 0.3]))[0]
    P = _cameras(int(10 * distance), x, distance, cone)
    rms, mean = expected_pose_errors_for_cameras(P, x[None], R_w_o, LAYOUT, POINT, SIGMA)
    e = _pnp_errors(P, x, R_w_o, np.random.default_rng(0))
    mc_rms, mc_mean = np.sqrt(np.mean(e**2)), e.mean()
    # first order is exact enough at these errors (a few mm on a 0.37 m layout)
    assert abs(float(rms) / mc_rms - 1) < 0.15, (float(rms), mc_rms)
    assert abs(float(mean) / mc_mean - 1) < 0.15, (float(mean), mc_mean)
    # the mean is the Gaussian's expected norm, not Jensen's bound sqrt(E|e|^2) (~1.2x here)
    assert float(mean) < 0.95 * float(rms)
    # per frame: covariance trace against the Monte-Carlo mean square
    cov = pose_point_covariances(
        P, np.repeat(R_w_o[None], F, 0), x - POINT @ R_w_o.T, LAYOUT, POINT, SIGMA
    )
    ratio = np.trace(np.asarray(cov), axis1=1, axis2=2) / np.mean(e**2, axis=0)
    assert np.all(np.abs(ratio - 1) < 0.35), ratio  # 150 draws per frame: ~12 % std


def test_gaussian_mean_norm_closed_forms_and_gradient():
    # isotropic: sigma * 2 sqrt(2 / pi); one axis: sigma * sqrt(2 / pi) (chi distributions)
    np.testing.assert_allclose(gaussian_mean_norm(4.0 * np.eye(3)), 4 * np.sqrt(2 / np.pi), 1e-7)
    np.testing.assert_allclose(
        gaussian_mean_norm(np.diag([9.0, 0, 0])), 3 * np.sqrt(2 / np.pi), 1e-7
    )
    # planar isotropic: sigma * sqrt(pi / 2) (Rayleigh)
    np.testing.assert_allclose(gaussian_mean_norm(np.diag([1.0, 1.0, 0])), np.sqrt(np.pi / 2), 1e-7)
    A = np.random.default_rng(3).normal(size=(3, 3))
    g = jax.grad(gaussian_mean_norm)(jnp.asarray(A @ A.T))
    assert np.all(np.isfinite(np.asarray(g)))


def test_gaussian_mean_norm_matches_a_fine_quadrature_on_elongated_errors():
    # the 33-node double-exponential rule against the plain trapezoidal rule in log s with
    # step 0.01 over [-90, 90], on rotated covariances with eigenvalue ratios up to 1e7 (a
    # depth error along the rays is the design's elongated case)
    rng = np.random.default_rng(5)
    u = np.arange(-90.0, 90.0, 0.01)
    for _ in range(12):
        lam = np.exp(rng.uniform(-16.0, 0.0, 3)) * rng.uniform(1e-6, 1e-2)
        Rq, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        cov = Rq @ np.diag(lam) @ Rq.T
        det = np.prod(1.0 + 2.0 * np.exp(u)[:, None] * lam[None, :], axis=1)
        f = -np.expm1(-0.5 * np.log(det)) * np.exp(-0.5 * u)
        ref = 0.01 * (f.sum() - 0.5 * (f[0] + f[-1])) / (2 * np.sqrt(np.pi))
        np.testing.assert_allclose(float(gaussian_mean_norm(jnp.asarray(cov))), ref, rtol=1e-7)


def test_gradient_with_respect_to_cameras_is_finite_and_matches_differences():
    t = np.linspace(0.0, 1.0, F)
    x = np.stack([0.3 * np.sin(3 * t), 0.2 * t, 0.1 * np.cos(2 * t)], 1)
    P = jnp.asarray(_cameras(1, x, 0.9, 0.5))

    def f(P):
        return expected_pose_errors_for_cameras(P, x[None], np.eye(3), LAYOUT, POINT, SIGMA)[1]

    g = jax.grad(f)(P)
    assert np.all(np.isfinite(np.asarray(g)))
    d = np.random.default_rng(2).normal(size=P.shape) * 1e-3
    fd = (f(P + 1e-4 * d) - f(P - 1e-4 * d)) / 2e-4
    np.testing.assert_allclose(float(jnp.sum(g * d)), float(fd), rtol=1e-5)


def test_bad_layouts_are_refused():
    P = jnp.asarray(_cameras(1, np.zeros((F, 3)), 0.9, 0.5))
    with pytest.raises(ValueError, match=r"layout: expected \(M, 3\) reference points, M >= 4"):
        expected_pose_errors_for_cameras(P, np.zeros((1, F, 3)), np.eye(3), LAYOUT[:3])
    with pytest.raises(ValueError, match=r"samples: expected shape \(S, 12, 3\)"):
        expected_pose_errors_for_cameras(P, np.zeros((F, 3)), np.eye(3), LAYOUT)
    with pytest.raises(ValueError, match=r"method 'pose' needs 'layout'"):
        cell_from_dict(_cell(estimator={"method": "pose"}))
    with pytest.raises(ValueError, match=r"'estimator\.layout': expected >= 4 reference points"):
        cell_from_dict(_cell(estimator={"method": "pose", "layout": [[0, 0, 0], [1, 0, 0]] * 2}))
    with pytest.raises(ValueError, match=r"'estimator\.layout' belongs to method 'pose'"):
        cell_from_dict(_cell(estimator={"method": "dct", "layout": LAYOUT.tolist()}))
    with pytest.raises(ValueError, match=r"'estimator\.R_w_o': expected a rotation"):
        cell_from_dict(
            _cell(
                estimator={
                    "method": "pose",
                    "layout": LAYOUT.tolist(),
                    "R_w_o": np.ones((3, 3)).tolist(),
                }
            )
        )
    spec = cell_from_dict(_cell(estimator={"method": "pose", "layout": LAYOUT.tolist()}))
    assert spec.method == "pose" and np.allclose(spec.point, 0)
    assert cell_from_dict(spec.to_dict()).to_dict() == spec.to_dict()

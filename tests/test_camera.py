import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxtraj as jt
from jaxtraj.camera import distort

K = np.array([[650.0, 0.0, 322.0], [0.0, 640.0, 241.0], [0.0, 0.0, 1.0]])
DIST = np.array([-0.21, 0.08, 0.0012, -0.0008, -0.01])


def _pose(rng):
    rvec = rng.normal(size=3) * 0.4
    R = cv2.Rodrigues(rvec)[0]
    t = rng.normal(size=3) * 0.2 + np.array([0.0, 0.0, 1.2])
    return rvec, R, t


def test_projection_matrix_and_project_match_opencv(rng):
    rvec, R, t = _pose(rng)
    X = rng.normal(size=(30, 3)) * 0.2
    ref = cv2.projectPoints(X, rvec, t, K, None)[0][:, 0]
    np.testing.assert_allclose(jt.project(K, R, t, X), ref, atol=1e-9)
    P = jt.projection_matrix(K, R, t)
    h = np.hstack([X, np.ones((30, 1))]) @ np.asarray(P).T
    np.testing.assert_allclose(h[:, :2] / h[:, 2:], ref, atol=1e-9)
    ref_d = cv2.projectPoints(X, rvec, t, K, DIST)[0][:, 0]
    np.testing.assert_allclose(jt.project(K, R, t, X, DIST), ref_d, atol=1e-8)


def test_camera_centre(rng):
    _, R, t = _pose(rng)
    P = jt.projection_matrix(K, R, t)
    C = jt.camera_centre(P)
    np.testing.assert_allclose(C, -R.T @ t, atol=1e-12)
    np.testing.assert_allclose(P @ jnp.append(C, 1.0), 0.0, atol=1e-9)


def test_undistort_points_matches_opencv(rng):
    uv = rng.uniform([20, 20], [620, 460], size=(50, 2))
    ref = cv2.undistortPoints(uv[:, None, :], K, DIST, P=K)[:, 0]
    ours = jt.undistort_points(uv, K, DIST)
    # OpenCV's fixed-point iteration stops early; ours inverts distort() to round-off.
    np.testing.assert_allclose(ours, ref, atol=2e-3)
    xy = (np.asarray(ours) - K[:2, 2]) / np.diag(K)[:2]
    redist = np.asarray(distort(xy, DIST)) * np.diag(K)[:2] + K[:2, 2]
    np.testing.assert_allclose(redist, uv, atol=1e-8)


def test_look_at_points_optical_axis_at_target(rng):
    pos = rng.normal(size=3)
    target = pos + np.array([0.3, -0.2, 1.0])
    R, t = jt.look_at(pos, target, up_w=(0.0, -1.0, 0.0))
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    uv = jt.project(K, R, t, target)
    np.testing.assert_allclose(uv, K[:2, 2], atol=1e-9)
    np.testing.assert_allclose(R @ pos + t, 0.0, atol=1e-12)


def test_jit_vmap_grad(rng):
    _, R, t = _pose(rng)
    X = jnp.asarray(rng.normal(size=(5, 3)) * 0.2)
    f = lambda X: jt.project(K, R, t, X, DIST)  # noqa: E731
    np.testing.assert_allclose(jax.jit(f)(X), f(X), atol=1e-12)
    np.testing.assert_allclose(jax.vmap(f)(X), f(X), atol=1e-12)
    check_grads(jax.jit(f), (X,), order=1, modes=["fwd", "rev"])
    uv = f(X)
    g = lambda uv: jt.undistort_points(uv, K, DIST)  # noqa: E731
    # jit-compiled: run eagerly, the undistortion's scan is compiled again at every call
    check_grads(jax.jit(g), (uv,), order=1, modes=["fwd", "rev"], atol=1e-5, rtol=1e-5)

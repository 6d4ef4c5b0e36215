"""Recursive sliding-window DCT: equals the batch solve, O(k^2) information updates,
velocity/prediction, batching and bad inputs."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraj as jt
from jaxtraj.estimators import (
    stream_estimate,
    stream_init,
    stream_rebase,
    stream_run,
    stream_update,
)
from tests.test_estimators_scenes import robot_scene

F, K = 90, 8


@pytest.fixture
def scene(rng):
    return robot_scene(rng, F=F, mode="random", noise=0.4)


def _batch(s, sl, basis):
    return jt.reconstruct_points(s["P"][sl], s["uv"][sl][None], basis(s["times"][sl])).coeffs[0]


def test_growing_window_equals_batch(scene):
    s = scene
    basis = jt.DCTBasis.from_times(s["times"], K)
    _, est = stream_run(stream_init(basis, F), s["P"], s["uv"], s["times"])
    ref = _batch(s, slice(None), basis)
    np.testing.assert_allclose(np.asarray(est.coeffs[-1]), np.asarray(ref), atol=1e-9, rtol=1e-9)
    assert bool(est.ok[-1]) and not bool(est.ok[3])


def test_sliding_window_equals_batch(scene):
    s = scene
    W = 40
    basis = jt.DCTBasis.from_times(s["times"], K)
    state, _ = stream_run(stream_init(basis, W), s["P"], s["uv"], s["times"])
    # the information after downdates equals the window's normal equations exactly
    N, b = jt.normal_equations(s["P"][-W:], s["uv"][-W:], basis(s["times"][-W:]))
    np.testing.assert_allclose(
        np.asarray(state.N), np.asarray(N), rtol=1e-9, atol=1e-9 * np.abs(N).max()
    )
    np.testing.assert_allclose(
        np.asarray(state.b), np.asarray(b), rtol=1e-9, atol=1e-9 * np.abs(b).max()
    )
    # rebased onto the window's own span, the estimate equals the batch solution
    wb = jt.DCTBasis.from_times(s["times"][-W:], K)
    est = stream_estimate(stream_rebase(state, wb), horizon=0.03)
    ref = _batch(s, slice(F - W, F), wb)
    np.testing.assert_allclose(np.asarray(est.coeffs), np.asarray(ref), atol=1e-9, rtol=1e-9)
    # position, velocity and prediction from the same coefficients
    t = s["times"][-1]
    np.testing.assert_allclose(
        np.asarray(est.position), np.asarray(wb(jnp.array([t])) @ ref)[0], atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(est.velocity), np.asarray(wb(jnp.array([t]), 1) @ ref)[0], atol=1e-10
    )
    np.testing.assert_allclose(
        np.asarray(est.predicted), np.asarray(wb(jnp.array([t + 0.03])) @ ref)[0], atol=1e-12
    )
    assert np.linalg.norm(np.asarray(est.position) - s["X"][-1]) < 0.01


def test_missing_frames_jit_and_vmap(scene, rng):
    s = scene
    basis = jt.DCTBasis.from_times(s["times"], K)
    w = np.ones(F)
    w[10:20] = 0.0
    uv = s["uv"].copy()
    uv[10:20] = np.nan
    _, est = stream_run(stream_init(basis, F), s["P"], uv, s["times"], w)
    ref = jt.reconstruct(s["P"], uv, basis(s["times"]), w).coeffs
    np.testing.assert_allclose(np.asarray(est.coeffs[-1]), np.asarray(ref), atol=1e-9)
    # one eager update equals the jitted one
    st0 = stream_init(basis, 5)
    a = stream_update(st0, s["P"][0], s["uv"][0], s["times"][0])
    b = jax.jit(stream_update)(st0, s["P"][0], s["uv"][0], s["times"][0])
    np.testing.assert_allclose(np.asarray(a.N), np.asarray(b.N), rtol=1e-13)
    uvs = np.stack([s["uv"], s["uv"] + rng.normal(size=(F, 2))])
    # A 30-frame window on a basis spanning 90 frames leaves directions of the coefficients
    # undetermined (scaled condition number ~1e18). The estimate's ridge keeps it a
    # continuous function of the data: the batched program (different rounding) agrees
    # with the single run (without the ridge they differed by 1e-5 m) and is accurate.
    run = jax.jit(
        jax.vmap(
            lambda u: stream_run(stream_init(basis, 30), s["P"], u, s["times"])[1].position[-1]
        )
    )
    batch = np.asarray(run(uvs))
    one = stream_run(stream_init(basis, 30), s["P"], uvs[1], s["times"])[1].position[-1]
    np.testing.assert_allclose(batch[1], np.asarray(one), atol=1e-10)
    # last-frame error ~1-6 mm over seeds (the 90-frame window's: 3-13 mm); a solution
    # moved along the undetermined directions would be off by centimetres or more
    assert np.linalg.norm(batch[0] - s["X"][-1]) < 0.01


def test_gradient_through_stream(scene):
    s = scene
    basis = jt.DCTBasis.from_times(s["times"][:30], 5)

    def f(uv):
        _, est = stream_run(stream_init(basis, 30), s["P"][:30], uv, s["times"][:30])
        return jnp.sum(est.position[-1])

    uv = jnp.asarray(s["uv"][:30])
    g = np.asarray(jax.grad(f)(uv))
    d = np.random.default_rng(0).normal(size=uv.shape)
    fd = (f(uv + 1e-4 * d) - f(uv - 1e-4 * d)) / 2e-4
    assert float(np.sum(g * d)) == pytest.approx(float(fd), rel=1e-5)


def test_bad_inputs(scene):
    s = scene
    basis = jt.DCTBasis.from_times(s["times"], K)
    with pytest.raises(ValueError, match="basis"):
        stream_init(np.zeros((F, K)), 10)
    with pytest.raises(ValueError, match="window"):
        stream_init(basis, 0)
    st = stream_init(basis, 10)
    with pytest.raises(ValueError, match="P"):
        stream_update(st, s["P"][0, :2], s["uv"][0], 0.0)
    with pytest.raises(ValueError, match="uv"):
        stream_update(st, s["P"][0], s["uv"][:2], 0.0)
    with pytest.raises(ValueError, match="uv"):
        stream_run(st, s["P"], s["uv"][:-1], s["times"])

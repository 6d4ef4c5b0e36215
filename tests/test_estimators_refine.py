"""Maximum-likelihood refinement: never worse than the start, reaches the noise floor,
robust losses reject outliers, batching, gradients and bad inputs."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraj as jt
from jaxtraj.estimators import refine_dct, refine_points
from jaxtraj.estimators.refine import _errors
from tests.test_estimators_scenes import project_np, rmse, robot_scene

F, K = 60, 6


def _in_span_scene(rng, noise=0.5):
    s = robot_scene(rng, F=F, mode="random", noise=noise)
    b = np.asarray(jt.dct_basis(s["times"], K))
    true = np.linalg.lstsq(b, s["X"], rcond=None)[0]
    X = b @ true
    uv = project_np(s["P"], X) + noise * rng.normal(size=(F, 2))
    return s, b, true, X, uv


REFINE = jax.jit(lambda P, uv, b, c: refine_dct(P, uv, b, c, pixel_sigma=0.5))


def test_never_worse_and_reaches_noise_floor():
    rng = np.random.default_rng(5)
    for _ in range(3):
        s, b, true, _X, uv = _in_span_scene(rng)
        lin = jt.reconstruct(s["P"], uv, b)
        out = REFINE(s["P"], uv, b, lin.coeffs)
        assert float(out.cost) <= float(out.cost_initial)
        assert float(out.rms_px) <= float(out.rms_px_initial) + 1e-12
        # the ML estimate's reprojection error is no larger than that of the truth
        e_true = np.asarray(
            _errors(jnp.asarray(s["P"]), jnp.asarray(uv), jnp.asarray(b), jnp.asarray(true))
        )
        assert float(out.rms_px) <= np.sqrt(np.mean(np.sum(e_true**2, 1))) + 1e-9
        floor = 0.5 * np.sqrt(2 * (2 * F - 3 * K) / (2 * F))  # expected RMS at the optimum
        assert float(out.rms_px) < 1.2 * floor
        assert bool(out.converged)
    # a perturbed start is pulled back: refinement from a bad start still converges
    bad = REFINE(s["P"], uv, b, lin.coeffs + 0.02)
    assert float(bad.rms_px) == pytest.approx(float(out.rms_px), rel=1e-6)


def test_robust_losses_reject_outliers(rng):
    s, b, _, X, uv = _in_span_scene(rng)
    uv = uv.copy()
    uv[::8] += 30.0
    lin = jt.reconstruct(s["P"], uv, b)
    errs = {}
    for loss in ("l2", "huber", "cauchy"):
        out = refine_dct(s["P"], uv, b, lin.coeffs, pixel_sigma=0.5, loss=loss, loss_scale=1.5)
        errs[loss] = rmse(out.points, X)
    assert errs["huber"] < 0.3 * rmse(lin.points, X)
    assert errs["cauchy"] < 0.3 * rmse(lin.points, X)


def test_vmap_jit_grad_and_solvers(rng):
    s, b, _, _X, uv = _in_span_scene(rng)
    uvs = np.stack([uv, uv + 0.3 * rng.normal(size=uv.shape)])
    w = np.ones((2, F))
    w[0, 3:6] = 0.0
    lin = jt.reconstruct_points(s["P"], uvs, b, w)
    batch = refine_points(s["P"], uvs, b, lin.coeffs, w, pixel_sigma=0.5)
    one = refine_dct(s["P"], uvs[0], b, lin.coeffs[0], w[0], pixel_sigma=0.5)
    np.testing.assert_allclose(np.asarray(batch.coeffs[0]), np.asarray(one.coeffs), atol=1e-9)
    gn = refine_dct(s["P"], uvs[0], b, lin.coeffs[0], w[0], pixel_sigma=0.5, solver="gn")
    np.testing.assert_allclose(np.asarray(gn.coeffs), np.asarray(one.coeffs), atol=1e-7)

    def f(u):
        return jnp.sum(REFINE(s["P"], u, b, lin.coeffs[1]).points[10])

    g = np.asarray(jax.grad(f)(jnp.asarray(uvs[1])))
    d = rng.normal(size=(F, 2))
    # a step of 1e-3 px: the solver stops within its tolerance, which a smaller step would
    # magnify into the difference quotient (3e-4 relative at 1e-4 px once; 1e-10 at 1e-3)
    fd = (f(uvs[1] + 1e-3 * d) - f(uvs[1] - 1e-3 * d)) / 2e-3
    assert float(np.sum(g * d)) == pytest.approx(float(fd), rel=1e-4)


def test_bad_inputs(rng):
    s, b, true, _, uv = _in_span_scene(rng)
    with pytest.raises(ValueError, match="coeffs"):
        refine_dct(s["P"], uv, b, true[:-1])
    with pytest.raises(ValueError, match="solver"):
        refine_dct(s["P"], uv, b, true, solver="bfgs")
    with pytest.raises(ValueError, match="loss"):
        refine_dct(s["P"], uv, b, true, loss="l1")
    with pytest.raises(ValueError, match="max_steps"):
        refine_dct(s["P"], uv, b, true, max_steps=0)
    with pytest.raises(ValueError, match="uv"):
        refine_points(s["P"], uv, b, true[None])


def test_flagged_starts_are_kept(rng):
    s, b, _, _X, uv = _in_span_scene(rng)
    uvs = np.stack([uv, uv + 0.3 * rng.normal(size=uv.shape)])
    lin = jt.reconstruct_points(s["P"], uvs, b)
    start = np.asarray(lin.coeffs) + 0.01  # a start the optimiser would move
    status = np.array([jt.Status.OK, jt.Status.DEGENERATE])
    out = refine_points(s["P"], uvs, b, start, status=status, pixel_sigma=0.5)
    free = refine_points(s["P"], uvs, b, start, pixel_sigma=0.5)
    np.testing.assert_array_equal(np.asarray(out.coeffs[1]), start[1])
    assert np.asarray(out.kept_start).tolist() == [False, True]
    assert float(out.cost[1]) == float(out.cost_initial[1])
    np.testing.assert_array_equal(np.asarray(out.coeffs[0]), np.asarray(free.coeffs[0]))
    assert float(free.rms_px[1]) < float(free.rms_px_initial[1])  # it would have moved
    with pytest.raises(ValueError, match="status"):
        refine_points(s["P"], uvs, b, start, status=status[:1])

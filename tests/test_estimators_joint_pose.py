"""Joint 6-DoF fit of one rigid motion to all points' rays versus per-frame Kabsch."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

import jaxtraj as jt
from jaxtraj.estimators import fit_rigid_trajectory, kabsch_per_frame
from tests.test_estimators_scenes import project_np, robot_scene

F, K = 60, 6
MODEL = np.array([[0.06, 0, 0], [-0.05, 0.04, 0], [0, -0.05, 0.02], [0.02, 0.03, -0.04]])
FIT = jax.jit(lambda P, uv, b: fit_rigid_trajectory(P, uv, MODEL, b))


def _scene(rng, noise):
    s = robot_scene(rng, F=F, mode="random", noise=0.0)
    b = np.asarray(jt.dct_basis(s["times"], K))
    t = b @ np.linalg.lstsq(b, s["X"], rcond=None)[0]
    rv = np.stack(
        [0.3 * np.sin(2 * s["times"]), 0.2 * np.cos(3 * s["times"]), 0.1 + 0 * s["times"]], 1
    )
    rv = b @ np.linalg.lstsq(b, rv, rcond=None)[0]
    rv = rv - rv[F // 2]  # in the span and 0 at the reference (middle) frame
    R0 = np.asarray(jaxlie.SO3.exp(jnp.array([0.4, -0.3, 1.0])).as_matrix())
    R = np.asarray(jax.vmap(lambda r: jaxlie.SO3.exp(r).as_matrix())(jnp.asarray(rv))) @ R0
    Xm = np.einsum("fij,mj->mfi", R, MODEL) + t
    uv = np.array([project_np(s["P"], x) for x in Xm]) + noise * rng.normal(size=(4, F, 2))
    return s, b, R, t, uv


def _rot_deg(Ra, Rb):
    c = (np.trace(np.einsum("fji,fjk->fik", Ra, Rb), axis1=1, axis2=2) - 1) / 2
    return np.degrees(np.mean(np.arccos(np.clip(c, -1, 1))))


def test_noise_free_is_exact(rng):
    s, b, R, t, uv = _scene(rng, 0.0)
    res = FIT(s["P"], uv, b)
    # exact up to the tiny non-commutativity of exp(phi beta) R_ref with the start's R_ref
    np.testing.assert_allclose(np.asarray(res.t), t, atol=2e-6)
    np.testing.assert_allclose(np.asarray(res.R), R, atol=2e-6)
    assert float(res.rms_px) < 1e-3 * float(res.rms_px_initial) + 1e-6
    # the points of a rotating body are not exactly in the span: Kabsch is only close
    _, tk = kabsch_per_frame(s["P"], uv, MODEL, b)
    assert 1e-8 < np.abs(np.asarray(tk) - t).max() < 1e-4


def test_joint_fit_beats_per_frame_kabsch():
    rng = np.random.default_rng(4)
    gains_t, gains_r = [], []
    for _ in range(4):
        s, b, R, t, uv = _scene(rng, 0.5)
        res = FIT(s["P"], uv, b)
        Rk, tk = kabsch_per_frame(s["P"], uv, MODEL, b)
        et = np.sqrt(np.mean(np.sum((np.asarray(res.t) - t) ** 2, 1)))
        ek = np.sqrt(np.mean(np.sum((np.asarray(tk) - t) ** 2, 1)))
        gains_t.append(ek / et)
        gains_r.append(_rot_deg(np.asarray(Rk), R) / _rot_deg(np.asarray(res.R), R))
        assert float(res.rms_px) <= float(res.rms_px_initial)
    assert np.mean(gains_t) > 1.05 and np.mean(gains_r) > 1.05, (gains_t, gains_r)


def test_vmap_and_missing_detections(rng):
    s, b, _R, t, uv = _scene(rng, 0.3)
    w = np.ones((4, F))
    w[1, 10:20] = 0.0
    uv2 = uv.copy()
    uv2[1, 10:20] = np.nan
    res = fit_rigid_trajectory(s["P"], uv2, MODEL, b, w)
    assert np.all(np.isfinite(np.asarray(res.R)))
    assert np.sqrt(np.mean(np.sum((np.asarray(res.t) - t) ** 2, 1))) < 2e-3
    batch = jax.vmap(lambda u: FIT(s["P"], u, b).t)(np.stack([uv, uv + 0.1]))
    np.testing.assert_allclose(np.asarray(batch[0]), np.asarray(FIT(s["P"], uv, b).t), atol=1e-9)


def test_bad_inputs(rng):
    s, b, _, _, uv = _scene(rng, 0.0)
    with pytest.raises(ValueError, match="model_points"):
        fit_rigid_trajectory(s["P"], uv[:2], MODEL[:2], b)
    with pytest.raises(ValueError, match="uv"):
        fit_rigid_trajectory(s["P"], uv[:3], MODEL, b)
    with pytest.raises(ValueError, match="basis"):
        fit_rigid_trajectory(s["P"], uv, MODEL, b[:-1])
    with pytest.raises(ValueError, match="loss"):
        fit_rigid_trajectory(s["P"], uv, MODEL, b, loss="l1")

"""float32 inputs with x64 enabled (as in these tests): the estimators run, return float32,
and agree with the truth (estimate_points, the filter) or with their float64 results (the
Levenberg-Marquardt fits). A float64 constant once leaked into the smoothers' scans, and
optimistix's damping is float64: every one of these calls failed."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraj as jt
from jaxtraj import estimators as es
from tests.test_estimate_points import TIMES, cameras, pixels, prior_tracks

N = 3


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(3)
    X = prior_tracks(rng, 2, N, 2.0)
    _, P = cameras(rng, "random", X, 2.0)
    return X, P, pixels(rng, P, X, 0.3)


def _floats(tree):
    return {
        str(a.dtype)
        for a in jax.tree_util.tree_leaves(tree)
        if hasattr(a, "dtype") and jnp.issubdtype(a.dtype, jnp.floating)
    }


def _both(fn, *arrays):
    """fn on float64 and on float32 copies of ``arrays``: (result64, result32)."""
    assert jax.config.jax_enable_x64  # the case this file is about
    r64 = fn(*(jnp.asarray(a, jnp.float64) for a in arrays))
    r32 = fn(*(jnp.asarray(a, jnp.float32) for a in arrays))
    assert _floats(r32) == {"float32"}, _floats(r32)
    return r64, r32


def test_estimate_points_and_the_filter(scene):
    X, P, uv = scene
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    r = jt.estimate_points(f32(P), f32(uv), f32(TIMES), pixel_sigma=0.3)
    assert _floats(r) == {"float32"}, _floats(r)
    # float32 may flag a track that float64 reports OK (measured here: 1 of 3, the order-2
    # fit judged singular in float32; float64: all 3 OK, 3.6-4.4 mm); its OK tracks are
    # as accurate as float64's
    ok = np.asarray(r.status) == jt.Status.OK
    err = np.linalg.norm(np.asarray(r.points) - X, axis=-1).mean(axis=1)
    assert ok.sum() >= 2 and np.all(err[ok] < 0.006), (r.status, err)
    start = np.stack([X[:, 0], np.zeros_like(X[:, 0])], axis=1)  # (N, 2, 3)
    f = es.filter_points(
        f32(P),
        f32(uv),
        f32(TIMES),
        start_mean=f32(start),
        start_cov=0.01 * jnp.eye(6, dtype=jnp.float32),
        process_psd=2.0,
        pixel_sigma=0.3,
    )
    assert _floats(f) == {"float32"}, _floats(f)
    err = np.linalg.norm(np.asarray(f.points) - X, axis=-1).mean(axis=1)
    assert np.all(err < 0.01), err
    mean, cov = es.predict(jax.tree.map(lambda a: a[0], f), 0.1)  # 0.1 s ahead
    assert mean.dtype == cov.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(cov)))


def test_refinement_and_the_rigid_fit(scene):
    X, P, uv = scene
    basis = jt.dct_basis(TIMES, 6)
    start = jt.reconstruct_points(P, uv, basis).coeffs
    r64, r32 = _both(es.refine_points, P, uv, basis, start)
    assert np.abs(np.asarray(r32.points) - np.asarray(r64.points)).max() < 1e-3
    model = X[:, 0] - X[:, 0].mean(axis=0)  # the points' layout at the first frame
    g64, g32 = _both(lambda P, u, m, b: es.fit_rigid_trajectory(P, u, m, b), P, uv, model, basis)
    assert np.abs(np.asarray(g32.t) - np.asarray(g64.t)).max() < 1e-3

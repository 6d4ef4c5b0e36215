"""jaxtraj.estimate_points: model choice, depth determinability, honest covariance."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraj as jt

K = np.array([[800.0, 0.0, 319.5], [0.0, 800.0, 239.5], [0.0, 0.0, 1.0]])
F, RATE = 60, 30.0
TIMES = np.arange(F) / RATE


def prior_tracks(rng, order, n, q):
    """n trajectories (n, F, 3) drawn from the integrated-white-noise prior of ``order``
    (noise density q), centred 1 m above the floor."""
    dt = 1.0 / RATE
    x = rng.normal(size=(n, F, 3)) * np.sqrt(q * dt)
    x = np.cumsum(x, axis=1)
    for _ in range(order - 1):
        x = np.cumsum(x * dt, axis=1)
    return x - x.mean(axis=1, keepdims=True) + np.array([0.0, 0.0, 1.0])


def cameras(rng, mode, X, dist):
    """Camera centres (F, 3) and projection matrices (F, 3, 4) looking at the centroid of
    the points of each frame: random positions, an orbit of ``deg`` per frame, or a
    camera that follows the points at a fixed offset."""
    centre = X.mean(axis=0)
    m = centre.mean(axis=0)
    if mode == "random":
        d = rng.normal(size=(F, 3))
        d[:, 2] = np.abs(d[:, 2]) * 0.5 + 0.2
        C = m + dist * d / np.linalg.norm(d, axis=1, keepdims=True)
    elif mode.startswith("orbit"):
        a = rng.uniform(0, 2 * np.pi) + np.deg2rad(float(mode[5:])) * np.arange(F)
        C = m + dist * np.stack([np.cos(a) * 0.94, np.sin(a) * 0.94, np.full(F, 0.34)], 1)
    else:  # follow
        d = np.array([0.6, -0.5, 0.62])
        C = centre + dist * d / np.linalg.norm(d)
    P = []
    for c, x in zip(C, centre, strict=True):
        R, t = jt.look_at(c, x, up_w=(0.0, 0.0, 1.0))
        P.append(K @ np.hstack([np.asarray(R), np.asarray(t)[:, None]]))
    return C, np.array(P)


def pixels(rng, P, X, noise):
    h = np.einsum("fij,nfj->nfi", P[:, :, :3], X) + P[None, :, :, 3]
    return h[..., :2] / h[..., 2:] + noise * rng.normal(size=(*X.shape[:2], 2))


N = 8  # tracks per call: one shape, so the suite compiles the estimator once for it


def scene(seed, order, mode, n=N, q=None, dist=2.0, noise=0.5):
    rng = np.random.default_rng(seed)
    q = {1: 0.05, 2: 2.0}[order] if q is None else q
    X = prior_tracks(rng, order, n, q)
    C, P = cameras(rng, mode, X, dist)
    return X, C, P, pixels(rng, P, X, noise)


def mean_error(est, X):
    return np.linalg.norm(np.asarray(est.points) - X, axis=-1).mean(axis=1)


@pytest.mark.parametrize("order", [1, 2])
def test_picks_the_generating_prior(order):
    picks = []
    for seed in range(3):
        _, _, P, uv = scene(seed, order, "random")
        est = jt.estimate_points(P, uv, TIMES, pixel_sigma=0.5)
        picks.append(np.asarray(est.order))
        assert np.all(np.asarray(est.status) == jt.Status.OK)
    picks = np.concatenate(picks)
    # measured: 24/24 tracks for either order
    assert np.mean(picks == order) >= 0.9, picks


def dct_tracks(rng, k, n):
    """n trajectories (n, F, 3) inside the span of the k-vector DCT basis: the constant
    1 m above the floor, the other coefficients decaying with frequency."""
    B = np.asarray(jt.dct_basis(TIMES, k))
    scale = 0.3 * np.sqrt(F) / np.arange(1, k)  # about 0.3 m per coefficient and frame
    beta = rng.normal(size=(n, k, 3))
    beta[:, 1:] *= scale[None, :, None]
    beta[:, 0] = np.sqrt(F) * np.array([0.0, 0.0, 1.0])
    return np.einsum("fk,nka->nfa", B, beta)


def test_picks_the_dct_span_on_data_inside_it():
    k = 6  # one of the candidate sizes
    assert k in jt.estimators.estimate.DCT_KS
    rng = np.random.default_rng(5)
    X = dct_tracks(rng, k, N)
    _, P = cameras(rng, "random", X, 2.0)
    uv = pixels(rng, P, X, 0.5)
    est = jt.estimate_points(P, uv, TIMES, pixel_sigma=0.5)
    smoother = jt.estimators.smooth_points(P, uv, TIMES, pixel_sigma=0.5)  # order 2
    # measured: all 8 tracks pick the 6-vector DCT, error 0.4x the order-2 smoother's
    assert np.mean(np.asarray(est.dct_k) == k) >= 0.9, est.dct_k
    assert np.all(np.asarray(est.order)[np.asarray(est.dct_k) > 0] == 0)
    assert np.all(np.asarray(est.status) == jt.Status.OK)
    assert mean_error(est, X).mean() < 0.8 * mean_error(smoother, X).mean()
    # the DCT's posterior alone is the error's; the reported covariance keeps the
    # smoothers' along-ray bound, so it is conservative (measured: MSE / trace 0.12)
    e2 = np.mean(np.sum((np.asarray(est.points) - X) ** 2, axis=-1))
    post = np.mean(np.trace(np.asarray(est.posterior_cov), axis1=-2, axis2=-1))
    assert 0.6 < e2 / post < 1.5
    assert e2 < np.mean(np.trace(np.asarray(est.cov), axis1=-2, axis2=-1))


def test_follower_and_slow_orbit_flagged_random_not():
    # the same motion (an order-2 draw, a walking-pace body) seen three ways, 3 m away
    for mode, flagged in (("follow", True), ("orbit1", True), ("random", False)):
        X, _, P, uv = scene(7, 2, mode, q=0.5, dist=3.0)
        est = jt.estimate_points(P, uv, TIMES, pixel_sigma=0.5)
        status = np.asarray(est.status)
        err = mean_error(est, X)
        kappa = np.asarray(est.depth_uncertainty)
        if flagged:
            assert np.all(status == jt.Status.DEGENERATE), (mode, status, kappa)
            # the reported along-ray uncertainty is a sizeable part of the distance
            assert np.all(kappa > 0.08)
        else:
            assert np.all(status == jt.Status.OK), (mode, kappa)
            assert np.all(err < 0.02), err
            assert np.all(kappa < 0.03), kappa


def test_no_ok_status_for_an_estimate_metres_off():
    # a camera that follows the point: every smoother collapses the estimate onto it
    X, _, P, uv = scene(3, 2, "follow", q=0.5, dist=3.0)
    smoothed = jt.estimators.smooth_points(P, uv, TIMES, pixel_sigma=0.5)
    assert np.all(mean_error(smoothed, X) > 0.3)  # the failure this test is about
    est = jt.estimate_points(P, uv, TIMES, pixel_sigma=0.5)
    err = mean_error(est, X)
    assert np.all((np.asarray(est.status) != jt.Status.OK) | (err < 0.1))


@pytest.mark.parametrize("order", [1, 2])
def test_covariance_matches_monte_carlo_error(order):
    # truths drawn from the prior, random cameras: the reported covariance is the error's
    e2, tr = [], []
    for seed in range(11, 15):
        X, _, P, uv = scene(seed, order, "random")
        est = jt.estimate_points(P, uv, TIMES, pixel_sigma=0.5)
        e2.append(np.sum((np.asarray(est.points) - X) ** 2, axis=-1))
        tr.append(np.trace(np.asarray(est.cov), axis1=-2, axis2=-1))
    # measured 0.96 (order 1), 1.09 (order 2) on these 32 tracks
    assert np.mean(e2) / np.mean(tr) == pytest.approx(1.0, abs=0.15)


def test_vmap_equals_loop():
    _, _, P, uv = scene(5, 2, "orbit45")
    batch = jt.estimate_points(P, uv, TIMES, pixel_sigma=0.5)
    for i in (0, 5):
        # one track at a time (tiled to the batch's shape, so nothing is compiled again)
        one = jt.estimate_points(P, np.repeat(uv[i : i + 1], N, 0), TIMES, pixel_sigma=0.5)
        np.testing.assert_allclose(np.asarray(one.points[3]), np.asarray(batch.points[i]))
        np.testing.assert_allclose(np.asarray(one.cov[3]), np.asarray(batch.cov[i]))
        assert int(one.order[3]) == int(batch.order[i])
        assert int(one.status[3]) == int(batch.status[i])


def small_scene(f=24):
    rng = np.random.default_rng(2)
    X = prior_tracks(rng, 2, 1, 2.0)
    _, P = cameras(rng, "random", X, 2.0)
    return rng, P[:f], pixels(rng, P, X, 0.5)[:, :f], TIMES[:f]


def test_jit_equals_eager():
    _, P, uv, times = small_scene()
    kw = dict(pixel_sigma=0.5, orders=(2,), dct_ks=(4,), iterations=1)
    eager = jt.estimate_points(P, uv, times, **kw)
    jitted = jax.jit(lambda u: jt.estimate_points(P, u, times, **kw))(uv)
    # the same program inside another jit: XLA may fuse differently (measured 2e-8 m)
    np.testing.assert_allclose(np.asarray(jitted.points), np.asarray(eager.points), atol=1e-7)
    np.testing.assert_allclose(np.asarray(jitted.std), np.asarray(eager.std), rtol=1e-6)
    assert int(jitted.status[0]) == int(eager.status[0]) == jt.Status.OK


def test_gradients_with_respect_to_pixels_and_cameras_are_finite_and_correct():
    rng, P, uv, times = small_scene()

    def f_(uv, P):
        est = jt.estimate_points(
            P, uv, times, pixel_sigma=0.5, orders=(2,), dct_ks=(4,), iterations=1
        )
        return jnp.sum(est.points[0, 5] + est.points[0, 17])

    value_and_grad = jax.jit(jax.value_and_grad(f_, argnums=(0, 1)))
    uv, P = jnp.asarray(uv), jnp.asarray(P)
    _, (g_uv, g_P) = value_and_grad(uv, P)
    assert np.all(np.isfinite(g_uv)) and np.all(np.isfinite(g_P))
    d_uv = rng.normal(size=uv.shape)
    # a camera perturbation of 1e-8 of the entries' size: the fit is linear there (at 1e-6
    # the difference quotient is off by 30 %, curvature, not a wrong gradient)
    d_P = rng.normal(size=P.shape) * 1e-5 * np.abs(np.asarray(P)).mean()
    eps = 1e-3
    fd = (
        value_and_grad(uv + eps * d_uv, P + eps * d_P)[0]
        - value_and_grad(uv - eps * d_uv, P - eps * d_P)[0]
    ) / (2 * eps)
    directional = float(np.sum(g_uv * d_uv) + np.sum(g_P * d_P))
    # measured: 1e-7 relative for pixels alone, 2e-5 for cameras alone
    assert directional == pytest.approx(float(fd), rel=1e-4)


def test_bad_input():
    _, _, P, uv = scene(1, 2, "random")
    with pytest.raises(ValueError, match="uv"):
        jt.estimate_points(P, uv[0], TIMES)
    with pytest.raises(ValueError, match="uv"):
        jt.estimate_points(P, uv[:, :-1], TIMES)
    with pytest.raises(ValueError, match="times"):
        jt.estimate_points(P, uv, TIMES[::-1])
    with pytest.raises(ValueError, match="weights"):
        jt.estimate_points(P, uv, TIMES, np.ones((N, F - 1)))
    bad = uv.copy()
    bad[1, 4] = np.nan
    with pytest.raises(ValueError, match="uv"):
        jt.estimate_points(P, bad, TIMES)
    w = np.ones((N, F))
    w[1, 4] = 0.0  # a NaN pixel with weight 0 is a missing detection, not an error
    assert jt.estimate_points(P, bad, TIMES, w).points.shape == (N, F, 3)
    few = np.zeros((N, F))
    few[:, :2] = 1.0
    with pytest.raises(ValueError, match="observed frames"):
        jt.estimate_points(P, uv, TIMES, few)
    with pytest.raises(ValueError, match="orders"):
        jt.estimate_points(P, uv, TIMES, orders=(4,))
    for ks in ((0,), (4, 4), (F,), (2.5,)):
        with pytest.raises(ValueError, match="dct_ks"):
            jt.estimate_points(P, uv, TIMES, dct_ks=ks)
    with pytest.raises(ValueError, match="max_depth_uncertainty"):
        jt.estimate_points(P, uv, TIMES, max_depth_uncertainty=0.0)
    with pytest.raises(ValueError, match="pixel_sigma"):
        jt.estimate_points(P, uv, TIMES, pixel_sigma=-1.0)


def test_regularised_dct_flags_a_follower_it_cannot_measure():
    from jaxtraj.estimators import reconstruct_regularised_points

    X, _, P, uv = scene(3, 2, "follow", q=0.5, dist=3.0)
    res, _, _ = reconstruct_regularised_points(P, uv, TIMES, k=30)
    err = mean_error(res, X)
    assert np.any(err > 0.3)  # the failure this test is about
    assert np.all((np.asarray(res.status) != jt.Status.OK) | (err < 0.1)), err

"""The design objective for the per-point estimator: expected error of the smoother."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtraj import estimate_points, projection_matrix
from jaxtraj.design import (
    expected_smoother_errors_for_cameras,
    plausible_trajectories,
    smoother_error_terms,
)
from jaxtraj.design import smoother_error as se
from jaxtraj.design.objectives import project_points
from jaxtraj.estimators import smooth_points
from jaxtraj.estimators.smoothness import _argmin_log
from jaxtraj.sim import following_camera, orbit_camera, random_discontinuous_camera

F, T, SIGMA, DRAWS = 30, 6.0, 0.5, 200
K = jnp.array([[700.0, 0.0, 320.0], [0.0, 700.0, 240.0], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def scene():
    times = jnp.linspace(0.0, T, F)
    pred = jnp.stack(
        [0.2 * jnp.sin(0.5 * times), 0.15 * jnp.cos(0.3 * times), 0.01 * times], axis=1
    )
    x = plausible_trajectories(jax.random.PRNGKey(1), pred, times, 1, extent=0.05)[1]

    def cams(path):
        return jax.vmap(lambda R, t: projection_matrix(K, R, t))(path.R_c_w, path.t_c_w)

    paths = {
        "orbit": cams(orbit_camera(x, radius=0.8, angular_speed=1.5, height=0.5, times=times)),
        "slow orbit": cams(orbit_camera(x, radius=0.8, angular_speed=0.2, height=0.5, times=times)),
        "random": cams(random_discontinuous_camera(jax.random.PRNGKey(4), x)),
        "follower": cams(following_camera(x, jnp.array([0.0, -0.3, 0.8]))),
    }
    return times, x, paths


def _monte_carlo(P, x, times, fit):
    noise = SIGMA * jax.random.normal(jax.random.PRNGKey(7), (DRAWS, F, 2))
    points = np.asarray(fit(P, project_points(P, x)[None] + noise, times))
    err2 = np.sum((points - np.asarray(x)[None]) ** 2, axis=-1)
    return float(np.sqrt(np.mean(err2)))


@pytest.mark.parametrize(
    "camera, dominant, least_share", [("orbit", "bias", 0.5), ("random", "noise", 0.2)]
)
def test_predicted_error_matches_monte_carlo_of_the_estimator(scene, camera, dominant, least_share):
    """Within 15 % of the RMS error of ``estimate_points`` (order-2 prior, its own noise
    density per draw) and of the smoother at the predicted density, over 200 draws; the
    orbit's error is mostly the prior's bias, the random camera's has a large noise part."""
    times, x, paths = scene
    P = paths[camera]
    bias2, var, q = smoother_error_terms(P, x, times, SIGMA, order=2)
    predicted = float(jnp.sqrt(jnp.mean(bias2 + var)))
    fixed = _monte_carlo(
        P,
        x,
        times,
        lambda P, uv, t: (
            smooth_points(P, uv, t, order=2, pixel_sigma=SIGMA, process_psd=float(q)).points
        ),
    )
    chosen = _monte_carlo(
        P,
        x,
        times,
        lambda P, uv, t: (
            estimate_points(P, uv, t, pixel_sigma=SIGMA, orders=(2,), dct_ks=()).points
        ),
    )
    assert abs(predicted / fixed - 1) < 0.15, (predicted, fixed)
    assert abs(predicted / chosen - 1) < 0.15, (predicted, chosen)
    share = float(jnp.mean(bias2 if dominant == "bias" else var) / jnp.mean(bias2 + var))
    assert share > least_share, (dominant, share)


def test_order_one_slow_orbit_bias_matches_monte_carlo(scene):
    """A slow camera: the prior, not the pixels, sets the depth. The predicted error is
    the prior's bias along the rays (decimetres), and matches simulation."""
    times, x, paths = scene
    P = paths["slow orbit"]
    bias2, var, q = smoother_error_terms(P, x, times, SIGMA, order=1)
    predicted = float(jnp.sqrt(jnp.mean(bias2 + var)))
    mc = _monte_carlo(
        P,
        x,
        times,
        lambda P, uv, t: (
            smooth_points(P, uv, t, order=1, pixel_sigma=SIGMA, process_psd=float(q)).points
        ),
    )
    assert abs(predicted / mc - 1) < 0.15, (predicted, mc)
    assert predicted > 0.1  # [m]: the slide along the rays, not the pixel noise
    assert float(jnp.mean(bias2)) > 0.95 * float(jnp.mean(bias2 + var))


def test_follower_and_slow_orbit_predicted_far_worse_than_random(scene):
    times, x, paths = scene
    rms = {
        name: float(expected_smoother_errors_for_cameras(P, x[None], times, SIGMA, 2)[0])
        for name, P in paths.items()
    }
    assert rms["random"] < 0.01, rms
    assert rms["follower"] > 10 * rms["random"], rms
    assert rms["slow orbit"] > 10 * rms["random"], rms


def test_gradient_with_respect_to_the_cameras_is_finite_and_matches_differences(scene):
    """At a given density (the chosen one is a grid choice, held fixed for gradients)."""
    times, x, paths = scene
    P = paths["orbit"]
    q = float(smoother_error_terms(P, x, times, SIGMA, order=2)[2])

    def f(scale):
        Ps = P.at[:, :, 3].multiply(1.0 + scale)  # moves every camera
        bias2, var, _ = smoother_error_terms(Ps, x, times, SIGMA, 2, process_psd=q)
        return jnp.sqrt(jnp.mean(bias2 + var))

    g = float(jax.grad(f)(0.0))
    h = 1e-6
    fd = float((f(h) - f(-h)) / (2 * h))
    assert np.isfinite(g) and g != 0.0
    assert abs(g - fd) < 1e-3 * abs(fd) + 1e-9, (g, fd)


def test_bad_arguments(scene):
    times, x, paths = scene
    P = paths["orbit"]
    with pytest.raises(ValueError, match="order"):
        expected_smoother_errors_for_cameras(P, x[None], times, SIGMA, order=4)
    with pytest.raises(ValueError, match="samples"):
        expected_smoother_errors_for_cameras(P, x, times, SIGMA)
    with pytest.raises(ValueError, match="times"):
        expected_smoother_errors_for_cameras(P, x[None], times[::-1], SIGMA)


def test_density_search_finds_the_full_grids_density_and_held_densities_are_used(scene):
    """The density search reads 8 of the 10 grid values; on camera paths from fast to
    degenerate and for orders 1 and 2 it picks the full grid's density, so the predicted
    errors are the same; held densities (a design round's line search) are used as given,
    and without ``hold`` the search runs as before; on any grid profile with one minimum,
    wherever that lies (the ends included), it hands the parabola the full grid's three
    values."""
    times, x, paths = scene
    samples = jnp.stack([x, x + jnp.array([0.05, -0.02, 0.01])])
    held_errors = jax.jit(se.frame_errors2_held, static_argnames="order")
    for name, P in paths.items():
        for order in (1, 2):
            fast = se._terms(P, x, times, SIGMA, order, None)
            full = se._terms(P, x, times, SIGMA, order, None, full_grid=True)
            for a, b in zip(fast, full, strict=True):
                np.testing.assert_allclose(a, b, rtol=1e-12, err_msg=f"{name}, order {order}")
            if order != 2:
                continue
            plain, q = held_errors(P, samples, times, SIGMA, order)
            kept, q3 = held_errors(P, samples, times, SIGMA, order, (2.0 * q, jnp.asarray(True)))
            np.testing.assert_array_equal(q3, 2.0 * q)
            tau = (times[-1] - times[0]) / (F - 1)
            # (the follower's and slow orbit's near-singular systems amplify rounding)
            for i in range(2 if name in ("orbit", "random") else 0):
                bias2, var, _ = smoother_error_terms(
                    P, samples[i], times, SIGMA, order, float(2.0 * q[i] / tau ** (2 * order - 1))
                )
                np.testing.assert_allclose(kept[i], bias2 + var, rtol=1e-9)
            searched, q4 = held_errors(P, samples, times, SIGMA, order, (2.0 * q, False))
            np.testing.assert_allclose(searched, plain, rtol=1e-12)
            np.testing.assert_allclose(q4, q, rtol=1e-12)
    grid = jnp.asarray(10.0 ** np.arange(-4.0, 5.01, 1.0))
    for best in range(grid.shape[0]):
        values = jnp.asarray((np.arange(grid.shape[0]) - best - 0.3) ** 2)[None]
        searched = se._search_density(
            lambda idx, v=values: jnp.take_along_axis(v, idx, axis=1), grid, 1
        )
        assert np.sum(np.isfinite(searched)) <= 8
        assert float(_argmin_log(grid, searched[0])) == float(_argmin_log(grid, values[0]))

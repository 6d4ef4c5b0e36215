"""The DCT candidate of estimate_points: its evidence only where its factor is trusted."""

from __future__ import annotations

import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxtraj.estimators import _dct_candidate as dc
from jaxtraj.estimators._common import normalise_cameras

DATA = Path(__file__).parent / "data"


def dense_neg2(Hb, gb, c, prec, mean):
    """-2 log evidence of the linear-Gaussian model by dense NumPy algebra."""
    N = Hb + np.diag(prec)
    b = gb + prec * mean
    return (
        c
        + np.sum(prec * mean**2)
        - b @ np.linalg.solve(N, b)
        + np.linalg.slogdet(N)[1]
        - np.sum(np.log(prec))
    )


def test_posterior_matches_dense_algebra_and_refuses_a_singular_precision():
    rng = np.random.default_rng(0)
    n = 12
    J = rng.normal(size=(30, n))
    Hb, gb, c = J.T @ J, rng.normal(size=n), 40.0
    prec, mean = np.full(n, 0.5), rng.normal(size=n)
    neg2, beta, _ = jax.jit(dc._posterior)(Hb, gb, c, prec, mean)
    np.testing.assert_allclose(float(neg2), dense_neg2(Hb, gb, c, prec, mean), rtol=1e-10)
    np.testing.assert_allclose(
        beta, np.linalg.solve(Hb + np.diag(prec), gb + prec * mean), rtol=1e-9
    )
    # the data pin one direction 1e18 times more than the prior pins the others, and two
    # nearly equal directions: the second one's pivot loses more than half the digits
    u = rng.normal(size=n)
    Hs = 1e18 * (np.outer(u, u) + np.outer(u + 1e-6 * rng.normal(size=n), u))
    Hs = 0.5 * (Hs + Hs.T)
    neg2_s = jax.jit(dc._posterior)(Hs, gb, c, prec, mean)[0]
    assert np.isinf(float(neg2_s)), neg2_s


def test_a_fit_linearised_next_to_a_camera_has_no_evidence():
    # One track of the trust benchmark (sim/orbit5/0.5px): the size-12 fit relinearised
    # at a trajectory that passes near a camera gives a normal matrix of condition ~1e16;
    # its clamped pivots once gave an evidence of -7e7 that beat every smoother and a
    # status-OK estimate 300 m off.
    d = np.load(DATA / "track_near_camera.npz")
    P, uv, w, times = (jnp.asarray(d[k]) for k in ("P", "uv", "w", "times"))
    sigma2 = float(d["pixel_sigma"]) ** 2
    x_lin = jnp.asarray(d["x_lin"])  # the order-2 smoother's estimate (8 cm off)
    Pn = normalise_cameras(P)
    blocks = dc.data_blocks(Pn, uv, w, x_lin, sigma2)

    @functools.partial(jax.jit, static_argnums=0)
    def fit(k):
        return dc.dct_fit(Pn, uv, w, times, sigma2, x_lin, blocks, k, 1.0)[:2]

    neg2, x = fit(12)
    err = np.linalg.norm(np.asarray(x) - d["X"], axis=-1).mean()
    assert not err < 1.0  # the failure this test is about (NaN or metres off)
    assert np.isinf(float(neg2)), neg2
    neg2_4, x4 = fit(4)  # a small basis stays a candidate on the same data
    assert np.isfinite(float(neg2_4))
    assert np.linalg.norm(np.asarray(x4) - d["X"], axis=-1).mean() < 0.1

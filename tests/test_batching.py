"""How the batched drivers group points, and their input checks, on a CPU and (simulated) on
an accelerator: same numbers and same errors whichever path runs.

The accelerator's path is taken here by making the platform look like a GPU
(``platform_of`` patched): the drivers then group points as on a GPU (one vmap over all
points) and check tracks the way they do for device-resident arrays.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtraj as jt
from jaxtraj import _batching, _checks
from tests._scenes import scene


def _as_gpu(monkeypatch):
    monkeypatch.setattr(_batching, "platform_of", lambda x=None: "gpu")
    monkeypatch.setattr(_checks, "platform_of", lambda x=None: "gpu")


def test_map_points_equals_vmap_for_every_group_size():
    xs = jnp.arange(21.0).reshape(7, 3)
    ref = jax.vmap(lambda x: jnp.sum(x**2))(xs)
    for per_step in (0, 1, 3, 7, 16):
        out = _batching.map_points(lambda x: jnp.sum(x**2), xs, per_step)
        np.testing.assert_array_equal(np.asarray(out), np.asarray(ref))


def test_platform_of_and_points_per_step():
    assert _batching.platform_of(np.ones(3)) == jax.default_backend()
    assert _batching.platform_of(jnp.ones(3)) == jax.devices()[0].platform
    seen = []
    jax.jit(lambda x: seen.append(_batching.platform_of(x)) or x)(jnp.ones(3))
    assert seen == [jax.default_backend()]  # a tracer: the default backend
    on_cpu = _batching.platform_of(jnp.ones(3)) == "cpu"
    assert _batching.points_per_step(8, 0, jnp.ones(3)) == (8 if on_cpu else 0)


def _tracks(rng, n=5):
    s = scene(rng, F=40, k=6, noise=0.3, in_span=False)
    uv = np.stack([s["uv"] + rng.normal(size=s["uv"].shape) * 0.5 for _ in range(n)])
    w = np.ones(uv.shape[:2])
    w[1, ::5] = 0.0
    return s, uv, w


def test_accelerator_grouping_gives_the_cpu_numbers(rng, monkeypatch):
    from jaxtraj.estimators import select_k_points

    s, uv, w = _tracks(rng)
    ref = jt.reconstruct_points(s["P"], uv, s["basis"], w)
    ref_k = select_k_points(s["P"], uv, s["times"], (3, 5), w, folds=2)
    _as_gpu(monkeypatch)
    assert _batching.points_per_step(8, 0) == 0
    got = jt.reconstruct_points(s["P"], uv, s["basis"], w)
    got_k = select_k_points(s["P"], uv, s["times"], (3, 5), w, folds=2)
    np.testing.assert_allclose(np.asarray(got.coeffs), np.asarray(ref.coeffs), rtol=1e-10)
    np.testing.assert_allclose(np.asarray(got.gain), np.asarray(ref.gain), rtol=1e-8)
    np.testing.assert_array_equal(np.asarray(got.status), np.asarray(ref.status))
    np.testing.assert_allclose(np.asarray(got_k.score), np.asarray(ref_k.score), rtol=1e-9)
    np.testing.assert_array_equal(np.asarray(got_k.k), np.asarray(ref_k.k))


def test_accelerator_grouping_gives_the_cpu_numbers_for_the_regularised_dct(rng, monkeypatch):
    """The weight choices (K-fold and GCV, one eigendecomposition per fold and track) vmapped
    over the tracks as on a GPU equal the CPU's loop of unbatched calls."""
    from jaxtraj.estimators import reconstruct_regularised_points

    s, uv, w = _tracks(rng)
    grid = np.logspace(-2, 6, 5)

    def run():
        args = (s["P"], uv, s["times"], w)
        return [
            reconstruct_regularised_points(*args, k=8, grid=grid, folds=3, criterion=c)
            for c in ("kfold", "gcv")
        ]

    ref = run()
    _as_gpu(monkeypatch)
    got = run()
    for (r, _, c), (g, _, d) in zip(ref, got, strict=True):
        np.testing.assert_allclose(np.asarray(d.cv_rms_px), np.asarray(c.cv_rms_px), rtol=1e-9)
        # 8 Lanczos steps in each eigenbasis (batched and unbatched LAPACK round apart)
        np.testing.assert_allclose(np.asarray(d.gain), np.asarray(c.gain), rtol=0.02)
        np.testing.assert_array_equal(np.asarray(d.lam), np.asarray(c.lam))
        np.testing.assert_allclose(np.asarray(g.points), np.asarray(r.points), atol=1e-10)
        np.testing.assert_array_equal(np.asarray(g.status), np.asarray(r.status))


@pytest.mark.parametrize("accelerator", [False, True])
def test_track_checks_on_both_paths(rng, monkeypatch, accelerator):
    s, uv, w = _tracks(rng)
    P, basis = s["P"], s["basis"]
    if accelerator:
        _as_gpu(monkeypatch)
        assert _checks.on_accelerator(jnp.asarray(uv))
    uv_d, w_d = jnp.asarray(uv), jnp.asarray(w)
    jt.reconstruct_points(P, uv_d, basis, w_d)  # valid: no error
    assert _checks.check_tracks(uv_d, w_d) == 32  # fewest observed: track 1, 8 of 40 weigh 0
    assert _checks.check_tracks(uv_d, None) == 40
    bad = uv.copy()
    bad[2, 7] = np.nan
    with pytest.raises(ValueError, match=r"uv: 1 non-finite pixel\(s\) .* index \(2, 7\)"):
        jt.reconstruct_points(P, jnp.asarray(bad), basis, w_d)
    bad[1, 5] = np.nan  # weight 0 there: ignored
    with pytest.raises(ValueError, match=r"uv: 1 non-finite"):
        jt.reconstruct_points(P, jnp.asarray(bad), basis, w_d)
    neg = w.copy()
    neg[0, 3] = -1.0
    with pytest.raises(ValueError, match="weights: must be finite and >= 0"):
        jt.reconstruct_points(P, uv_d, basis, jnp.asarray(neg))
    few = w.copy()
    few[4, 6:] = 0.0  # 6 observed frames: 2 * 6 < 3 * k
    with pytest.raises(ValueError, match=r"k=6 is too large for 6 observed frame"):
        jt.reconstruct_points(P, uv_d, basis, jnp.asarray(few))

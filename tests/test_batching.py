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


# --- every core of a CPU: on_cores ---------------------------------------------------------


def _counting(kernel, calls):
    def run(pts):
        calls.append(jax.tree_util.tree_leaves(pts)[0].shape[0])
        return kernel(pts)

    return run


def test_on_cores_splits_pads_and_joins_in_order(monkeypatch):
    monkeypatch.setenv("JAXTRAJ_CPU_THREADS", "3")
    xs, ys = jnp.arange(202.0), jnp.arange(404.0).reshape(202, 2)
    calls = []
    out = _batching.on_cores(
        _counting(lambda p: {"a": p[0] * 2.0, "b": p[1].sum(1)}, calls), (xs, ys), min_per_core=8
    )
    assert calls == [72, 72, 72]  # ceil(202 / 3) = 68, aligned to 8; the last chunk padded
    np.testing.assert_array_equal(np.asarray(out["a"]), 2.0 * np.arange(202.0))
    np.testing.assert_array_equal(np.asarray(out["b"]), np.asarray(ys).sum(1))


def test_on_cores_runs_once_when_traced_small_single_core_or_off_the_cpu(monkeypatch):
    monkeypatch.setenv("JAXTRAJ_CPU_THREADS", "2")
    xs = jnp.arange(300.0)
    calls = []
    kernel = _counting(lambda p: p * 2.0, calls)
    jax.jit(lambda x: _batching.on_cores(kernel, x))(xs)  # traced points
    jax.jit(lambda c: _batching.on_cores(lambda p: p * c, xs, (c,)))(2.0)  # traced other
    _batching.on_cores(kernel, xs[:100])  # fewer than 2 x 64 points
    monkeypatch.setenv("JAXTRAJ_CPU_THREADS", "1")
    _batching.on_cores(kernel, xs)
    monkeypatch.setenv("JAXTRAJ_CPU_THREADS", "2")
    monkeypatch.setattr(_batching, "platform_of", lambda x=None: "gpu")
    _batching.on_cores(kernel, xs)
    assert calls == [300, 100, 300, 300]
    monkeypatch.setenv("JAXTRAJ_CPU_THREADS", "0")
    with pytest.raises(ValueError, match="JAXTRAJ_CPU_THREADS"):
        _batching.cpu_cores()


def test_on_cores_carries_the_callers_precision_into_its_threads(monkeypatch):
    monkeypatch.setenv("JAXTRAJ_CPU_THREADS", "2")
    with jax.enable_x64(False):
        out = _batching.on_cores(lambda p: p + jnp.ones(()), np.arange(256.0), min_per_core=8)
    assert out.dtype == jnp.float32  # a thread without the context would make float64


def test_drivers_split_over_cores_give_the_one_call_numbers(rng, monkeypatch):
    """reconstruct_points and estimate_points on 2 chunks from 2 threads equal one call
    over all points, for 130 tracks (chunks of 72, the last padded)."""
    from jaxtraj import solve

    monkeypatch.setenv("JAXTRAJ_CPU_THREADS", "2")
    s = scene(rng, F=24, k=4, noise=0.3, in_span=False)
    n = 2 * _batching.MIN_POINTS_PER_CORE + 2
    uv = s["uv"][None] + rng.normal(size=(n, *s["uv"].shape)) * 0.5
    w = np.ones(uv.shape[:2])
    w[3, ::4] = 0.0
    kernel, calls = solve._reconstruct_points, []

    def counted(P, uv, *args):
        calls.append(uv.shape[0])
        return kernel(P, uv, *args)

    monkeypatch.setattr(solve, "_reconstruct_points", counted)
    got = jt.reconstruct_points(s["P"], uv, s["basis"], w, penalty=np.full(4, 1e-3))
    monkeypatch.setenv("JAXTRAJ_CPU_THREADS", "1")
    ref = jt.reconstruct_points(s["P"], uv, s["basis"], w, penalty=np.full(4, 1e-3))
    assert calls == [72, 72, n]
    for name in ("coeffs", "rms_px", "gain", "depth_uncertainty"):
        np.testing.assert_allclose(getattr(got, name), getattr(ref, name), rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(got.status, ref.status)

    one = jt.estimate_points(s["P"], uv, s["times"], w, pixel_sigma=0.5, orders=(1,), dct_ks=())
    monkeypatch.setenv("JAXTRAJ_CPU_THREADS", "2")
    est = jt.estimate_points(s["P"], uv, s["times"], w, pixel_sigma=0.5, orders=(1,), dct_ks=())
    for name in ("points", "cov", "order", "status"):
        np.testing.assert_allclose(getattr(est, name), getattr(one, name), rtol=1e-12, atol=1e-15)


def _lapack_calls(fn, *args) -> set:
    import re

    return set(re.findall(r"custom_call @(lapack_\w+)", fn.lower(*args).as_text()))


def test_kernels_split_over_cores_call_no_lapack(rng):
    """Kernels with LAPACK calls are not run from several threads (module notes of
    jaxtraj._batching); this guards the three that are. refine_points' kernel, which does
    call LAPACK, shows that the check sees such calls."""
    from jaxtraj import solve
    from jaxtraj.estimators import estimate, refine, select_k

    s, uv, w = _tracks(rng)
    P, uv, w, t, B = (jnp.asarray(a) for a in (s["P"], uv, w, s["times"], s["basis"]))
    bounds = jnp.asarray([20.0, 0.3, 0.5])
    opts = dict(
        pixel_sigma=jnp.asarray(0.5),
        iterations=3,
        loss="l2",
        loss_scale=jnp.asarray(2.0),
        depth_guess=jnp.asarray(1.0),
        criterion="ml",
    )
    kernels = {
        "reconstruct_points": (solve._reconstruct_points, P, uv, B, w, bounds, 1, True, None, 8),
        "estimate_points": (
            jax.jit(lambda P, u, t, w: estimate._estimate(P, u, t, w, (1, 2), (4,), 0.08, opts, 8)),
            P, uv, t, w,
        ),
        "select_k_points": (
            select_k._select_k_points, P, uv, t, w, (3, 5), 2, 100.0, "gain_weighted", 20.0, 8
        ),
    }  # fmt: skip
    for name, (fn, *args) in kernels.items():
        assert _lapack_calls(fn, *args) == set(), name
    lin = jt.reconstruct_points(P, uv, B, w)
    lm = jax.jit(lambda c: refine._refine_points(P, uv, B, c, w, lin.status, {}))
    assert _lapack_calls(lm, lin.coeffs)  # the check sees LAPACK where it is


def _batched_lapack_calls(fn, *args) -> dict:
    """LAPACK custom calls of ``fn`` and whether any of their operands or results has a
    batch axis (rank above 2)."""
    import re

    calls = {}
    for line in fn.lower(*args).as_text().splitlines():
        m = re.search(r"custom_call @(lapack_\w+)", line)
        if m:
            ranks = [s.count("x") for s in re.findall(r"tensor<([^>]*)>", line)]
            calls[m.group(1)] = calls.get(m.group(1), False) or max(ranks, default=0) > 2
    return calls


def test_regularised_choice_split_over_cores_calls_lapack_unbatched(rng):
    """The regularised DCT's per-track choice runs from several threads; its LAPACK calls
    (eigendecomposition, the held-out Cholesky of folds of more than 8 frames) must be
    unbatched (module notes of jaxtraj._batching). refine_points' batched QR shows that
    the check sees a batch axis."""
    from jaxtraj.estimators import refine, regularised

    s, uv, w = _tracks(rng)
    P, uv, w, t, B = (jnp.asarray(a) for a in (s["P"], uv, w, s["times"], s["basis"]))
    basis = jt.DCTBasis.from_times(t, 12)
    rough, Phi = regularised.roughness_penalty(basis), basis(t)
    grid = jnp.logspace(-4, 10, 5)
    for folds in (2, 5, None):  # held-out blocks of 40 rows (LAPACK), 16 rows, GCV
        calls = _batched_lapack_calls(
            regularised._chosen_points, P, uv, Phi, w, rough, grid, 20.0, folds, 1
        )
        assert "lapack_dsyevd_ffi" in calls, (folds, calls)
        assert not any(calls.values()), (folds, calls)
    lin = jt.reconstruct_points(P, uv, B, w)
    lm = jax.jit(lambda c: refine._refine_points(P, uv, B, c, w, lin.status, {}))
    assert any(_batched_lapack_calls(lm, lin.coeffs).values())


def test_regularised_choice_split_over_cores_gives_the_one_call_numbers(rng, monkeypatch):
    """reconstruct_regularised_points with a weight per point, its tracks in 2 chunks from
    2 threads (7 tracks: chunks of 4, the last padded), equals one call."""
    from jaxtraj.estimators import reconstruct_regularised_points

    s, uv, w = _tracks(rng, n=7)
    kw = dict(k=12, grid=np.logspace(-4, 10, 5))
    monkeypatch.setenv("JAXTRAJ_CPU_THREADS", "1")
    ref, _, ref_c = reconstruct_regularised_points(s["P"], uv, s["times"], w, **kw)
    monkeypatch.setenv("JAXTRAJ_CPU_THREADS", "2")
    got, _, got_c = reconstruct_regularised_points(s["P"], uv, s["times"], w, **kw)
    np.testing.assert_array_equal(got_c.lam, ref_c.lam)
    np.testing.assert_allclose(got_c.criterion, ref_c.criterion, rtol=1e-9)
    np.testing.assert_allclose(got.points, ref.points, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(got.gain, ref.gain, rtol=1e-9)
    np.testing.assert_array_equal(got.status, ref.status)


def test_one_blas_thread_limits_blas_inside_and_restores_it(monkeypatch):
    """Inside one_blas_thread every BLAS library runs one thread; the limit is lifted when
    the last of several overlapping users leaves (not when the first does), and
    JAXTRAJ_ONE_BLAS_THREAD=0 leaves BLAS alone."""
    threadpoolctl = pytest.importorskip("threadpoolctl")

    def threads():
        info = threadpoolctl.threadpool_info()
        return [i["num_threads"] for i in info if i["user_api"] == "blas"]

    jt.estimators.select_penalty_cv  # noqa: B018 (the package is imported)
    _batching._controller()  # loads JAX's LAPACK (SciPy's BLAS) first
    before = threads()
    assert before, "no BLAS library loaded"
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        outer = threads()
        first, second = _batching.one_blas_thread(), _batching.one_blas_thread()
        first.__enter__()
        second.__enter__()
        assert set(threads()) == {1}
        first.__exit__(None, None, None)  # overlapping: the second is still inside
        assert set(threads()) == {1}
        second.__exit__(None, None, None)
        assert threads() == outer
        monkeypatch.setenv("JAXTRAJ_ONE_BLAS_THREAD", "0")
        with _batching.one_blas_thread():
            assert threads() == outer
    assert threads() == before

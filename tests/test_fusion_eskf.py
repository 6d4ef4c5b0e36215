"""Error-state filter and RTS smoother: linear limit, NumPy reference, jit/vmap, dtypes."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtraj.fusion import (
    FusionResult,
    ImuData,
    ImuNoise,
    NominalState,
    RobotNoise,
    RobotPoses,
    build_events,
    eskf,
    eskf_batch,
    initial_covariance,
    initial_state,
    rts_smoother,
)
from jaxtraj.fusion.events import POSE
from jaxtraj.fusion.reference import eskf_numpy
from jaxtraj.fusion.simulate import LissajousTrajectory, simulate_recording

G = np.array([0.0, 0.0, -9.81])


# --------------------------------------------------------------------------- linear limit
def _linear_problem(rng, n=60, m=14):
    """Orientation frozen: no gyro signal or noise, zero orientation/gyro-bias prior."""
    t = np.cumsum(rng.uniform(0.003, 0.006, n))
    imu = ImuData(
        t=jnp.asarray(t), gyro=jnp.zeros((n, 3)), accel=jnp.asarray(rng.normal(0, 1, (n, 3)))
    )
    t_rob = np.sort(rng.uniform(t[0] - 0.01, t[-1] + 0.01, m))
    t_rob = np.unique(np.append(t_rob, t[10]))  # one pose exactly at an IMU time
    m = len(t_rob)
    robot = RobotPoses(
        t=jnp.asarray(t_rob),
        p=jnp.asarray(rng.normal(0, 0.01, (m, 3))),
        q=jnp.tile(jnp.asarray([1.0, 0.0, 0.0, 0.0]), (m, 1)),
    )
    noise = ImuNoise(0.05, 0.0, 0.02, 0.0)
    rnoise = RobotNoise(2e-3, 1e-3)
    A = rng.normal(size=(9, 9)) * 0.1
    S9 = A @ A.T + np.diag([1e-4] * 3 + [1e-2] * 3 + [1e-2] * 3)
    P0 = np.zeros((15, 15))
    lin = np.r_[0:3, 3:6, 9:12]
    P0[np.ix_(lin, lin)] = S9
    x0 = NominalState.create(
        rng.normal(0, 0.01, 3), [1.0, 0, 0, 0], v=rng.normal(0, 0.1, 3), b_a=[0.01, 0, -0.02]
    )
    return imu, robot, noise, rnoise, x0, P0, lin


def _kf_rts_numpy(ev, x0, P0lin, noise, rnoise):
    """Textbook linear KF + RTS on s = (p, v, b_a) with the filter's input interpolation."""
    t, kind, act = np.asarray(ev.t), np.asarray(ev.kind), np.asarray(ev.active)
    u0, u1, t1, z = np.asarray(ev.u0), np.asarray(ev.u1), np.asarray(ev.t1), np.asarray(ev.z_p)
    s = np.concatenate([x0.p, x0.v, x0.b_a])
    P = P0lin.copy()
    first = int(np.argmax(kind == 0))
    t_last, seg = t[first], (t[first], t1[first], u0[first], u1[first])
    I3, Z3 = np.eye(3), np.zeros((3, 3))
    H = np.hstack([I3, Z3, Z3])
    Rm = rnoise.position**2 * I3
    filt, prior = [], []
    for e in range(len(t)):
        te = max(t[e], t_last)
        dt = te - t_last
        w = np.clip((t_last + dt / 2 - seg[0]) / (seg[1] - seg[0]), 0, 1)
        a = (seg[2] + w * (seg[3] - seg[2]))[3:] + G
        h = dt * dt / 2
        F = np.block([[I3, dt * I3, -h * I3], [Z3, I3, -dt * I3], [Z3, Z3, I3]])
        s = F @ s + np.concatenate([h * a, dt * a, np.zeros(3)])
        Q = np.diag(
            [0] * 3
            + [noise.accel_noise_density**2 * dt] * 3
            + [noise.accel_random_walk**2 * dt] * 3
        )
        P = F @ P @ F.T + Q
        prior.append((F, s.copy(), P.copy()))
        if kind[e] == POSE and act[e]:
            S = H @ P @ H.T + Rm
            K = P @ H.T @ np.linalg.inv(S)
            s = s + K @ (z[e] - H @ s)
            P = (np.eye(9) - K @ H) @ P
        if kind[e] == 0:
            seg = (t[e], t1[e], u0[e], u1[e])
        t_last = te
        filt.append((s.copy(), P.copy()))
    sm = [filt[-1]]
    for e in range(len(t) - 2, -1, -1):
        s_f, P_f = filt[e]
        F, s_p, P_p = prior[e + 1]
        C = P_f @ F.T @ np.linalg.inv(P_p)
        s_n, P_n = sm[0]
        sm.insert(0, (s_f + C @ (s_n - s_p), P_f + C @ (P_n - P_p) @ C.T))
    return filt, sm


def test_linear_limit_filter_and_smoother_equal_kalman_and_rts(rng):
    imu, robot, noise, rnoise, x0, P0, lin = _linear_problem(rng)
    ev = build_events(imu, robot, noise=rnoise)
    res = eskf(ev, x0, P0, noise)
    sm = rts_smoother(res, noise)
    filt, smo = _kf_rts_numpy(ev, x0, P0[np.ix_(lin, lin)], noise, rnoise)
    for out, ref in ((res, filt), (sm, smo)):
        s_est = np.concatenate([out.x.p, out.x.v, out.x.b_a], axis=1)
        s_ref = np.stack([r[0] for r in ref])
        P_ref = np.stack([r[1] for r in ref])
        P_est = np.asarray(out.P)[:, lin][:, :, lin]
        assert np.max(np.abs(s_est - s_ref)) < 1e-10
        assert np.max(np.abs(P_est - P_ref)) < 1e-10 * np.max(np.abs(P_ref))
        # orientation stays exactly frozen
        np.testing.assert_allclose(out.x.q, np.tile([1.0, 0, 0, 0], (len(ev.t), 1)), atol=1e-15)
    assert int(np.sum(res.updated)) > 5


# --------------------------------------------------------------------------- general case
@pytest.fixture(scope="module")
def small_recording():
    rec = simulate_recording(
        jax.random.PRNGKey(3),
        LissajousTrajectory(),
        duration=1.0,
        imu_noise=ImuNoise.xsens_mti(),
        robot_noise=RobotNoise.kuka_class(),
        imu_rate=100.0,
        robot_period=0.012,
        image_rate=20.0,
        latency=0.004,
        imu_jitter=0.3,
    )
    ev = build_events(
        rec.imu, rec.robot, rec.image_times, noise=RobotNoise.kuka_class(), latency=0.004
    )
    P0 = initial_covariance(1e-3, 0.05, 0.02, 0.1, 0.01)
    return rec, ev, initial_state(ev), P0


def test_filter_equals_numpy_reference(small_recording):
    _, ev, x0, P0 = small_recording
    noise = ImuNoise.xsens_mti()
    res = eskf(ev, x0, P0, noise)
    ref, P_ref = eskf_numpy(ev, x0, P0, noise)
    np.testing.assert_allclose(res.x.p, ref["p"], atol=1e-11)
    np.testing.assert_allclose(res.x.v, ref["v"], atol=1e-9)
    q = np.asarray(res.x.q) * np.sign(np.asarray(res.x.q)[:, :1])
    np.testing.assert_allclose(q, ref["q"], atol=1e-10)
    np.testing.assert_allclose(res.x.b_a, ref["b_a"], atol=1e-9)
    np.testing.assert_allclose(res.x.b_g, ref["b_g"], atol=1e-10)
    assert np.max(np.abs(np.asarray(res.P) - P_ref)) < 1e-9 * np.max(np.abs(P_ref))


def test_jit_equals_eager(small_recording):
    _, ev, x0, P0 = small_recording
    noise = ImuNoise.xsens_mti()
    part = jax.tree_util.tree_map(lambda a: a[:10], ev)
    assert int(np.sum(part.active)) >= 2
    res = eskf(part, x0, P0, noise)
    with jax.disable_jit():
        eager = eskf(part, x0, P0, noise)
        eager_s = rts_smoother(eager, noise)
    np.testing.assert_allclose(res.x.p, eager.x.p, atol=1e-13)
    np.testing.assert_allclose(res.P, eager.P, atol=1e-15)
    np.testing.assert_allclose(rts_smoother(res, noise).x.p, eager_s.x.p, atol=1e-13)


def test_vmap_over_recordings_equals_loop():
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    noise, rnoise = ImuNoise.xsens_mti(), RobotNoise.kuka_class()
    P0 = initial_covariance(1e-3, 0.05, 0.02, 0.1, 0.01)

    def one(key):
        rec = simulate_recording(
            key,
            LissajousTrajectory(),
            duration=0.5,
            imu_noise=noise,
            robot_noise=rnoise,
            imu_rate=100.0,
            image_rate=10.0,
        )
        ev = build_events(rec.imu, rec.robot, rec.image_times, noise=rnoise, latency=rec.latency)
        return ev, initial_state(ev)

    evs, x0s = jax.jit(jax.vmap(one))(keys)  # one compiled program, not op by op
    batched = jax.vmap(lambda e, x: eskf(e, x, P0, noise))(evs, x0s)
    smoothed = jax.vmap(lambda r: rts_smoother(r, noise))(batched)
    # shared layout (same rates, no jitter): eskf_batch keeps the update a real branch
    assert bool(jnp.all(evs.kind == evs.kind[0]))
    shared = eskf_batch(evs, x0s, P0, noise)
    np.testing.assert_allclose(shared.x.p, batched.x.p, atol=1e-13)
    np.testing.assert_allclose(shared.P, batched.P, atol=1e-16)
    assert shared.kind.shape == evs.kind.shape
    # different layouts: falls back to a plain vmap
    mixed = evs.__class__(**{**vars(evs), "active": evs.active.at[0, :].set(False)})
    fallback = eskf_batch(mixed, x0s, P0, noise)
    np.testing.assert_allclose(fallback.x.p[1:], batched.x.p[1:], atol=1e-13)
    assert not bool(jnp.any(fallback.updated[0]))
    with pytest.raises(ValueError, match="events: expected a batch"):
        eskf_batch(jax.tree_util.tree_map(lambda a: a[0], evs), x0s, P0, noise)
    for i in range(3):
        ev_i, x0_i = jax.tree_util.tree_map(lambda a, i=i: a[i], (evs, x0s))
        single = eskf(ev_i, x0_i, P0, noise)
        np.testing.assert_allclose(batched.x.p[i], single.x.p, atol=1e-12)
        np.testing.assert_allclose(batched.P[i], single.P, atol=1e-15)
        np.testing.assert_allclose(smoothed.x.p[i], rts_smoother(single, noise).x.p, atol=1e-12)


def test_float32_close_to_float64(small_recording):
    _rec, ev, x0, P0 = small_recording
    noise = ImuNoise.xsens_mti()
    f32 = jax.tree_util.tree_map(
        lambda a: a.astype(jnp.float32) if jnp.issubdtype(a.dtype, jnp.floating) else a, (ev, x0)
    )
    r64 = eskf(ev, x0, P0, noise)
    r32 = eskf(*f32, P0.astype(jnp.float32), noise, store="diag")
    assert r32.x.p.dtype == jnp.float32 and r32.P.dtype == jnp.float32
    assert bool(r32.ok)
    # float32 round-off is far below the filter's own uncertainty
    sig = np.sqrt(np.asarray(r64.variances)[:, :3])
    err = np.abs(np.asarray(r32.x.p, np.float64) - np.asarray(r64.x.p))
    assert np.max(err / sig) < 0.05
    s32 = rts_smoother(eskf(*f32, P0.astype(jnp.float32), noise), noise)
    assert s32.x.p.dtype == jnp.float32 and bool(s32.ok)


def test_smoother_reduces_error_and_covariance(small_recording):
    from jaxtraj.fusion.simulate import true_states

    rec, ev, x0, P0 = small_recording
    noise = ImuNoise.xsens_mti()
    res = eskf(ev, x0, P0, noise)
    sm = rts_smoother(res, noise)
    truth = true_states(LissajousTrajectory(), ev.t, rec.imu.t, rec.b_a, rec.b_g)
    e_f = np.sqrt(np.mean((np.asarray(res.x.p) - truth.p) ** 2))
    e_s = np.sqrt(np.mean((np.asarray(sm.x.p) - truth.p) ** 2))
    assert e_s < e_f
    # smoothed variances never exceed filtered ones
    assert np.all(np.asarray(sm.variances) <= np.asarray(res.variances) * (1 + 1e-9) + 1e-18)
    assert isinstance(sm, FusionResult)


# --------------------------------------------------------------------------- bad inputs
def test_bad_options_and_shapes(small_recording):
    _, ev, x0, P0 = small_recording
    noise = ImuNoise.xsens_mti()
    with pytest.raises(ValueError, match="reset"):
        eskf(ev, x0, P0, noise, reset="sometimes")
    with pytest.raises(ValueError, match="store"):
        eskf(ev, x0, P0, noise, store="none")
    with pytest.raises(ValueError, match=r"P0: expected shape \(15, 15\)"):
        eskf(ev, x0, P0[:6, :6], noise)
    diag = eskf(ev, x0, P0, noise, store="diag")
    with pytest.raises(ValueError, match="full covariances"):
        rts_smoother(diag, noise)


def test_gradient_of_log_likelihood(small_recording):
    """d(total NLL)/d(initial position, accel noise density) by finite differences."""
    from jax.test_util import check_grads

    _, ev, x0, P0 = small_recording
    part = jax.tree_util.tree_map(lambda a: a[:24], ev)

    def total_nll(p0, density):
        noise = ImuNoise(density, 1.7e-4, 4e-5, 1e-6)
        x = NominalState(p=p0, v=x0.v, q=x0.q, b_a=x0.b_a, b_g=x0.b_g)
        return jnp.sum(eskf(part, x, P0, noise).nll)

    check_grads(jax.jit(total_nll), (x0.p, jnp.asarray(6e-4)), order=1, modes=("rev",), eps=1e-6)

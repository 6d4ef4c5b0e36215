"""Robot models (URDF package data) and the pure-JAX forward kinematics."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxtraj.io.urdf import ROBOTS, load_robot, read_urdf, robot_file
from jaxtraj.robot import (
    camera_pose,
    forward_kinematics,
    jacobian,
    joint_frames,
    kinematic_chain,
    link_positions,
)

# KUKA datasheet (ROS-Industrial kuka_kr16_support kr16_2): ranges and rated speeds [deg].
KR16_LOWER = [-185, -155, -130, -350, -130, -350]
KR16_UPPER = [185, 35, 154, 350, 130, 350]
KR16_SPEED = [156, 156, 156, 330, 330, 615]
# KUKA KR 60-3 specification (as in ROS-Industrial kuka_kr60_support kr60ha).
KR60_LOWER = [-185, -135, -120, -350, -119, -350]
KR60_UPPER = [185, 35, 158, 350, 119, 350]
KR60_SPEED = [128, 102, 128, 260, 245, 322]


def _random_q(chain, rng, m):
    lo, hi = np.asarray(chain.lower), np.asarray(chain.upper)
    return lo + rng.uniform(size=(m, chain.n)) * (hi - lo)


@pytest.mark.parametrize(
    "name, lower, upper, speed",
    [
        ("kr16_2", KR16_LOWER, KR16_UPPER, KR16_SPEED),
        ("kr60_3", KR60_LOWER, KR60_UPPER, KR60_SPEED),
    ],
)
def test_shipped_models_carry_the_datasheet_limits(name, lower, upper, speed):
    chain = load_robot(name)
    assert chain.n == 6
    np.testing.assert_allclose(np.degrees(chain.lower), lower, atol=1e-12)
    np.testing.assert_allclose(np.degrees(chain.upper), upper, atol=1e-12)
    np.testing.assert_allclose(np.degrees(chain.velocity), speed, atol=1e-12)
    # documented assumptions: rated speed in 0.5 s, acceleration limit in 0.25 s
    np.testing.assert_allclose(np.degrees(chain.acceleration), 2 * np.asarray(speed), rtol=1e-12)
    np.testing.assert_allclose(np.degrees(chain.jerk), 8 * np.asarray(speed), rtol=1e-12)


def test_kr16_home_pose_matches_the_datasheet_geometry():
    """A2 = -90, A3 = +90 deg: upper arm up, forearm level; the flange sits at
    x = 0.26 + 0.67 + 0.158, z = 0.675 + 0.68 - 0.035 with x out of the flange."""
    chain = load_robot("KR 16-2")
    T = np.asarray(forward_kinematics(chain, np.radians([0, -90, 90, 0, 0, 0])))
    np.testing.assert_allclose(T[:3, 3], [1.088, 0.0, 1.32], atol=1e-15)
    np.testing.assert_allclose(T[:3, :3], np.eye(3), atol=1e-15)
    # A1 turns the arm clockwise seen from above (KUKA's A1 sign): +90 deg moves it to -y
    T = np.asarray(forward_kinematics(chain, np.radians([90, -90, 90, 0, 0, 0])))
    np.testing.assert_allclose(T[:3, 3], [0.0, -1.088, 1.32], atol=1e-15)


@pytest.mark.parametrize("name", sorted(ROBOTS))
@pytest.mark.parametrize("tip", ["flange", "tool0"])
def test_forward_kinematics_equals_pinocchio(name, tip, rng):
    pin = pytest.importorskip("pinocchio")
    chain = load_robot(name, tip_link=tip)
    model = pin.buildModelFromUrdf(str(robot_file(name)))
    data = model.createData()
    frame = model.getFrameId(tip)
    qs = _random_q(chain, rng, 40)
    ours = np.asarray(jax.jit(jax.vmap(lambda q: forward_kinematics(chain, q)))(qs))
    worst = 0.0
    for q, T in zip(qs, ours, strict=True):
        pin.framesForwardKinematics(model, data, q)
        worst = max(worst, np.max(np.abs(data.oMf[frame].homogeneous - T)))
    assert worst < 1e-12


def test_jit_vmap_and_camera_pose(rng):
    chain = load_robot("kr16_2")
    qs = _random_q(chain, rng, 5)
    loop = np.stack([np.asarray(forward_kinematics(chain, q)) for q in qs])
    batched = jax.vmap(lambda q: forward_kinematics(chain, q))(qs)
    np.testing.assert_allclose(batched, loop, atol=1e-15)
    np.testing.assert_allclose(jax.jit(forward_kinematics)(chain, qs[0]), loop[0], atol=1e-15)
    frames = np.asarray(joint_frames(chain, qs[0]))
    assert frames.shape == (7, 4, 4)
    np.testing.assert_allclose(frames[-1], loop[0], atol=1e-15)
    T_w_base = np.eye(4)
    T_w_base[:3, 3] = [2.0, -1.0, 0.5]
    T_f_c = np.eye(4)
    T_f_c[:3, :3] = [[0, 0, 1], [0, -1, 0], [1, 0, 0]]
    T_f_c[:3, 3] = [0.05, 0.0, 0.1]
    np.testing.assert_allclose(
        camera_pose(chain, qs[0], T_f_c, T_w_base), T_w_base @ loop[0] @ T_f_c, atol=1e-14
    )


def test_jacobian_equals_autodiff_and_gradients_check(rng):
    chain = load_robot("kr16_2")
    q = _random_q(chain, rng, 1)[0]
    J = np.asarray(jax.jit(jacobian)(chain, q))
    dT = np.asarray(jax.jit(jax.jacfwd(lambda x: forward_kinematics(chain, x)))(q))  # (4, 4, n)
    R = np.asarray(forward_kinematics(chain, q))[:3, :3]
    np.testing.assert_allclose(J[:3], dT[:3, 3], atol=1e-12)
    for i in range(chain.n):  # angular velocity: dR/dq_i R^T = [w_i]x
        W = dT[:3, :3, i] @ R.T
        np.testing.assert_allclose(J[3:, i], [W[2, 1], W[0, 2], W[1, 0]], atol=1e-12)
    position = jax.jit(lambda x: forward_kinematics(chain, x)[:3, 3])
    check_grads(position, (jnp.asarray(q),), order=1, modes=("fwd", "rev"))


def _mixed_chain(rng):
    """Four joints, two of them prismatic, with random origins, axes and tip."""

    def pose():
        Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        T = np.eye(4)
        T[:3, :3] = Q * np.sign(np.linalg.det(Q))
        T[:3, 3] = rng.normal(size=3)
        return T

    return kinematic_chain(
        "mixed",
        ["a", "b", "c", "d"],
        np.stack([pose() for _ in range(4)]),
        rng.normal(size=(4, 3)),
        pose(),
        -3 * np.ones(4),
        3 * np.ones(4),
        np.ones(4),
        joint_types=["revolute", "prismatic", "revolute", "prismatic"],
    )


@pytest.mark.parametrize("robot", ["kr16_2", "mixed"])
def test_link_positions_and_their_analytic_derivative(robot, rng):
    """The frames' origins, the tip and points on it, with the geometric Jacobian as their
    derivative: the same values and derivatives (forward and reverse, vmapped, jitted, the
    chain traced) as autodiff through the 4x4 products of joint_frames."""
    chain = load_robot(robot) if robot != "mixed" else _mixed_chain(rng)
    tip_points = jnp.asarray(rng.normal(size=(2, 3)))
    Q = jnp.asarray(rng.uniform(-1.0, 1.0, size=(4, chain.n)))

    def by_frames(q, points):
        T = joint_frames(chain, q)
        return jnp.concatenate([T[:, :3, 3], points @ T[-1, :3, :3].T + T[-1, :3, 3]])

    got = jax.vmap(lambda q: link_positions(chain, q, tip_points))(Q)
    want = jax.vmap(lambda q: by_frames(q, tip_points))(Q)
    assert got.shape == (4, chain.n + 3, 3)
    np.testing.assert_allclose(got, want, atol=1e-14)
    W = jnp.asarray(rng.normal(size=got.shape))

    @jax.jit
    def grads(ch, Q, points):  # the chain traced: its arrays are arguments
        f = jax.vmap(lambda q, p: link_positions(ch, q, p), in_axes=(0, None))
        return jax.grad(lambda Q, p: jnp.sum(W * f(Q, p)), argnums=(0, 1))(Q, points)

    def ref(Q, p):
        return jnp.sum(W * jax.vmap(lambda q: by_frames(q, p))(Q))

    want_grads = jax.grad(ref, argnums=(0, 1))(Q, tip_points)
    for a, b in zip(grads(chain, Q, tip_points), want_grads, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12)
    fwd = jax.jacfwd(lambda q: link_positions(chain, q, tip_points))(Q[0])
    np.testing.assert_allclose(
        fwd, jax.jacfwd(lambda q: by_frames(q, tip_points))(Q[0]), atol=1e-12
    )
    check_grads(lambda q: link_positions(chain, q, tip_points), (Q[1],), order=1)


def test_with_limits_overrides_and_validates():
    chain = load_robot("kr16_2")
    acc = np.radians([100.0] * 6)
    new = chain.with_limits(acceleration=acc)
    np.testing.assert_allclose(new.acceleration, acc)
    np.testing.assert_allclose(new.velocity, chain.velocity)
    with pytest.raises(ValueError, match=r"jerk: expected shape \(6,\)"):
        chain.with_limits(jerk=[1.0, 2.0])
    with pytest.raises(ValueError, match="acceleration: limits must be > 0"):
        chain.with_limits(acceleration=np.zeros(6))
    with pytest.raises(ValueError, match="joint 1 has lower"):
        chain.with_limits(lower=np.full(6, 1.0), upper=np.full(6, 0.5) + np.eye(6)[0])
    assert bool(chain.within_limits(np.zeros(6)))
    assert not bool(chain.within_limits(np.radians([0, 40, 0, 0, 0, 0])))


def test_unknown_robot_and_bad_urdf_name_the_problem(tmp_path):
    with pytest.raises(ValueError, match=r"unknown robot 'kr6'.*kr16_2, kr60_3"):
        load_robot("kr6")
    missing = tmp_path / "none.urdf"
    with pytest.raises(ValueError, match=r"none\.urdf: URDF file not found"):
        read_urdf(missing)
    bad = tmp_path / "bad.urdf"
    bad.write_text("<robot name='x'><link name='a'/>\n<joint name='j' type='revolute'>")
    with pytest.raises(ValueError, match=r"bad\.urdf: not a readable URDF file"):
        read_urdf(bad)
    cont = tmp_path / "cont.urdf"
    cont.write_text(
        "<robot name='c'><link name='a'/><link name='b'/>"
        "<joint name='spin' type='continuous'><parent link='a'/><child link='b'/>"
        "<axis xyz='0 0 1'/></joint></robot>"
    )
    with pytest.raises(ValueError, match=r"cont\.urdf: joint 'spin' is 'continuous'"):
        read_urdf(cont)
    with pytest.raises(ValueError, match="tip_link 'nowhere' is not a link"):
        load_robot("kr16_2", tip_link="nowhere")


def test_kinematic_chain_checks_its_arguments():
    eye = np.tile(np.eye(4), (2, 1, 1))
    args = ("r", ["j1", "j2"], eye, [[0, 0, 1], [0, 1, 0]], np.eye(4), [-1, -1], [1, 1], [1, 1])
    chain = kinematic_chain(*args)
    assert chain.joint_types == ("revolute", "revolute")
    with pytest.raises(ValueError, match="axes: joint 1 has a zero axis"):
        kinematic_chain(*args[:3], [[0, 0, 1], [0, 0, 0]], *args[4:])
    skew = eye.copy()
    skew[1, 0, 1] = 0.5
    with pytest.raises(ValueError, match=r"origins\[1\]: expected a rigid transform"):
        kinematic_chain(*args[:2], skew, *args[3:])
    with pytest.raises(ValueError, match="joint_types"):
        kinematic_chain(*args, joint_types=["revolute", "spherical"])


def test_float32_forward_kinematics_within_rounding(rng):
    """The same chain in float32: the flange within ~100 eps of the 2.5 m lever arm."""
    chain = load_robot("kr16_2")
    chain32 = jax.tree_util.tree_map(
        lambda a: a.astype(jnp.float32) if hasattr(a, "astype") else a, chain
    )
    qs = _random_q(chain, rng, 20)
    fk = jax.jit(jax.vmap(forward_kinematics, in_axes=(None, 0)))
    T64 = np.asarray(fk(chain, qs))
    T32 = fk(chain32, qs.astype(np.float32))
    assert T32.dtype == jnp.float32
    eps = np.finfo(np.float32).eps
    np.testing.assert_allclose(np.asarray(T32)[:, :3, :3], T64[:, :3, :3], atol=100 * eps)
    np.testing.assert_allclose(np.asarray(T32)[:, :3, 3], T64[:, :3, 3], atol=100 * eps * 2.5)

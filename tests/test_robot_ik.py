"""Inverse kinematics: residuals on reachable poses, clear errors on unreachable ones."""

from __future__ import annotations

import re

import numpy as np
import pytest

from jaxtraj.io.urdf import load_robot
from jaxtraj.robot import forward_kinematics, inverse_kinematics, pose_residual, solve_ik

HOME = np.radians([0, -90, 90, 0, 0, 0])


@pytest.fixture(scope="module")
def kr16():
    return load_robot("kr16_2")


def test_reachable_poses_are_solved_to_1e9_within_limits(kr16, rng):
    lo, hi = np.asarray(kr16.lower), np.asarray(kr16.upper)
    for _ in range(5):
        q_true = lo + rng.uniform(0.1, 0.9, 6) * (hi - lo)
        T = np.asarray(forward_kinematics(kr16, q_true))
        result = inverse_kinematics(kr16, T, q_true + rng.normal(0.0, 0.3, 6))
        assert bool(result.success)
        assert float(result.position_error) < 1e-9
        assert float(result.rotation_error) < 1e-9
        r = np.asarray(pose_residual(kr16, result.q, T))
        assert np.max(np.abs(r[:3])) < 1e-9 and np.max(np.abs(r[3:])) < 1e-9
        assert bool(kr16.within_limits(result.q))
    # from the preferred configuration itself, the solution is that configuration
    T = np.asarray(forward_kinematics(kr16, HOME + 0.2))
    np.testing.assert_allclose(solve_ik(kr16, T, HOME + 0.2), HOME + 0.2, atol=1e-9)


def test_unreachable_pose_names_the_pose_and_the_distance(kr16):
    """The flange at home, moved 1 m forward. The farthest flange position from the A2
    axis is 0.68 + hypot(0.67, 0.035) + 0.158 m (arm stretched), so the target lies
    |target - A2| - that far out of reach."""
    T = np.array(forward_kinematics(kr16, HOME))
    T[0, 3] += 1.0
    a2 = np.array([0.26, 0.0, 0.675])
    expected = np.linalg.norm(T[:3, 3] - a2) - (0.68 + np.hypot(0.67, 0.035) + 0.158)
    result = inverse_kinematics(kr16, T, HOME)
    assert not bool(result.reachable) and not bool(result.success)
    with pytest.raises(ValueError, match=r"start pose: X 2088\.0 Y 0\.0 Z 1320\.0 mm") as err:
        solve_ik(kr16, T, HOME, what="start pose")
    message = str(err.value)
    assert "out of reach of kuka_kr16_2" in message
    reported = float(re.search(r"lies ([0-9.]+) mm beyond", message).group(1))
    assert reported == pytest.approx(1000 * expected, abs=0.1)


def test_pose_reachable_only_outside_the_limits_names_the_joint(kr16):
    """A1 restricted to +-10 deg; the pose needs A1 = 90 deg (or -90 deg turned over)."""
    narrow = kr16.with_limits(
        lower=np.asarray(kr16.lower).copy() * [10 / 185, 1, 1, 1, 1, 1],
        upper=np.asarray(kr16.upper).copy() * [10 / 185, 1, 1, 1, 1, 1],
    )
    q = HOME + np.radians([90, 0, 0, 0, 0, 0])
    T = np.asarray(forward_kinematics(narrow, q))
    result = inverse_kinematics(narrow, T, HOME)
    assert bool(result.reachable) and not bool(result.within_limits)
    assert float(result.limit_excess[0]) > np.radians(70)
    with pytest.raises(ValueError, match=r"end pose: .* only outside its joint limits: joint_a1 ="):
        solve_ik(narrow, T, HOME, what="end pose")
    with pytest.raises(ValueError, match=r"end pose: expected a finite \(4, 4\) pose"):
        solve_ik(narrow, T[:3], what="end pose")

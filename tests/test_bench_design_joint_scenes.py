"""The workpiece scenes of benchmarks/bench_design_joint.py --compare (the design itself is
benchmarked, not tested here: its tests are in test_design_joint.py)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_design_joint


@pytest.mark.parametrize("scene", ["cmu131_01", "cmu131_03"])
def test_motion_capture_scene_is_a_scaled_take_in_the_built_in_cell(shared_data, scene):
    sim = bench_design_joint.scene_cell("sim", frames=20, starts=1)
    spec = bench_design_joint.scene_cell(scene, frames=20, starts=1, data=shared_data)
    x = spec.predicted
    assert x.shape == (20, 3) and spec.times.shape == (20,)
    assert spec.times[-1] == pytest.approx(bench_design_joint.MOCAP_SECONDS)
    # centred where the built-in workpiece moves, and of a size the workpiece robot reaches
    np.testing.assert_allclose(x.mean(axis=0), sim.predicted.mean(axis=0), atol=1e-9)
    span = np.max(x.max(axis=0) - x.min(axis=0))
    assert 0.4 < span < 1.0, span
    # a walking take, not the built-in curve: the path differs from it
    assert np.max(np.linalg.norm(x - sim.predicted, axis=1)) > 0.1
    np.testing.assert_allclose(spec.camera_start, x[0] + [-0.9, 0.0, 0.35])


def test_missing_take_is_skipped_and_unknown_scene_refused(tmp_path):
    assert bench_design_joint.scene_cell("cmu131_01", frames=20, starts=1, data=tmp_path) is None
    args = argparse.Namespace(scenes="sim,walk")
    with pytest.raises(SystemExit, match="unknown scene 'walk'"):
        bench_design_joint.compare(args)


def test_limits_sweep_refuses_unknown_limits_and_scenes():
    args = argparse.Namespace(limits_sweep="1,2", swept="velocity,speed", scenes="sim")
    with pytest.raises(SystemExit, match="--swept: unknown limit 'speed'"):
        bench_design_joint.limits_sweep(args)
    args = argparse.Namespace(limits_sweep="1", swept="jerk", scenes="walk")
    with pytest.raises(SystemExit, match="unknown scene 'walk'"):
        bench_design_joint.limits_sweep(args)


def test_unknown_estimator_refused():
    args = argparse.Namespace(scenes="sim", estimators="temporal,pnp")
    with pytest.raises(SystemExit, match="unknown 'pnp'"):
        bench_design_joint.compare(args)


def test_random_camera_pose_is_the_inverse_of_its_projection():
    spec = bench_design_joint.scene_cell("sim", frames=20, starts=1)
    P, T_w_c = (np.asarray(a) for a in bench_design_joint.random_camera(spec))
    assert P.shape == (20, 3, 4) and T_w_c.shape == (20, 4, 4)
    T_c_w = np.linalg.inv(T_w_c)
    np.testing.assert_allclose(P, np.asarray(spec.K) @ T_c_w[:, :3, :], atol=1e-9)
    # the paper's camera jumps between images (why no robot can follow it)
    assert np.median(np.linalg.norm(np.diff(T_w_c[:, :3, 3], axis=0), axis=1)) > 0.2


def test_random_camera_is_mostly_out_of_reach_and_its_reachable_variant_is_reached():
    """The paper's random viewpoints lie mostly beyond the KR 16's reach in the built-in
    cell; the variant kept within reach is reached (inverse kinematics within the joint
    ranges) at most images (those where one of the 32 draws is), from the same stand-off
    band, and its jumps break the joints' speed limits."""
    from jaxtraj.design.joint_path import RobotCell
    from jaxtraj.design_command import _chain, _start_configuration

    spec = bench_design_joint.scene_cell("sim", frames=8, starts=1)
    chain = _chain(spec)
    q0 = _start_configuration(spec, chain)
    cell = RobotCell(chain, spec.T_w_base, spec.T_f_c, spec.K, standoff=spec.standoff)
    _, T_paper = bench_design_joint.random_camera(spec)
    assert bench_design_joint.joint_excess(spec, cell, q0, T_paper)[0] >= 5
    spec.times = 0.05 * spec.times  # the 8 images within 0.5 s: jumps no joint can make
    P, T_w_c, reached = (
        np.asarray(a) for a in bench_design_joint.random_reachable_camera(spec, cell, q0, 32)
    )
    assert reached.sum() >= 6, reached
    out, worst, median, acc = bench_design_joint.joint_excess(spec, cell, q0, T_w_c)
    assert out == np.sum(~reached) and worst >= median > 1.0 and acc > 1.0, (worst, median, acc)
    distance = np.linalg.norm(T_w_c[:, :3, 3] - spec.predicted, axis=1)
    assert np.all((distance >= spec.standoff[0]) & (distance <= spec.standoff[1])), distance
    np.testing.assert_allclose(P, np.asarray(spec.K) @ np.linalg.inv(T_w_c)[:, :3, :], atol=1e-9)
    assert bench_design_joint.excess_text((0, worst, median, acc), 8).startswith("no: jumps at")
    assert bench_design_joint.excess_text((0, 0.8, 0.4, 0.9), 8).startswith("reached; the jumps")

"""Joint-space camera-path design: B-spline basis, path model, constraints, optimiser."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtraj import dct_basis, depth_uncertainty, look_at
from jaxtraj.design import plausible_trajectories
from jaxtraj.design.bspline import bspline_basis, clamped_knots
from jaxtraj.design.joint_optimise import (
    STATIONARITY_TOL,
    design_joint_path,
    evaluate_joint_path,
)
from jaxtraj.design.joint_path import (
    JOINT_CONSTRAINTS,
    MAX_GRID_STEP,
    JointPathModel,
    RobotCell,
    joint_constraint_values,
)
from jaxtraj.io.urdf import load_robot
from jaxtraj.robot import camera_pose, solve_ik
from jaxtraj.sim.scene import default_intrinsics

# camera optical axis (z) out of the flange (flange x), image y down at the home pose
T_F_C = np.array([[0, 0, 1, 0.08], [-1, 0, 0, 0.0], [0, -1, 0, 0.05], [0, 0, 0, 1.0]])


@pytest.mark.parametrize("derivative", [0, 1, 2, 3])
def test_bspline_basis_equals_scipy(derivative):
    interpolate = pytest.importorskip("scipy.interpolate")
    knots = clamped_knots(0.0, 10.0, 12, 5)
    t = np.linspace(0.0, 10.0, 301)
    ours = bspline_basis(t, knots, 5, derivative)
    ref = np.stack(
        [interpolate.BSpline(knots, np.eye(12)[j], 5)(t, nu=derivative) for j in range(12)], 1
    )
    np.testing.assert_allclose(ours, ref, atol=1e-12 * max(1.0, np.abs(ref).max()))
    if derivative == 0:
        np.testing.assert_allclose(ours.sum(axis=1), 1.0, atol=1e-14)


def test_bspline_arguments_are_checked():
    with pytest.raises(ValueError, match="needs at least 6 control points"):
        clamped_knots(0.0, 1.0, 4, 5)
    with pytest.raises(ValueError, match="expected t1 > t0"):
        clamped_knots(1.0, 1.0, 8, 5)


@pytest.fixture(scope="module")
def scene():
    """KR 16-2 at the world origin, a workpiece 2 m in front moving along a smooth
    curve (0.3 x 0.3 x 0.2 m), the camera starting 1 m from it looking at it."""
    kr16 = load_robot("kr16_2")
    times = np.linspace(0.0, 10.0, 12)
    s = times / 10
    predicted = np.stack(
        [
            2.0 + 0.15 * np.sin(2 * np.pi * s),
            0.3 * np.sin(np.pi * s) - 0.15,
            0.8 + 0.1 * np.cos(np.pi * s),
        ],
        1,
    )
    c0 = predicted[0] + np.array([-0.9, 0.0, 0.35])
    R_c_w, _ = look_at(jnp.asarray(c0), jnp.asarray(predicted[0]), jnp.asarray([0.0, 0, 1]))
    T_w_c = np.eye(4)
    T_w_c[:3, :3] = np.asarray(R_c_w).T
    T_w_c[:3, 3] = c0
    q0 = solve_ik(kr16, T_w_c @ np.linalg.inv(T_F_C), np.radians([0, -90, 90, 0, 45, 0]))
    cell = RobotCell(
        kr16, np.eye(4), T_F_C, default_intrinsics(), standoff=(0.6, 1.4), keep_out_radius=0.4
    )
    samples = plausible_trajectories(jax.random.PRNGKey(1), predicted, times, 2, extent=0.03)
    return {
        "kr16": kr16,
        "times": times,
        "predicted": predicted,
        "q0": np.asarray(q0),
        "cell": cell,
        "samples": samples,
        "basis": dct_basis(times, 6),
        "T_w_c": T_w_c,
    }


def test_path_starts_at_q0_at_rest_and_fits_a_path(scene, rng):
    model = JointPathModel.create(scene["times"], scene["q0"], n_control=8, grid_per_image=5)
    theta = rng.normal(0.0, 0.1, model.shape)
    for d in range(3):
        start = np.asarray(model.joints(theta, d))[0]
        np.testing.assert_allclose(start, scene["q0"] if d == 0 else 0.0, atol=1e-12)
    assert np.abs(np.asarray(model.joints(theta, 3))[0]).max() > 1e-3  # jerk is free
    # the grid contains the image times
    q_grid = np.asarray(model.joints(theta))[::5]
    np.testing.assert_allclose(q_grid, model.joints_at_images(theta), atol=1e-12)
    np.testing.assert_allclose(model.fit(model.joints(theta)), theta, atol=1e-9)
    with pytest.raises(ValueError, match="n_control: expected >= degree"):
        JointPathModel.create(scene["times"], scene["q0"], n_control=6)
    with pytest.raises(ValueError, match="strictly increasing"):
        JointPathModel.create(scene["times"][::-1], scene["q0"])


def test_default_grid_is_at_most_max_grid_step_apart(scene):
    """The default limit grid: 10 points per image interval where the images are close,
    more where they are further apart than 10 grid steps (12 images over 10 s)."""
    for frames, per_image in ((60, 10), (12, 46), (200, 10)):
        times = np.linspace(0.0, 10.0, frames)
        assert JointPathModel.default_grid_per_image(times) == per_image
        model = JointPathModel.create(times, scene["q0"], n_control=8)
        steps = np.diff(np.asarray(model.grid))
        assert model.grid.shape == (per_image * (frames - 1) + 1,)
        assert steps.max() <= MAX_GRID_STEP + 1e-12


def test_constraint_values_against_direct_computation(scene, rng):
    model = JointPathModel.create(scene["times"], scene["q0"], n_control=8, grid_per_image=5)
    cell, kr16 = scene["cell"], scene["kr16"]
    theta = rng.normal(0.0, 0.05, model.shape)
    values = jax.jit(joint_constraint_values)(
        model, theta, cell, scene["predicted"], scene["samples"]
    )
    assert set(values) == set(JOINT_CONSTRAINTS)
    # velocity of joint j on the grid: the spline's derivative over its control points
    knots = clamped_knots(0.0, 10.0, 8, 5)
    control = np.concatenate([np.zeros((3, 6)), theta]) + scene["q0"]
    grid = np.asarray(model.grid)
    qd = np.stack([bspline_basis(grid, knots, 5, 1) @ control[:, j] for j in range(6)], 1)
    expected = (qd / np.asarray(kr16.velocity)) ** 2 - 1
    np.testing.assert_allclose(values["joint_velocity"], expected.ravel(), atol=1e-12)
    # stand-off and field of view at the images from the camera poses
    q_img = np.asarray(model.joints_at_images(theta))
    T = np.stack([np.asarray(camera_pose(kr16, q, T_F_C)) for q in q_img])
    d = np.linalg.norm(T[:, :3, 3] - scene["predicted"], axis=1)
    np.testing.assert_allclose(values["standoff"][::2], (0.6 - d) / 0.6, atol=1e-12)
    x_c = np.einsum("fji,fj->fi", T[:, :3, :3], scene["samples"][0] - T[:, :3, 3])
    angle = np.arctan2(np.linalg.norm(x_c[:, :2], axis=1), x_c[:, 2])
    np.testing.assert_allclose(values["field_of_view"][: len(d)], angle / 0.28 - 1, atol=1e-12)
    assert values["end"][0] == -1.0  # no end constraint unless asked
    assert values["depth_determined"][0] == -1.0  # nor a depth bound
    # with a depth bound (a design for estimate_points): kappa of each plausible trajectory
    bounded = dataclasses.replace(cell, max_depth_uncertainty=0.08)
    values = joint_constraint_values(model, theta, bounded, scene["predicted"], scene["samples"])
    kappa = [float(depth_uncertainty(x, T[:, :3, 3], scene["times"], 2)) for x in scene["samples"]]
    np.testing.assert_allclose(values["depth_determined"], np.array(kappa) / 0.08 - 1, rtol=1e-9)


def test_geometry_on_every_other_grid_point(scene, rng):
    """With ``geometry_stride=2`` the floor and keep-out constraints use every other grid
    point (the floor's values are the full grid's there); the joint limits keep the full
    grid; a stride that does not divide the grid's points per image is refused."""
    full = JointPathModel.create(scene["times"], scene["q0"], n_control=8, grid_per_image=4)
    half = JointPathModel.create(
        scene["times"], scene["q0"], n_control=8, grid_per_image=4, geometry_stride=2
    )
    theta = rng.normal(0.0, 0.05, full.shape)
    args = (scene["cell"], scene["predicted"], scene["samples"])
    v1 = joint_constraint_values(full, theta, *args)
    v2 = joint_constraint_values(half, theta, *args)
    G, n_heights = full.grid.shape[0], v1["floor"].size // full.grid.shape[0]
    floor1 = np.asarray(v1["floor"]).reshape(G, n_heights)[::2].ravel()
    np.testing.assert_allclose(v2["floor"], floor1, atol=1e-12)
    assert v2["keep_out"].size == 2 * ((G - 1) // 2)  # chords between every other point
    for name in ("joint_velocity", "standoff", "field_of_view"):
        np.testing.assert_allclose(v2[name], v1[name], atol=1e-12)
    with pytest.raises(ValueError, match="geometry_stride: expected a divisor of grid_per_"):
        JointPathModel.create(scene["times"], scene["q0"], grid_per_image=5, geometry_stride=2)


def test_design_converges_and_holds_on_a_10x_finer_grid(scene, rng):
    """Maximise eta under every limit: each start converges (violation below 1e-3, KKT
    stationarity below the default tolerance), the constraints hold on a grid 10x finer
    than the design's, and the expected error falls; a warm re-plan from the design
    converges too.

    The design grid has 20 points per image interval (0.045 s apart; the built-in cell's
    default grid is 0.017 s): the 1 % grid margin covers a constraint's rise between grid
    points only on a fine enough grid, and at 10 per image (0.09 s) the floor, once active,
    rose 1.3 mm (1.3 % of its 0.1 m clearance) between them."""
    times, q0 = scene["times"], scene["q0"]
    model = JointPathModel.create(times, q0, n_control=8, grid_per_image=20)
    cell, pred, samples, basis = scene["cell"], scene["predicted"], scene["samples"], scene["basis"]
    inits = jnp.asarray(np.stack([np.zeros(model.shape), rng.normal(0, 0.02, model.shape)]))
    kwargs = {"objective": "eta", "penalties": (10.0, 30.0, 100.0, 100.0, 100.0, 100.0)}
    best, designs = design_joint_path(model, cell, pred, samples, basis, inits, **kwargs)
    assert np.all(np.asarray(designs.converged))
    assert np.all(np.asarray(designs.max_violation) <= 1e-3)
    assert np.all(np.asarray(designs.stationarity) <= STATIONARITY_TOL)
    fine = JointPathModel.create(times, q0, n_control=8, grid_per_image=100)
    values = joint_constraint_values(fine, best.theta, cell, pred, samples)
    worst = {k: float(jnp.max(v)) for k, v in values.items()}
    assert max(worst.values()) <= 2e-3, worst
    assert np.any(np.asarray(best.violation) > -0.02)  # some limit is active
    eta = evaluate_joint_path(model, jnp.stack([inits[0], best.theta]), cell, pred, samples, basis)
    assert float(eta.expected_mean_error[1]) < 0.5 * float(eta.expected_mean_error[0])
    # the worst frame is at least the RMS over frames (the DCT's per-frame errors)
    assert np.all(np.asarray(eta.expected_worst_error) >= np.asarray(eta.expected_error))
    warm, _ = design_joint_path(
        model, cell, pred + 0.01, samples + 0.01, basis, jnp.stack([best.theta] * 2), **kwargs
    )
    assert bool(warm.converged)
    # each start is its own search (starts_in="auto" on a CPU): a start alone gives the
    # same design bit for bit
    _, alone = design_joint_path(model, cell, pred, samples, basis, inits[1:], **kwargs)
    np.testing.assert_array_equal(np.asarray(alone.theta[0]), np.asarray(designs.theta[1]))
    assert int(alone.evaluations[0]) == int(designs.evaluations[1])
    # started from a design and its multipliers, a start already converged stops at once
    # (no round, the design unchanged) ...
    assert np.all(np.asarray(designs.rounds) <= 6) and np.all(np.asarray(designs.rounds) >= 1)
    _, again = design_joint_path(
        model, cell, pred, samples, basis, designs.theta, multipliers=designs.multipliers, **kwargs
    )
    stopped = np.asarray(designs.rounds) < 6  # these stopped because they had converged
    np.testing.assert_array_equal(np.asarray(again.rounds)[stopped], 0)
    np.testing.assert_allclose(np.asarray(again.theta)[stopped], np.asarray(designs.theta)[stopped])
    # ... and a moved prediction costs a fraction of a design. (The round counts are not
    # ordered: rounding alone moved this re-plan between 3 and 4 rounds against the
    # design's 3 and the re-plan without multipliers' 3; in evaluations the re-plan took
    # 135-255 against the design's 1173-1344 on an Intel Xeon, jax 0.10.2.)
    warm2, replanned = design_joint_path(
        model,
        cell,
        pred + 0.01,
        samples + 0.01,
        basis,
        designs.theta,
        multipliers=designs.multipliers,
        **kwargs,
    )
    assert bool(warm2.converged)
    assert int(warm2.evaluations) < 0.5 * int(np.min(np.asarray(designs.evaluations)))
    # the search counts its evaluations (at least one per round) and returns its inverse
    # Hessian; the identity passed explicitly is the default, and the re-plan started from
    # the design's inverse Hessian converges too
    assert np.all(np.asarray(designs.evaluations) > np.asarray(designs.rounds))
    n = int(np.prod(model.shape))
    assert designs.inverse_hessian.shape == (2, n, n)
    replan = (model, cell, pred + 0.01, samples + 0.01, basis, designs.theta)
    eye = jnp.broadcast_to(jnp.eye(n), (2, n, n))
    _, same = design_joint_path(
        *replan, multipliers=designs.multipliers, inverse_hessian=eye, **kwargs
    )
    np.testing.assert_array_equal(np.asarray(same.theta), np.asarray(replanned.theta))
    warm3, _ = design_joint_path(
        *replan,
        multipliers=designs.multipliers,
        inverse_hessian=designs.inverse_hessian,
        **kwargs,
    )
    assert bool(warm3.converged)
    with pytest.raises(ValueError, match=r"inverse_hessian: expected shape \(2, "):
        design_joint_path(*replan, inverse_hessian=jnp.zeros((2, 3, 3)), **kwargs)
    with pytest.raises(ValueError, match=r"multipliers: expected shape \(2, "):
        design_joint_path(model, cell, pred, samples, basis, inits, multipliers=jnp.zeros(3))
    with pytest.raises(ValueError, match=r"inits: expected shape \(B, 5, 6\)"):
        design_joint_path(model, cell, pred, samples, basis, inits[:, :2], **kwargs)
    with pytest.raises(ValueError, match="objective: expected one of"):
        design_joint_path(model, cell, pred, samples, basis, inits, objective="speed")


def test_design_program_evaluates_objective_and_constraints_at_one_place(scene, monkeypatch):
    """The solver's loop evaluates the Lagrangian at exactly one place, so the compiled
    design program holds the objective and the constraints once (a solver that traces
    them at several places compiled twice as long; see ``joint_optimise._design``)."""
    from jaxtraj.design import joint_optimise as jo

    model = JointPathModel.create(scene["times"], scene["q0"], n_control=8, grid_per_image=5)
    inits = jnp.zeros((2, *model.shape))
    problem = jo._problem(
        "mean_error",
        model,
        scene["cell"],
        scene["predicted"],
        scene["samples"],
        scene["basis"],
        0.3,
        inits.dtype,
    )
    lams = jnp.zeros((2, jax.eval_shape(problem.constraints, inits[0]).shape[0]))
    traced = {"objective": 0, "constraints": 0}
    for name in traced:
        original = getattr(jo._Problem, name)

        def counted(self, theta, *held, original=original, name=name):
            traced[name] += 1
            return original(self, theta, *held)

        monkeypatch.setattr(jo._Problem, name, counted)
    rhos = jnp.ones(3)
    H0s = jnp.broadcast_to(jnp.eye(inits[0].size), (2, inits[0].size, inits[0].size))
    jax.eval_shape(lambda: jo._design(inits, lams, H0s, problem, rhos, 10, 1e-9, 1e-3, 1e-3))
    assert traced == {"objective": 1, "constraints": 1}


def test_starts_run_as_one_search_each_on_threads_or_as_one_vectorised_search(monkeypatch):
    """``starts_in``: "threads" runs one single-start search per start and stacks them in
    the starts' order, "vmap" one search of all starts, "auto" threads on a CPU only."""
    from jaxtraj.design import joint_optimise as jo

    calls = []

    def fake(inits, lams, H0s, *args):
        calls.append(inits.shape[0])
        # the caller's thread-local settings hold in the threads too
        assert jnp.asarray(1.0).dtype == jnp.float32
        return inits[:, 0, 0] * 10, (lams, H0s[:, 0])

    monkeypatch.setattr(jo, "_design", fake)
    f32 = np.float32
    inits = np.arange(5, dtype=f32)[:, None, None] * np.ones((5, 2, 3), f32)
    lams, H0s = np.zeros((5, 4), f32), np.ones((5, 6, 6), f32)
    for mode, sizes in (("threads", [1] * 5), ("vmap", [5]), ("auto", [1] * 5)):
        calls.clear()
        with jax.enable_x64(False):  # the suite runs with float64 enabled globally
            out, (lam, H) = jo._run_starts(mode, inits, lams, H0s, "problem")
        assert calls == sizes, mode
        np.testing.assert_array_equal(out, 10 * np.arange(5.0))
        assert lam.shape == (5, 4) and H.shape == (5, 6)
    monkeypatch.setattr(jo, "platform_of", lambda x: "gpu")
    calls.clear()
    with jax.enable_x64(False):
        jo._run_starts("auto", inits, lams, H0s, "problem")
    assert calls == [5]
    with pytest.raises(ValueError, match="starts_in: expected one of"):
        design_joint_path(None, None, None, None, None, inits, starts_in="pool")


def test_design_report_from_the_search_equals_an_independent_evaluation(scene, rng):
    """The designs' errors and constraint values come from the search's last accepted
    evaluation (no second program); they equal evaluate_joint_path of the same paths."""
    model = JointPathModel.create(scene["times"], scene["q0"], n_control=8, grid_per_image=2)
    cell, data = scene["cell"], (scene["predicted"], scene["samples"], scene["basis"])
    inits = jnp.asarray(np.stack([np.zeros(model.shape), rng.normal(0, 0.02, model.shape)]))
    _, designs = design_joint_path(model, cell, *data, inits, penalties=(10.0, 30.0), inner_steps=5)
    again = evaluate_joint_path(model, designs.theta, cell, *data)
    for name in ("expected_error", "expected_mean_error", "expected_worst_error"):
        np.testing.assert_allclose(getattr(designs, name), getattr(again, name), rtol=1e-12)
    np.testing.assert_allclose(designs.violation, again.violation, rtol=0, atol=1e-12)
    np.testing.assert_allclose(designs.max_violation, again.max_violation, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(designs.feasible, again.feasible)
    assert np.all(np.isfinite(np.asarray(designs.expected_worst_error)))


def test_design_ends_where_the_objective_is_not_finite(scene, monkeypatch):
    """A start whose objective is NaN everywhere ends (every line search fails, round
    after round) and is reported as not converged with its parameters unchanged, instead
    of looping."""
    from jaxtraj.design import joint_optimise as jo

    monkeypatch.setattr(
        jo._Problem,
        "objective",
        lambda self, theta, held: (jnp.nan * jnp.sum(theta), jnp.zeros(3), held[0]),
    )
    model = JointPathModel.create(scene["times"], scene["q0"], n_control=8, grid_per_image=2)
    inits = jnp.zeros((1, *model.shape))
    best, designs = design_joint_path(
        model,
        scene["cell"],
        scene["predicted"],
        scene["samples"],
        scene["basis"],
        inits,
        objective="eta",
        penalties=(10.0, 30.0),
    )
    assert not bool(designs.converged[0])
    assert int(designs.rounds[0]) == 2
    np.testing.assert_array_equal(np.asarray(best.theta), np.zeros(model.shape))


def test_pose_estimator_evaluates_pnp_error_and_keeps_every_reference_point_in_view(scene, rng):
    from jaxtraj.design import expected_pose_errors_for_cameras, pose_point_covariances
    from jaxtraj.design.joint_optimise import visible_points
    from jaxtraj.design.joint_path import camera_poses, projection_matrices

    model = JointPathModel.create(scene["times"], scene["q0"], n_control=8, grid_per_image=5)
    thetas = rng.normal(0.0, 0.02, (2, *model.shape))
    layout = np.array([[-0.1, -0.1, 0], [0.1, -0.1, 0], [0.1, 0.1, 0], [-0.1, 0.1, 0.05]])
    point, R_w_o = np.array([0.02, 0.0, 0.0]), np.asarray(look_at([0, 0, 0.0], [-1, 0, 0.3])[0]).T
    args = (model, thetas, scene["cell"], scene["predicted"], scene["samples"], scene["basis"])
    pose = evaluate_joint_path(*args, estimator="pose", layout=(layout, point, R_w_o))
    for b in range(2):
        P = projection_matrices(
            scene["cell"], camera_poses(scene["cell"], model.joints_at_images(thetas[b]))
        )
        rms, mean = expected_pose_errors_for_cameras(P, scene["samples"], R_w_o, layout, point, 0.3)
        np.testing.assert_allclose(
            [pose.expected_error[b], pose.expected_mean_error[b]], [rms, mean], rtol=1e-10
        )
        # the field of view covers every reference point along every sample (S * M points)
        visible = visible_points(scene["samples"], (layout, point, R_w_o))
        assert visible.shape == (4 * len(scene["samples"]), *scene["samples"].shape[1:])
        np.testing.assert_allclose(visible[1], scene["samples"][0] + (layout[1] - point) @ R_w_o.T)
        fov = joint_constraint_values(model, thetas[b], scene["cell"], scene["predicted"], visible)
        i = JOINT_CONSTRAINTS.index("field_of_view")
        np.testing.assert_allclose(pose.violation[b, i], jnp.max(fov["field_of_view"]), rtol=1e-12)
        # the worst frame: the largest per-frame RMS over samples and frames
        e2 = [
            np.trace(
                np.asarray(
                    pose_point_covariances(
                        P, np.repeat(R_w_o[None], len(P), 0), x - R_w_o @ point, layout, point, 0.3
                    )
                ),
                axis1=1,
                axis2=2,
            )
            for x in np.asarray(scene["samples"])
        ]
        np.testing.assert_allclose(pose.expected_worst_error[b], np.sqrt(np.max(e2)), rtol=1e-10)
        assert pose.expected_worst_error[b] > pose.expected_error[b]
    with pytest.raises(ValueError, match=r"the 'pose' estimator needs the object's layout"):
        evaluate_joint_path(*args, estimator="pose")
    with pytest.raises(ValueError, match=r"layout: expected \(M, 3\) reference points"):
        evaluate_joint_path(*args, estimator="pose", layout=(layout[:3], point, R_w_o))


def test_keep_out_sees_a_pass_between_grid_points():
    from jaxtraj.design.joint_path import _swept_distance

    # relative position passing 0.1 m from the workpiece between two grid points 2 m apart
    r = jnp.array([[-1.0, 0.1, 0.0], [1.0, 0.1, 0.0], [1.0, 0.5, 0.0], [1.0, 0.5, 0.0]])
    np.testing.assert_allclose(_swept_distance(r), [0.1, np.hypot(1.0, 0.1), np.hypot(1, 0.5)])
    g = jax.grad(lambda r: jnp.sum(_swept_distance(r)))(r)
    assert np.all(np.isfinite(np.asarray(g)))  # a zero-length chord (last one) included


def test_smoother_evaluation_reports_its_worst_frame(scene, rng):
    from jaxtraj.design import expected_smoother_errors_for_cameras, smoother_error_terms
    from jaxtraj.design.joint_path import camera_poses, projection_matrices

    model = JointPathModel.create(scene["times"], scene["q0"], n_control=8, grid_per_image=5)
    theta = rng.normal(0.0, 0.05, model.shape)
    args = (model, theta[None], scene["cell"], scene["predicted"], scene["samples"])
    ev = evaluate_joint_path(*args, scene["basis"], estimator="smoother2")
    cell = scene["cell"]
    P = projection_matrices(cell, camera_poses(cell, model.joints_at_images(theta)))
    rms, mean = expected_smoother_errors_for_cameras(P, scene["samples"], scene["times"])
    np.testing.assert_allclose([ev.expected_error[0], ev.expected_mean_error[0]], [rms, mean])
    e2 = [sum(smoother_error_terms(P, x, scene["times"])[:2]) for x in scene["samples"]]
    np.testing.assert_allclose(ev.expected_worst_error[0], np.sqrt(np.max(e2)), rtol=1e-8)
    assert ev.expected_worst_error[0] > ev.expected_error[0]

"""Optimise a joint-space camera path: the expected reconstruction error under the robot's
and the cell's limits.

Augmented Lagrangian (Powell-Hestenes-Rockafellar for inequalities): with multipliers
``lambda >= 0`` and penalty ``rho``,

    L(theta) = f(theta) + 1 / (2 rho) sum_i (max(0, lambda_i + rho g_i(theta))^2 - lambda_i^2),

each outer round minimises ``L`` by BFGS from where the last round ended and then updates
``lambda <- max(0, lambda + rho g)``. Unlike a pure penalty, the multipliers let the
constraints hold with a finite ``rho`` and give a first-order (KKT) stationarity measure,
``||grad f + sum_i lambda_i grad g_i||_inf``, reported with the largest constraint
violation; a design is converged when both are below their tolerances, which is tested
after every accepted step (see :func:`_design`). Several starts run at once (on a CPU one
search per start, shared by threads; elsewhere one vectorised search, see
:func:`_run_starts`); the best feasible is reported.

The BFGS is written here rather than taken from optimistix for two measured reasons (the
built-in cell, DCT objective, F = 60, 8 starts, 2 cores): a loop with one evaluation of
the Lagrangian per pass compiles in half the time (XLA program 2.5 -> 0.7 MB, trace and
compilation 19 -> 9 s), and stopping on the KKT test as soon as it holds, instead of on a
relative change of ``L`` that the penalty's kinks keep from ever being met, with the
penalty raised late (10, 10, 10, 30, 30, 100, ...), lets every start converge (0 of 8
before, each round taking its 500 steps).
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._batching import cpu_cores, in_threads, platform_of
from ..analysis import reconstructibility
from .joint_path import (
    JOINT_CONSTRAINTS,
    JointPathModel,
    RobotCell,
    camera_poses,
    joint_constraint_values,
    projection_matrices,
)
from .objectives import _metrics, _sample_errors
from .pose_error import _checked_layout, _pose_metrics, _sample_covariances
from .smoother_error import frame_errors2_held as _smoother_frame_errors2

__all__ = [
    "JointPathDesign",
    "design_joint_path",
    "evaluate_joint_path",
    "visible_points",
]

JOINT_OBJECTIVES = ("mean_error", "error", "eta")
#: estimators a path can be designed for: the DCT of the paper (basis ``basis``), the
#: smoothness-prior smoother of :func:`jaxtraj.estimate_points` (order 1 or 2) and the
#: known-layout pose (per-image PnP of the object's reference points)
ESTIMATORS = ("dct", "smoother1", "smoother2", "pose")


class JointPathDesign(eqx.Module):
    """A designed (or evaluated) joint-space camera path.

    Attributes:
        theta: (p, n) path parameters (see :class:`~jaxtraj.design.JointPathModel`).
        expected_error: expected RMS error of the reconstruction [m] (the estimator the
            path is designed for: the DCT or the smoothness-prior smoother).
        expected_mean_error: expected mean Euclidean error (Jensen bound) [m].
        expected_worst_error: the largest expected error of one frame, over the frames and
            the plausible trajectories [m] (the mean may hide a poor frame, e.g. at an end;
            ``jaxtraj reconstruct`` flags a track whose worst frame's std exceeds 10 mm).
        violation: (C,) largest normalised value per constraint, in the order of
            :data:`~jaxtraj.design.joint_path.JOINT_CONSTRAINTS` (<= 0: satisfied).
        max_violation: ``max(0, violation)`` over all constraints.
        stationarity: ``||grad f + sum lambda_i grad g_i||_inf`` at ``theta`` (f the log
            of the objective); nan for an evaluated (not designed) path.
        converged: ``max_violation <= feasibility_tol`` and ``stationarity <=
            stationarity_tol``.
        feasible: ``max_violation <= feasibility_tol`` and a finite expected error.
        multipliers: (G,) the augmented Lagrangian's multipliers, one per constraint value
            (zeros for an evaluated path); pass them back with the design for a warm
            re-plan (``design_joint_path(..., multipliers=)``).
        rounds: augmented-Lagrangian rounds used (each start stops when it is converged).
        evaluations: evaluations of the Lagrangian's value and gradient the search made
            (0 for an evaluated path).
        inverse_hessian: (p n, p n) the search's last BFGS estimate of the inverse Hessian
            of the Lagrangian in the flattened parameters (the identity for an evaluated
            path); pass it back for a warm re-plan (``design_joint_path(...,
            inverse_hessian=)``), whose first round then starts from it.
    """

    theta: Float[Array, "p n"]
    expected_error: Float[Array, ""]
    expected_mean_error: Float[Array, ""]
    expected_worst_error: Float[Array, ""]
    violation: Float[Array, " C"]
    max_violation: Float[Array, ""]
    stationarity: Float[Array, ""]
    converged: Bool[Array, ""]
    feasible: Bool[Array, ""]
    multipliers: Float[Array, " G"]
    rounds: Int[Array, ""]
    evaluations: Int[Array, ""]
    inverse_hessian: Float[Array, "n n"]

    def report(self) -> dict:
        """Per constraint: largest value, active (within 0.02), satisfied (host side)."""
        return {
            name: {
                "max_value": float(self.violation[i]),
                "active": bool(abs(float(self.violation[i])) <= 0.02),
                "satisfied": bool(self.violation[i] <= 1e-3),
            }
            for i, name in enumerate(JOINT_CONSTRAINTS)
        }


class _Problem(eqx.Module):
    kind: str = eqx.field(static=True)
    estimator: str = eqx.field(static=True)
    model: JointPathModel
    cell: RobotCell
    predicted: Array
    samples: Array
    basis: Array
    pixel_sigma: Array
    margin: Array
    layout: Array  # (M, 3) reference points of the object (pose estimator only)
    point: Array  # (3,) the object point the samples follow (pose estimator only)
    R_w_o: Array  # (3, 3) the object's orientation (pose estimator only)
    visible: Array  # (V, F, 3) points kept in the field of view (see visible_points)

    def _cameras(self, theta):
        T_w_c = camera_poses(self.cell, self.model.joints_at_images(theta))
        return projection_matrices(self.cell, T_w_c)

    def _frame_terms(self, theta, held=None):
        """Per sample and frame: expected squared errors (S, F), or for the pose estimator
        the point covariances (S, F, 3, 3); and the (S,) smoother's noise densities
        (``held = (densities, hold)``: where ``hold``, those densities instead of a search;
        see :func:`jaxtraj.design.smoother_error.frame_errors2_held`; zeros for the other
        estimators)."""
        P = self._cameras(theta)
        noq = jnp.zeros(self.samples.shape[0], P.dtype)
        if self.estimator == "dct":
            return _sample_errors(P, self.samples, self.basis, self.pixel_sigma), noq
        if self.estimator == "pose":
            covs = _sample_covariances(
                P, self.samples, self.R_w_o, self.layout, self.point, self.pixel_sigma
            )
            return covs, noq
        order = int(self.estimator[-1])
        times = self.model.times
        return _smoother_frame_errors2(P, self.samples, times, self.pixel_sigma, order, held)

    def _errors_from(self, terms):
        """``(rms, mean, worst)`` [m] of the frame terms: the worst is
        ``max sqrt(E|x_hat - x|^2)`` over the samples and frames (reported, not designed
        for)."""
        e2 = jnp.trace(terms, axis1=-2, axis2=-1) if self.estimator == "pose" else terms
        worst = jnp.sqrt(jnp.max(jnp.where(jnp.isnan(e2), jnp.inf, e2)))
        rms, mean = _pose_metrics(terms) if self.estimator == "pose" else _metrics(terms)
        return rms, mean, worst

    def report_errors(self, theta):
        """``(rms, mean, worst)`` [m] (see :meth:`_errors_from`); one evaluation of the
        frames."""
        return self._errors_from(self._frame_terms(theta)[0])

    def objective(self, theta, held):
        """The objective (minimised), the (3,) expected errors ``(rms, mean, worst)`` [m]
        of :meth:`report_errors` from the same evaluation of the frames, so that the
        design's report needs no second program (NaN for ``eta``, which does not compute
        them: its report comes from :func:`_evaluate`), and the smoother's densities for
        the next evaluation (see :meth:`_frame_terms`)."""
        if self.kind == "eta":  # maximise the geometric mean of eta over the samples
            c = camera_poses(self.cell, self.model.joints_at_images(theta))[:, :3, 3]
            etas = jax.vmap(lambda x: reconstructibility(c, x, self.basis))(self.samples)
            return -jnp.mean(jnp.log(etas)), jnp.full(3, jnp.nan, theta.dtype), held[0]
        terms, qs = self._frame_terms(theta, held)
        rms, mean, worst = self._errors_from(terms)
        value = jnp.log(mean if self.kind == "mean_error" else rms)
        return value, jnp.stack([rms, mean, worst]), qs

    def constraint_values(self, theta):
        """The unmargined values per constraint (see :func:`joint_constraint_values`)."""
        return joint_constraint_values(self.model, theta, self.cell, self.predicted, self.visible)

    def constraints(self, theta):
        values = self.constraint_values(theta)
        return jnp.concatenate([values[name] for name in JOINT_CONSTRAINTS]) + self.margin


#: Armijo's sufficient-decrease fraction of the BFGS line search
ARMIJO = 0.1
#: penalty of every round of a warm re-plan (from the last design, its multipliers and
#: inverse Hessian): over 12 random 10 mm moves of the built-in cell's prediction, the
#: median re-plan of one start took 0.86 / 0.11 / 0.69 s (DCT / pose / smoother2) with 30
#: against 1.95 / 0.24 / 0.84 s with the design's last penalty, 100 (README, issue 21)
REPLAN_PENALTY = 30.0
#: penalty of the first evaluation of a design, which tests the given start and
#: multipliers: there ``grad L = grad f + sum_i max(0, lambda_i + rho g_i) grad g_i`` is
#: ``grad f + sum_i lambda_i grad g_i`` to within ``rho |g|``
RHO_CHECK = 1e-8
#: largest change of one parameter (a joint's control point) in one step [rad]: the first
#: step of a round follows the raw gradient, which can be huge where the objective is
#: near a singularity (eta -> 0 for a camera that does not move)
MAX_STEP = 0.2
#: default KKT stationarity tolerance, ``||grad f + sum_i lambda_i grad g_i||_inf`` with
#: ``f`` the log of the objective and the parameters in radians: moving any control point
#: by 0.01 rad then changes the objective by at most 0.01 % to first order. Measured on
#: the built-in cell (DCT, F = 60, 8 starts): the best design's expected error is 6.426 mm
#: at this tolerance and 6.419 mm at 1e-3 (0.1 %, far below the error model's 15 %), while
#: a warm re-plan of one start takes 0.4 s instead of 3-4 s (the last 1e-2 -> 1e-3 costs
#: most of the BFGS steps on the penalty's kinks).
STATIONARITY_TOL = 1e-2
_CHECK, _ROUND, _SEARCH = 0, 1, 2  # what an evaluation of the solver's loop is for


class _Search(NamedTuple):
    """State of one start's search (see :func:`_design`)."""

    phase: Int[Array, ""]  # _CHECK, _ROUND (first evaluation of a round) or _SEARCH
    i: Int[Array, ""]  # the round
    k: Int[Array, ""]  # accepted BFGS steps in this round
    x: Float[Array, " n"]  # the accepted point, flattened
    f: Float[Array, ""]  # the Lagrangian there (this round's multipliers and penalty)
    g: Float[Array, " n"]  # its gradient
    c: Float[Array, " G"]  # the constraint values there
    err: Float[Array, " 3"]  # the expected errors there (see _Problem.objective)
    qs: Float[Array, " S"]  # the smoother's densities of this round (see _design)
    H: Float[Array, "n n"]  # inverse Hessian estimate
    p: Float[Array, " n"]  # search direction
    alpha: Float[Array, ""]  # step along p tried next
    lam: Float[Array, " G"]  # this round's multipliers
    lam_out: Float[Array, " G"]  # the multipliers reported
    rounds: Int[Array, ""]
    evaluations: Int[Array, ""]  # of the Lagrangian's value and gradient
    done: Bool[Array, ""]


def _lagrangian(x, lam, rho, problem, shape, held):
    """Augmented Lagrangian of the flattened parameters, and (the constraint values, the
    expected errors, the smoother's densities; ``held`` as for :meth:`_Problem.objective`)."""
    theta = x.reshape(shape)
    g = problem.constraints(theta)
    shifted = jnp.maximum(lam + rho * g, 0.0)
    f, err, qs = problem.objective(theta, held)
    return f + jnp.sum(shifted**2 - lam**2) / (2 * rho), (g, err, qs)


@eqx.filter_jit
def _design(
    inits, lams, H0s, problem: _Problem, rhos, inner_steps, rtol, feasibility_tol, stat_tol
):
    """ALM rounds from each start until its design is converged or the rounds run out.

    Each round minimises the augmented Lagrangian by BFGS (inverse Hessian from the
    identity, or in the first round from the start's ``H0s``; backtracking line search
    with Armijo's test, the step shrunk to the minimum of the quadratic through the last
    trial). The whole search of one start is one loop
    with exactly one evaluation of the Lagrangian's value and gradient per pass (the
    first test of the start, a round's first point, or a line-search trial), so the
    compiled program holds the objective and the constraints once: about a quarter of the
    program, and half the trace and compilation time, of a solver that traces them at
    several places. Every pass either accepts a step or at least halves the trial step, so
    each round ends after finitely many passes, also where the Lagrangian is not finite.

    The smoother's objective (``estimator="smoother1"/"smoother2"``) chooses each plausible
    trajectory's noise density at the start's check and at each round's first point, and
    holds it through the round's line-search trials (its gradient treats the density as
    fixed anyway, so each round now minimises one smooth function): the density search
    was half of an evaluation's cost, and on the built-in cell the design took 28.2-28.3 s
    instead of 37.0 s with 10639 evaluations instead of 12818, every start converged
    (README). The expected errors reported are those of the last accepted point with its
    round's densities (equal to a fresh choice to 4 digits on the built-in cell).

    After every accepted point the KKT conditions are tested with the multiplier estimate
    ``max(0, lambda + rho g)``: the gradient of the Lagrangian is then exactly
    ``grad f + sum_i lambda_i grad g_i``; the start stops as soon as it and the largest
    violation are within their tolerances. A round ends when its Lagrangian is stationary
    (gradient within ``stat_tol``) while a constraint is violated, when its step and
    change fall below ``rtol``, when the line search fails, or after ``inner_steps``
    accepted steps; the multipliers are then updated to ``max(0, lambda + rho g)``.
    """
    shape = inits.shape[1:]
    n_rounds = rhos.shape[0]
    dtype = inits.dtype
    n = int(np.prod(shape))
    eye = jnp.eye(n, dtype=dtype)
    value_grad = jax.value_and_grad(_lagrangian, has_aux=True)
    # where each constraint's values lie in the flat vector
    bounds = list(itertools.pairwise(np.cumsum((0, *_constraint_sizes(problem, inits[0])))))

    def step(s: _Search, H0) -> _Search:
        search = s.phase == _SEARCH
        rho = jnp.where(s.phase == _CHECK, jnp.asarray(RHO_CHECK, dtype), rhos[s.i])
        xt = jnp.where(search, s.x + s.alpha * s.p, s.x)
        (ft, (ct, et, qt)), gt = value_grad(xt, s.lam, rho, problem, shape, (s.qs, search))
        finite = jnp.isfinite(ft) & jnp.all(jnp.isfinite(gt))
        slope = s.g @ s.p
        armijo = search & finite & (ft <= s.f + ARMIJO * s.alpha * slope)
        accept = ~search | armijo
        # BFGS update of the inverse Hessian with the accepted step (a round restarts it)
        sv, yv = xt - s.x, gt - s.g
        sy = sv @ yv
        update = armijo & (sy > jnp.finfo(dtype).eps)
        r = 1.0 / jnp.where(update, sy, 1.0)
        V = eye - r * jnp.outer(sv, yv)
        H = jnp.where(update, V @ s.H @ V.T + r * jnp.outer(sv, sv), s.H)
        H = jnp.where(s.phase == _ROUND, jnp.where(s.i == 0, H0, eye), H)
        x = jnp.where(accept, xt, s.x)
        f = jnp.where(accept, ft, s.f)
        g = jnp.where(accept, gt, s.g)
        c = jnp.where(accept, ct, s.c)
        err = jnp.where(accept, et, s.err)
        p = -H @ g
        descent = g @ p < 0
        H = jnp.where(descent, H, eye)
        p = jnp.where(descent, p, -g)
        # a rejected trial: the minimiser of the quadratic through f, the slope and f(alpha)
        curv = ft - s.f - slope * s.alpha
        shrunk = -slope * s.alpha**2 / (2.0 * jnp.where(curv > 0, curv, 1.0))
        shrunk = jnp.where(finite & (curv > 0), shrunk, 0.5 * s.alpha)
        # a new direction: the full step, at most MAX_STEP per parameter
        longest = jnp.max(jnp.abs(p))
        full = jnp.minimum(1.0, MAX_STEP / jnp.where(longest > 0, longest, 1.0))
        alpha = jnp.where(accept, full, jnp.clip(shrunk, 0.1 * s.alpha, 0.5 * s.alpha))
        k = s.k + armijo.astype(jnp.int32)
        # KKT test at the accepted point, multipliers max(0, lambda + rho g)
        stat = jnp.max(jnp.abs(g))
        viol = jnp.maximum(jnp.max(c), 0.0)
        lam_hat = jnp.maximum(s.lam + rho * c, 0.0)
        kkt = accept & (viol <= feasibility_tol) & (stat <= stat_tol)
        small = (
            armijo
            & (jnp.abs(ft - s.f) <= rtol * jnp.abs(ft) + 1e-2 * rtol)
            & (jnp.max(jnp.abs(sv)) <= rtol * jnp.max(jnp.abs(xt)) + 1e-2 * rtol)
        )
        # the line search has failed when the trial step has become negligible, or is not
        # a number (a start whose Lagrangian is not finite): written so that NaN fails
        failed = search & ~armijo & ~(s.alpha * jnp.max(jnp.abs(s.p)) >= 1e-12)
        stationary = accept & (stat <= stat_tol)
        end = (s.phase != _CHECK) & ~kkt & (stationary | small | failed | (k >= inner_steps))
        last = end & (s.i + 1 >= n_rounds)
        # rounds used: those whose search took a step (none if the start was converged)
        used = s.i + jnp.where(k > 0, 1, 0)
        return _Search(
            phase=jnp.where(end | (s.phase == _CHECK), _ROUND, _SEARCH).astype(jnp.int32),
            i=s.i + (end & ~last).astype(jnp.int32),
            k=jnp.where(end, 0, k),
            x=x,
            f=f,
            g=g,
            c=c,
            err=err,
            qs=qt,
            H=H,
            p=p,
            alpha=alpha,
            lam=jnp.where(end & ~last, lam_hat, s.lam),
            lam_out=jnp.where(kkt | last, lam_hat, s.lam_out),
            rounds=jnp.where(kkt, used, jnp.where(last, n_rounds, s.rounds)),
            evaluations=s.evaluations + 1,
            done=kkt | last,
        )

    def one(theta0, lam0, H0):
        x0 = theta0.reshape(-1)
        zero = jnp.zeros((), dtype)
        start = _Search(
            phase=jnp.asarray(_CHECK, jnp.int32),
            i=jnp.zeros((), jnp.int32),
            k=jnp.zeros((), jnp.int32),
            x=x0,
            f=zero,
            g=jnp.zeros(n, dtype),
            c=jnp.zeros_like(lam0),
            err=jnp.zeros(3, dtype),
            qs=jnp.ones(problem.samples.shape[0], dtype),
            H=eye,
            p=jnp.zeros(n, dtype),
            alpha=jnp.ones((), dtype),
            lam=lam0,
            lam_out=lam0,
            rounds=jnp.zeros((), jnp.int32),
            evaluations=jnp.zeros((), jnp.int32),
            done=jnp.zeros((), bool),
        )
        s = jax.lax.while_loop(lambda s: ~s.done, lambda s: step(s, H0), start)
        values = s.c - problem.margin  # the reports use the unmargined values
        viol = jnp.stack([jnp.max(values[a:b]) for a, b in bounds])
        search = (s.rounds, s.evaluations, s.H)
        return s.x.reshape(shape), s.lam_out, jnp.max(jnp.abs(s.g)), search, viol, s.err

    if inits.shape[0] == 1:  # one start (a thread's, or a re-plan): no batched loop
        return jax.tree_util.tree_map(lambda a: a[None], one(inits[0], lams[0], H0s[0]))
    return jax.vmap(one)(inits, lams, H0s)


#: how :func:`design_joint_path` runs its starts (``starts_in=``)
STARTS_IN = ("auto", "vmap", "threads")


def _run_starts(starts_in, inits, lams, H0s, *args):
    """:func:`_design` over the starts: one vectorised search (``"vmap"``), or one
    single-start search per start on a pool of threads, one per core (``"threads"``).

    In a vectorised search every start computes until the slowest has converged (on the
    built-in cell, DCT, 8 starts: 4116 evaluations for the slowest, 1144-2956 for the
    others), and on a CPU a start's evaluation costs as much alone as in the batch (1.95
    against 1.93 ms per start and evaluation), so the vectorised search does the slowest
    start's work eight times. One search per start does each start's own work, and the
    cores share it: 77.2 -> 28.1 s with compilation on 2 cores, pose 42.2 -> 33.2 s,
    smoother2 117.6 -> 72.2 s (README, issue 21).
    JAX compiles the program once (the other threads wait for it); a start's result does
    not depend on the number of threads or their order.
    """
    if starts_in == "auto":
        starts_in = "threads" if platform_of(inits) == "cpu" else "vmap"
    B = inits.shape[0]
    if starts_in == "vmap" or B == 1:
        return _design(inits, lams, H0s, *args)

    def one(i):
        return _design(inits[i : i + 1], lams[i : i + 1], H0s[i : i + 1], *args)

    searches = in_threads(one, list(range(B)), cpu_cores())
    return jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *searches)


def _judged(theta, viol, errors, stat, lam, search, feasibility_tol, stationarity_tol):
    """One :class:`JointPathDesign` from its largest value per constraint ``viol``, its
    expected errors ``(rms, mean, worst)`` and its search's ``(rounds, evaluations,
    inverse Hessian)``."""
    rounds, evaluations, H = search
    worst = jnp.maximum(jnp.max(viol), 0.0)
    feasible = (worst <= feasibility_tol) & jnp.isfinite(errors[0])
    return JointPathDesign(
        theta=theta,
        expected_error=errors[0],
        expected_mean_error=errors[1],
        expected_worst_error=errors[2],
        violation=viol,
        max_violation=worst,
        stationarity=stat,
        converged=feasible & (stat <= stationarity_tol),
        feasible=feasible,
        multipliers=lam,
        rounds=rounds,
        evaluations=evaluations,
        inverse_hessian=H,
    )


@eqx.filter_jit
def _evaluate(thetas, stationarity, lams, search, problem, feasibility_tol, stationarity_tol):
    def one(theta, stat, lam, search):
        values = problem.constraint_values(theta)
        viol = jnp.stack([jnp.max(values[name]) for name in JOINT_CONSTRAINTS])
        errors = jnp.stack(problem.report_errors(theta))
        return _judged(theta, viol, errors, stat, lam, search, feasibility_tol, stationarity_tol)

    return jax.vmap(one)(thetas, stationarity, lams, search)


@eqx.filter_jit
def _reported(thetas, stationarity, lams, search, viol, errors, tols):
    """The designs from what the search's last accepted evaluation computed: the largest
    (unmargined) value per constraint and the expected errors. A separate program for the
    report (:func:`_evaluate`) took 6 s of tracing and compilation on the built-in cell, a
    sixth of the whole design."""

    def judge(*args):
        return _judged(*args, *tols)

    return jax.vmap(judge)(thetas, viol, errors, stationarity, lams, search)


@eqx.filter_jit
def _constraint_values_of(problem, theta):
    return problem.constraint_values(theta)


def _constraint_sizes(problem, theta) -> tuple[int, ...]:
    """Number of values of each constraint, in :data:`JOINT_CONSTRAINTS` order (their
    shapes only). Through a module-level jit, so that a problem of the same shapes is not
    traced again: tracing the constraints took 0.4 s, most of a warm re-plan's time."""
    shapes = jax.eval_shape(_constraint_values_of, problem, theta)
    return tuple(shapes[name].size for name in JOINT_CONSTRAINTS)


def _problem(
    objective,
    model,
    cell,
    predicted,
    samples,
    basis,
    pixel_sigma,
    dtype,
    margin=0.0,
    estimator="dct",
    layout=None,
):
    if objective not in JOINT_OBJECTIVES:
        raise ValueError(f"objective: expected one of {JOINT_OBJECTIVES}, got {objective!r}")
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator: expected one of {ESTIMATORS}, got {estimator!r}")
    if (estimator == "pose") != (layout is not None):
        raise ValueError(
            "layout: the 'pose' estimator needs the object's layout (layout, point, R_w_o), "
            "and the other estimators take none"
        )
    samples = jnp.asarray(samples, dtype)
    pose = layout is not None
    if layout is None:
        layout = (jnp.zeros((4, 3)), jnp.zeros(3), jnp.eye(3))
    points, point, R_w_o = (jnp.asarray(a, dtype) for a in layout)
    points = _checked_layout(points, dtype)
    if point.shape != (3,) or R_w_o.shape != (3, 3):
        raise ValueError(
            f"layout: expected point (3,) and R_w_o (3, 3), got {point.shape} and {R_w_o.shape}"
        )
    visible = visible_points(samples, (points, point, R_w_o)) if pose else samples
    return _Problem(
        objective,
        estimator,
        model,
        cell,
        jnp.asarray(predicted, dtype),
        jnp.asarray(samples, dtype),
        jnp.asarray(basis, dtype),
        jnp.asarray(pixel_sigma, dtype),
        jnp.asarray(margin, dtype),
        points,
        point,
        R_w_o,
        visible,
    )


def visible_points(
    samples: Float[ArrayLike, "S F 3"], layout: tuple | None = None
) -> Float[Array, "V F 3"]:
    """The points a design keeps in the field of view: the sample trajectories, or for the
    known-layout pose (``layout = (points, point, R_w_o)``) every reference point of the
    object along each sample (S * M trajectories): PnP needs them all in the image."""
    samples = jnp.asarray(samples)
    if layout is None:
        return samples
    points, point, R_w_o = (jnp.asarray(a, samples.dtype) for a in layout)
    offsets = (points - point) @ R_w_o.T  # (M, 3): reference point minus followed point
    return (samples[:, None] + offsets[None, :, None]).reshape(-1, *samples.shape[1:])


def evaluate_joint_path(
    model: JointPathModel,
    thetas: Float[ArrayLike, "B p n"],
    cell: RobotCell,
    predicted: Float[ArrayLike, "F 3"],
    samples: Float[ArrayLike, "S F 3"],
    basis: Float[ArrayLike, "F kb"],
    *,
    pixel_sigma: float = 0.3,
    feasibility_tol: float = 1e-3,
    estimator: str = "dct",
    layout: tuple | None = None,
) -> JointPathDesign:
    """Errors (for ``estimator``, see :func:`design_joint_path`) and constraint report of
    given paths (leading axis B; stationarity nan)."""
    thetas = jnp.asarray(thetas)
    problem = _problem(
        "mean_error",
        model,
        cell,
        predicted,
        samples,
        basis,
        pixel_sigma,
        thetas.dtype,
        estimator=estimator,
        layout=layout,
    )
    nan = jnp.full(thetas.shape[:1], jnp.nan, thetas.dtype)
    n_values = sum(_constraint_sizes(problem, thetas[0]))
    lams = jnp.zeros((thetas.shape[0], n_values), thetas.dtype)
    zero = jnp.zeros(thetas.shape[:1], jnp.int32)
    search = (zero, zero, _identities(thetas))
    return _evaluate(thetas, nan, lams, search, problem, feasibility_tol, 0.0)


def _identities(thetas):
    """(B, p n, p n) identities: the inverse Hessian of a search that has not begun."""
    B, n = thetas.shape[0], int(np.prod(thetas.shape[1:]))
    return jnp.broadcast_to(jnp.eye(n, dtype=thetas.dtype), (B, n, n))


def design_joint_path(
    model: JointPathModel,
    cell: RobotCell,
    predicted: Float[ArrayLike, "F 3"],
    samples: Float[ArrayLike, "S F 3"],
    basis: Float[ArrayLike, "F kb"],
    inits: Float[ArrayLike, "B p n"],
    *,
    multipliers: Float[ArrayLike, "B G"] | None = None,
    inverse_hessian: Float[ArrayLike, "B n n"] | None = None,
    objective: str = "mean_error",
    estimator: str = "dct",
    layout: tuple | None = None,
    pixel_sigma: float = 0.3,
    penalties: tuple[float, ...] = (10.0, 10.0, 10.0, 30.0, 30.0, 100.0, 100.0, 100.0),
    inner_steps: int = 500,
    rtol: float = 1e-9,
    grid_margin: float = 0.01,
    feasibility_tol: float = 1e-3,
    stationarity_tol: float = STATIONARITY_TOL,
    starts_in: str = "auto",
) -> tuple[JointPathDesign, JointPathDesign]:
    """Design a joint-space camera path from several starts at once.

    Args:
        model: the path model (start configuration, basis, limit grid).
        cell: the camera robot and the cell's limits.
        predicted: (F, 3) predicted workpiece point at the image times [m].
        samples: (S, F, 3) plausible workpiece trajectories (row 0 may be the prediction).
        basis: (F, kb) the reconstruction's DCT basis at the image times.
        inits: (B, p, n) initial parameters (e.g. :meth:`JointPathModel.fit` of heuristic
            joint paths, or the last design for a warm re-plan).
        multipliers: (B, G) initial multipliers (default zeros); for a warm re-plan the
            last design's ``multipliers``, with every penalty :data:`REPLAN_PENALTY` (as
            many as the design's, so that nothing is compiled again): a start already
            converged for the new prediction then stops at once, one that is not needs a
            round or two instead of the whole continuation.
        inverse_hessian: (B, p n, p n) inverse Hessians for the first round's BFGS (default:
            the identity); for a warm re-plan the last design's ``inverse_hessian``, so that
            the search does not learn the curvature again from scratch.
        objective: ``"mean_error"`` (expected mean Euclidean error, default),
            ``"error"`` (expected RMS error) or ``"eta"`` (maximise Park et al.'s eta,
            geometric mean over the samples; cheap, but blind to conditioning).
        estimator: whose error the objective is: ``"dct"`` (the paper's DCT with
            ``basis``; :func:`~jaxtraj.design.expected_errors_for_cameras`) or
            ``"smoother1"`` / ``"smoother2"`` (the smoothness prior of that order, as
            :func:`jaxtraj.estimate_points` fits it, with its noise density chosen by the
            expected marginal likelihood; bias and noise variance of the linearised
            smoother, :mod:`jaxtraj.design.smoother_error`) or ``"pose"`` (the object's
            pose from its known reference points by per-image PnP, error of the object
            point the samples follow; :mod:`jaxtraj.design.pose_error`).
        layout: for ``"pose"`` only: ``(points, point, R_w_o)``, the (M, 3) reference
            points and the (3,) followed point in the object frame [m], and the object's
            (3, 3) orientation in the world.
        pixel_sigma: detection noise [px].
        penalties: ``rho`` per augmented-Lagrangian round; each start stops as soon as it
            is converged (both tolerances below). Raised late: a small ``rho`` keeps the
            penalty's kinks mild while the active constraints are found.
        inner_steps: accepted BFGS steps per round at most; rtol: a round also ends when
            a step changes the Lagrangian and every parameter by less than this
            (relative).
        grid_margin: the design holds every normalised constraint to ``<= -grid_margin``
            on its grid (1 % of the limit by default), so that it still holds between the
            grid points (checked on a 10x finer grid in the tests); reports use the
            unmargined values. Between points ``h`` apart a constraint rises by at most
            ``h^2 / 8`` times its second derivative, so the margin covers that rise only
            on a fine enough grid (``JointPathModel.create(grid_per_image=)``): on a test
            scene with points 0.09 s apart an active floor constraint rose 1.3 mm (1.3 %
            of its 0.1 m clearance) between them; the built-in cell's are 0.017 s apart.
        feasibility_tol, stationarity_tol: the convergence test (largest normalised
            violation, and KKT stationarity of the log objective per radian; see
            :data:`STATIONARITY_TOL`).
        starts_in: ``"vmap"`` (one vectorised search of all starts, as on an
            accelerator), ``"threads"`` (one search per start, the starts shared by
            threads, one per CPU core; each start stops when it has converged instead of
            computing until the slowest has) or ``"auto"`` (default: threads on a CPU,
            vmap elsewhere). Both compile one program; a start's result agrees between
            them up to rounding, which can send a search down another path.

    Returns:
        ``(best, designs)``: the best feasible design (lowest objective; the least
        infeasible if none is feasible) and all B designs (leading axis B).
    """
    if starts_in not in STARTS_IN:
        raise ValueError(f"starts_in: expected one of {STARTS_IN}, got {starts_in!r}")
    inits = jnp.asarray(inits)
    if inits.ndim != 3 or inits.shape[1:] != model.shape:
        raise ValueError(
            f"inits: expected shape (B, {model.shape[0]}, {model.shape[1]}), got {inits.shape}"
        )
    problem = _problem(
        objective,
        model,
        cell,
        predicted,
        samples,
        basis,
        pixel_sigma,
        inits.dtype,
        grid_margin,
        estimator,
        layout,
    )
    rhos = jnp.asarray(penalties, inits.dtype)
    n_values = sum(_constraint_sizes(problem, inits[0]))
    if multipliers is None:
        lams = jnp.zeros((inits.shape[0], n_values), inits.dtype)
    else:
        lams = jnp.asarray(multipliers, inits.dtype)
        if lams.shape != (inits.shape[0], n_values):
            raise ValueError(
                f"multipliers: expected shape ({inits.shape[0]}, {n_values}), got {lams.shape}"
            )
    H0s = _identities(inits)
    if inverse_hessian is not None:
        given = jnp.asarray(inverse_hessian, inits.dtype)
        if given.shape != H0s.shape:
            raise ValueError(f"inverse_hessian: expected shape {H0s.shape}, got {given.shape}")
        H0s = given
    thetas, lams, stationarity, search, viol, errors = _run_starts(
        starts_in,
        inits,
        lams,
        H0s,
        problem,
        rhos,
        inner_steps,
        rtol,
        feasibility_tol,
        stationarity_tol,
    )
    tols = (feasibility_tol, stationarity_tol)
    if objective == "eta":  # the search did not compute the errors
        report = eqx.tree_at(lambda p: p.margin, problem, jnp.zeros_like(problem.margin))
        designs = _evaluate(thetas, stationarity, lams, search, report, *tols)
    else:
        designs = _reported(thetas, stationarity, lams, search, viol, errors, tols)
    metric = designs.expected_error if objective == "error" else designs.expected_mean_error
    score = jnp.where(designs.feasible, metric, jnp.inf)
    i = jnp.where(jnp.any(designs.feasible), jnp.argmin(score), jnp.argmin(designs.max_violation))
    best = jax.tree_util.tree_map(lambda a: a[i], designs)
    return best, designs

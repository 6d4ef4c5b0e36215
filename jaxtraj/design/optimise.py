"""Optimise a camera path: minimise the expected error (RMS or mean Euclidean) or maximise
eta, under the limits.

The constraints enter as a quadratic penalty ``mu sum max(g, 0)^2`` with continuation
(``mu`` raised round by round, each round a BFGS run of optimistix started where the last
ended), so the result is feasible to about ``1 / mu``. Several initial guesses run at
once (``vmap``); the best feasible one is reported, with the constraints that are active
(within ``active_tol`` of their limit) and the largest violation of each.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float

from .constraints import CONSTRAINTS, CellLimits, constraint_values, penalty
from .objectives import expected_error, expected_errors_for_cameras, path_reconstructibility
from .path import CameraPathModel

__all__ = ["PathDesign", "design_camera_path", "evaluate_path"]

OBJECTIVES = ("error", "mean_error", "eta")


class PathDesign(eqx.Module):
    """A designed (or evaluated) camera path.

    Attributes:
        theta: (k, 3) path parameters.
        expected_error: expected RMS reconstruction error [m].
        expected_mean_error: expected mean Euclidean reconstruction error [m] (an upper
            bound, see :func:`~jaxtraj.design.expected_error` with ``metric="mean"``).
        eta: reconstructibility (geometric mean over the samples).
        violation: (C,) largest normalised constraint value per constraint, in the order
            of :data:`~jaxtraj.design.constraints.CONSTRAINTS` (<= 0: satisfied).
        active: (C,) constraints within ``active_tol`` of their limit.
        feasible: every violation <= ``feasible_tol`` and a finite expected error.
        peak_velocity [m/s], peak_acceleration [m/s^2]: on the limit grid.
    """

    theta: Float[Array, "k 3"]
    expected_error: Float[Array, ""]
    expected_mean_error: Float[Array, ""]
    eta: Float[Array, ""]
    violation: Float[Array, " C"]
    active: Bool[Array, " C"]
    feasible: Bool[Array, ""]
    peak_velocity: Float[Array, ""]
    peak_acceleration: Float[Array, ""]

    def report(self) -> dict:
        """The constraints by name: value, active, satisfied (host-side, one design)."""
        return {
            name: {
                "max_value": float(self.violation[i]),
                "active": bool(self.active[i]),
                "satisfied": bool(self.violation[i] <= 1e-3),
            }
            for i, name in enumerate(CONSTRAINTS)
        }


def evaluate_path(
    model: CameraPathModel,
    theta: Float[ArrayLike, "k 3"],
    K: Float[ArrayLike, "3 3"],
    predicted: Float[ArrayLike, "F 3"],
    samples: Float[ArrayLike, "S F 3"],
    basis: Float[ArrayLike, "F kb"],
    limits: CellLimits,
    *,
    pixel_sigma: float = 0.3,
    active_tol: float = 0.02,
    feasible_tol: float = 1e-3,
) -> PathDesign:
    """Objectives and constraint report of one path (jit- and vmap-compatible)."""
    theta = jnp.asarray(theta)
    values = constraint_values(model, theta, limits, predicted, samples)
    viol = jnp.stack([jnp.max(values[name]) for name in CONSTRAINTS])
    P = model.projection_matrices(theta, K, predicted)
    error, mean_error = expected_errors_for_cameras(P, samples, basis, pixel_sigma)
    return PathDesign(
        theta=theta,
        expected_error=error,
        expected_mean_error=mean_error,
        eta=path_reconstructibility(model, theta, samples, basis),
        violation=viol,
        active=jnp.abs(viol) <= active_tol,
        feasible=jnp.all(viol <= feasible_tol) & jnp.isfinite(error),
        peak_velocity=jnp.max(jnp.linalg.norm(model.velocity(theta), axis=1)),
        peak_acceleration=jnp.max(jnp.linalg.norm(model.acceleration(theta), axis=1)),
    )


class _Objective(eqx.Module):
    """``f(theta, mu)``: the objective plus ``mu`` times the constraint penalty. A pytree,
    so that :func:`_optimise` compiles once per problem shape, not once per call."""

    kind: str = eqx.field(static=True)
    model: CameraPathModel
    K: Array
    predicted: Array
    samples: Array
    basis: Array
    limits: CellLimits
    pixel_sigma: Array

    def __call__(self, theta, mu):
        m, K, x, S, B = self.model, self.K, self.predicted, self.samples, self.basis
        if self.kind in ("error", "mean_error"):
            metric = "mean" if self.kind == "mean_error" else "rms"
            main = jnp.log(expected_error(m, theta, K, x, S, B, self.pixel_sigma, metric))
        else:
            main = -jnp.log(path_reconstructibility(m, theta, S, B))
        return main + mu * penalty(constraint_values(m, theta, self.limits, x, S))


@eqx.filter_jit
def _optimise(theta0, f, mus, max_steps, rtol):
    solver = optx.BFGS(rtol=rtol, atol=rtol * 1e-2)

    def round_(theta, mu):
        sol = optx.minimise(f, solver, theta, args=mu, max_steps=max_steps, throw=False)
        new = f(sol.value, mu)
        better = jnp.isfinite(new) & (new <= f(theta, mu))
        return jnp.where(better, sol.value, theta), sol.result == optx.RESULTS.successful

    def one(theta):
        theta, ok = jax.lax.scan(round_, theta, mus)  # one compiled round for every mu
        return theta, jnp.all(ok)

    return jax.vmap(one)(theta0)


@eqx.filter_jit
def _evaluate_many(thetas, f: _Objective):
    return jax.vmap(
        lambda th: evaluate_path(
            f.model, th, f.K, f.predicted, f.samples, f.basis, f.limits, pixel_sigma=f.pixel_sigma
        )
    )(thetas)


def design_camera_path(
    model: CameraPathModel,
    K: Float[ArrayLike, "3 3"],
    predicted: Float[ArrayLike, "F 3"],
    samples: Float[ArrayLike, "S F 3"],
    basis: Float[ArrayLike, "F kb"],
    limits: CellLimits,
    inits: Float[ArrayLike, "B k 3"],
    *,
    objective: str = "error",
    pixel_sigma: float = 0.3,
    penalty_weights: tuple[float, ...] = (1e1, 1e3, 1e5),
    max_steps: int = 300,
    rtol: float = 1e-6,
    mesh=None,
) -> tuple[PathDesign, PathDesign, Array]:
    """Design a camera path from several initial guesses at once.

    Args:
        model: the path model (start position, basis, limit grid).
        K: (3, 3) camera matrix.
        predicted: (F, 3) predicted workpiece point at the image times (the camera looks
            at it).
        samples: (S, F, 3) plausible workpiece trajectories the path must measure well.
        basis: (F, kb) the reconstruction's basis at the image times.
        limits: the cell's limits.
        inits: (B, k, 3) initial parameters (e.g. :meth:`CameraPathModel.fit` of heuristic
            paths).
        objective: ``"error"`` (expected RMS error, default), ``"mean_error"`` (expected
            mean Euclidean error, the paper's metric) or ``"eta"`` (maximise eta). The
            best design is chosen by the expected mean error for ``"mean_error"`` and by
            the expected RMS error otherwise.
        pixel_sigma: detection noise [px].
        penalty_weights: the penalty continuation ``mu`` per round.
        max_steps: BFGS steps per round; rtol: its tolerance.
        mesh: a ``jax.sharding.Mesh``; the initial guesses are then split over its devices
            (padded with copies of the last one, which are dropped).

    Returns:
        ``(best, all_designs, converged)``: the best feasible design (lowest expected
        error; the least infeasible if none is feasible), all B designs (leading axis B),
        and (B,) the optimiser's convergence flags.
    """
    if objective not in OBJECTIVES:
        raise ValueError(f"objective: expected one of {OBJECTIVES}, got {objective!r}")
    inits = jnp.asarray(inits)
    if inits.ndim != 3 or inits.shape[1:] != (model.k, 3):
        raise ValueError(f"inits: expected shape (B, {model.k}, 3), got {inits.shape}")
    dtype = inits.dtype
    f = _Objective(
        objective,
        model,
        jnp.asarray(K, dtype),
        jnp.asarray(predicted, dtype),
        jnp.asarray(samples, dtype),
        jnp.asarray(basis, dtype),
        limits,
        jnp.asarray(pixel_sigma, dtype),
    )
    mus = jnp.asarray(penalty_weights, inits.dtype)
    n = inits.shape[0]
    if mesh is not None:
        from jax.sharding import NamedSharding
        from jax.sharding import PartitionSpec as Pspec

        pad = (-n) % mesh.devices.size
        padded = jnp.concatenate([inits, jnp.repeat(inits[-1:], pad, axis=0)])
        inits = jax.device_put(padded, NamedSharding(mesh, Pspec(mesh.axis_names[0])))
    thetas, converged = _optimise(inits, f, mus, max_steps, rtol)
    thetas, converged = thetas[:n], converged[:n]
    designs = _evaluate_many(thetas, f)
    worst = jnp.max(designs.violation, axis=1)
    worst = jnp.where(jnp.isfinite(designs.expected_error), worst, jnp.inf)
    metric = designs.expected_mean_error if objective == "mean_error" else designs.expected_error
    score = jnp.where(designs.feasible, metric, jnp.inf)  # feasible: finite
    i = jnp.where(jnp.any(designs.feasible), jnp.argmin(score), jnp.argmin(worst))
    best = jax.tree_util.tree_map(lambda a: a[i], designs)
    return best, designs, converged

"""Joint 6-DoF trajectory of a rigid object from the rays of all its reference points.

The per-frame approach reconstructs every reference point independently and fits a rigid
transform to each frame's points (Kabsch, :func:`jaxtraj.fit_rigid`). The joint estimator
fits *one* rigid motion to all pixels at once::

    T_w_o(t) = (exp([phi(t) beta_r]_x) R_ref,  phi(t) beta_t)
    uv_{i,m} ~ pi(P_i (R(t_i) x_m + p(t_i)))

with translation and rotation vector each in a trajectory basis (k, 3), minimising the
(robust) reprojection error over ``(beta_t, beta_r)`` with Levenberg-Marquardt. The start
is the per-frame Kabsch fit projected onto the basis, so no initial guess is needed. All
M points share 6k unknowns instead of 3k each, and rigidity is enforced exactly.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float

from .._checks import check_shape
from .._precision import cast_floats, least_squares_dtype
from ..rigid import fit_rigid
from ..solve import reconstruct
from ._common import as_float, check_loss, rho

__all__ = ["RigidTrajectory", "fit_rigid_trajectory", "kabsch_per_frame"]


class RigidTrajectory(eqx.Module):
    """Result of :func:`fit_rigid_trajectory`.

    Attributes:
        R: (F, 3, 3) rotations ``R_w_o``; t: (F, 3) translations ``t_w_o`` [m].
        trans_coeffs, rot_coeffs: (k, 3) basis coefficients of translation and rotation
            vector (relative to ``R_ref``); R_ref: (3, 3).
        rms_px: reprojection RMS over all observed pixels [px]; rms_px_initial: at the start.
        converged: the optimiser reported success.
    """

    R: Float[Array, "F 3 3"]
    t: Float[Array, "F 3"]
    trans_coeffs: Float[Array, "k 3"]
    rot_coeffs: Float[Array, "k 3"]
    R_ref: Float[Array, "3 3"]
    rms_px: Float[Array, ""]
    rms_px_initial: Float[Array, ""]
    converged: Bool[Array, ""]


def kabsch_per_frame(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "M F 2"],
    model_points: Float[ArrayLike, "M 3"],
    basis: Float[ArrayLike, "F k"],
    weights: Float[ArrayLike, "M F"] | None = None,
) -> tuple[Float[Array, "F 3 3"], Float[Array, "F 3"]]:
    """Baseline: reconstruct each point (paper eq. 6), then Kabsch per frame -> (R, t)."""
    _check(P, uv, model_points, basis, weights)
    P, uv, model_points, basis, weights = as_float(P, uv, model_points, basis, weights)
    w = jnp.ones(uv.shape[:2], P.dtype) if weights is None else weights
    rec = jax.vmap(lambda u, ww: reconstruct(P, u, basis, ww))(uv, w)
    return fit_rigid(model_points, jnp.swapaxes(rec.points, 0, 1))


def _check(P, uv, model_points, basis, weights):
    check_shape("P", P, (None, 3, 4), "one projection matrix per frame")
    F = np.shape(P)[0]
    check_shape("model_points", model_points, (None, 3), "(M, 3) points in the object frame")
    M = np.shape(model_points)[0]
    if M < 3:
        raise ValueError(f"model_points: need at least 3 reference points, got {M}")
    check_shape("uv", uv, (M, F, 2), f"(M, F, 2) pixels of the M={M} points")
    check_shape("basis", basis, (F, None), "(F, k) basis at the frame times")
    if weights is not None:
        check_shape("weights", weights, (M, F), "(M, F) weights")


def fit_rigid_trajectory(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "M F 2"],
    model_points: Float[ArrayLike, "M 3"],
    basis: Float[ArrayLike, "F k"],
    weights: Float[ArrayLike, "M F"] | None = None,
    *,
    loss: str = "l2",
    loss_scale: float = 2.0,
    max_steps: int = 100,
    init: tuple[Float[ArrayLike, "F 3 3"], Float[ArrayLike, "F 3"]] | None = None,
) -> RigidTrajectory:
    """Fit one rigid motion (translation and rotation in a basis) to all points' pixels.

    Args:
        P: (F, 3, 4) projection matrices (undistorted).
        uv: (M, F, 2) pixels of the M reference points [px]; weight-0 entries ignored.
        model_points: (M, 3) the points in the object frame [m] (M >= 3, not collinear).
        basis: (F, k) trajectory basis at the frame times (used for translation and
            rotation; the per-point start uses it too, so 2 F >= 3 k).
        weights: (M, F) weights, 0 for missing detections.
        loss, loss_scale: robust loss on the reprojection error (see
            :func:`jaxtraj.estimators.refine_dct`).
        max_steps: Levenberg-Marquardt steps.
        init: per-frame starting poses ``(R_w_o (F, 3, 3), t_w_o (F, 3))``, e.g. from a
            per-image PnP; default :func:`kabsch_per_frame` (per-point reconstruction,
            which needs a camera path that makes each point reconstructible).

    Returns:
        A :class:`RigidTrajectory` with the pose ``T_w_o`` at every frame.
    """
    _check(P, uv, model_points, basis, weights)
    check_loss(loss, loss_scale)
    if init is not None:
        F = np.shape(P)[0]
        check_shape("init[0]", init[0], (F, 3, 3), "(F, 3, 3) starting rotations R_w_o")
        check_shape("init[1]", init[1], (F, 3), "(F, 3) starting translations t_w_o")
    P, uv, model_points, basis, weights = as_float(P, uv, model_points, basis, weights)
    w = jnp.ones(uv.shape[:2], P.dtype) if weights is None else weights
    obs = w > 0
    uv = jnp.where(obs[..., None], uv, 0.0)
    if init is None:
        R0, t0 = kabsch_per_frame(P, uv, model_points, basis, w)
    else:
        R0, t0 = (jnp.asarray(a, P.dtype) for a in init)
    args = cast_floats(  # float32 under x64: solved in float64 (least_squares_dtype)
        (P, uv, model_points, basis, w, R0, t0), least_squares_dtype(P.dtype)
    )
    return cast_floats(_fit(*args, loss, loss_scale, max_steps), P.dtype)


@eqx.filter_jit  # one compiled program per shape and loss (run eagerly: seconds per call)
def _fit(P, uv, model_points, basis, w, R0, t0, loss, loss_scale, max_steps):
    obs = w > 0
    F = basis.shape[0]
    R_ref = R0[F // 2]
    rotvec = jax.vmap(lambda R: jaxlie.SO3.from_matrix(R @ R_ref.T).log())(R0)
    pinv = jnp.linalg.pinv(basis)
    y0 = (pinv @ t0, pinv @ rotvec)

    def poses(y):
        bt, br = y
        R = jax.vmap(lambda r: jaxlie.SO3.exp(r).as_matrix())(basis @ br) @ R_ref
        return R, basis @ bt

    def errors(y):
        R, t = poses(y)
        X = jnp.einsum("fij,mj->mfi", R, model_points) + t  # (M, F, 3)
        h = jnp.einsum("fij,mfj->mfi", P[:, :, :3], X) + P[:, :, 3]
        return h[..., :2] / h[..., 2:3] - uv

    sw = jnp.sqrt(w)

    def residuals(y, _):
        e = errors(y)
        if loss != "l2":
            s = jnp.sum(e * e, axis=-1)
            safe = jnp.where(s > 0, s, 1.0)
            e = e * jnp.where(s > 0, jnp.sqrt(rho(safe, loss, loss_scale) / safe), 1.0)[..., None]
        return e * sw[..., None]

    def rms(y):
        e = errors(y)
        sq = jnp.where(obs, jnp.sum(e * e, axis=-1), 0.0)
        return jnp.sqrt(jnp.sum(sq) / jnp.maximum(jnp.sum(obs), 1))

    def cost(y):
        r = residuals(y, None)
        return jnp.sum(r * r)

    sol = optx.least_squares(
        residuals,
        optx.LevenbergMarquardt(rtol=1e-8, atol=1e-10),
        y0,
        max_steps=max_steps,
        throw=False,
    )
    better = jnp.isfinite(cost(sol.value)) & (cost(sol.value) <= cost(y0))
    y = jax.tree.map(lambda a, b: jnp.where(better, a, b), sol.value, y0)
    R, t = poses(y)
    return RigidTrajectory(
        R=R,
        t=t,
        trans_coeffs=y[0],
        rot_coeffs=y[1],
        R_ref=R_ref,
        rms_px=rms(y),
        rms_px_initial=rms(y0),
        converged=sol.result == optx.RESULTS.successful,
    )

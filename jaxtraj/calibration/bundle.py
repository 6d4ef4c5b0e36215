"""Robot-world hand-eye bundle adjustment: intrinsics, distortion, hand-eye and target pose.

One model covers both set-ups. With the robot's flange poses ``T_b_f_i`` and a planar
target with corners ``P_j`` (target frame ``t``), the target's pose in the camera of view
``i`` is

    T_c_t_i = X^-1 M_i B

- eye-in-hand (camera on the flange, target fixed): ``X = T_f_c``, ``M_i = T_b_f_i^-1``,
  ``B = T_b_t`` (the target in the robot base);
- eye-to-hand (camera fixed, target on the flange): ``X = T_b_c``, ``M_i = T_b_f_i``,
  ``B = T_f_t`` (the target on the flange).

:func:`refine_hand_eye` minimises ``sum_ij w_ij rho(|pi(K, d, T_c_t_i P_j) - uv_ij|^2)``
over the 21 parameters ``(fx, fy, cx, cy, k1, k2, p1, p2, k3, X, B)`` (and a correction
of each robot pose) with optimistix's Levenberg-Marquardt, started from a closed-form
solution (OpenCV's ``calibrateCamera`` and ``calibrateHandEye``). Compared with the
closed forms, it uses every corner of every view in one consistent model: the per-view
target poses (six free parameters each in ``calibrateCamera``) are replaced by the
robot's poses and two fixed transforms, which is what averages the noise of the per-view
poses out. The robot's reported poses are not taken as exact: each gets a 6-DoF
correction with a Gaussian prior of the controller's noise (measured: with 0.2 mm /
0.02 deg robot noise, taking the poses as exact moved the hand-eye rotation by 0.7-1 deg
through its correlation with the principal point).
Rotations are perturbed on the right, ``R = R_0 Exp(w)``; translations additively.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._precision import cast_floats, least_squares_dtype
from ..camera import distort

__all__ = ["PARAMETER_NAMES", "HandEyeBundle", "bundle_residuals", "refine_hand_eye"]

#: Names of the 21 parameters, in the order of :attr:`HandEyeBundle.covariance`
#: (units: px for the intrinsics, none for distortion, rad for the rotation
#: perturbations ``w`` (right, ``R = R_est Exp(w)``), m for translations).
PARAMETER_NAMES = (
    "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3",
    "X.wx", "X.wy", "X.wz", "X.tx", "X.ty", "X.tz",
    "B.wx", "B.wy", "B.wz", "B.tx", "B.ty", "B.tz",
)  # fmt: skip

_LOSSES = ("l2", "huber", "cauchy")
_VIEW_BUCKET = 8
_SOLVERS = {
    "lm": optx.LevenbergMarquardt,
    "gauss-newton": optx.GaussNewton,
    "dogleg": optx.Dogleg,
}
# Optimiser units per parameter: 1 px, 1e-3 (distortion), 1 mrad, 1 mm. Levenberg-Marquardt
# damps every coordinate alike, so the coordinates are put on comparable scales.
_SCALE = np.array([1.0] * 4 + [1e-3] * 5 + ([1e-3] * 3 + [1e-3] * 3) * 2)


class HandEyeBundle(eqx.Module):
    """Result of :func:`refine_hand_eye`.

    Attributes:
        K: (3, 3) camera matrix [px]; dist: (5,) (k1, k2, p1, p2, k3).
        T_x: (4, 4) the hand-eye transform ``X`` (``T_f_c`` eye-in-hand, ``T_b_c``
            eye-to-hand).
        T_b: (4, 4) the target transform ``B`` (``T_b_t`` eye-in-hand, ``T_f_t`` eye-to-hand).
        covariance: (21, 21) parameter covariance (order and units: :data:`PARAMETER_NAMES`),
            ``variance_factor (J^T J)^-1`` at the solution (robot corrections marginalised).
        variance_factor: ``SSR / (m - n)`` of the normalised residuals (about 1 when the
            given pixel and robot sigmas are right).
        robot_corrections: (V, 6) the corrections of the robot poses (rotation [rad],
            translation [m], in the base frame).
        rms_px, rms_px_initial: RMS reprojection error per corner after / before [px].
        residuals: (V, N, 2) reprojection errors after refinement [px] (0 where unobserved).
        steps: optimiser steps; converged: the optimiser reported success.
    """

    K: Float[Array, "3 3"]
    dist: Float[Array, " 5"]
    T_x: Float[Array, "4 4"]
    T_b: Float[Array, "4 4"]
    covariance: Float[Array, "21 21"]
    variance_factor: Float[Array, ""]
    robot_corrections: Float[Array, "V 6"]
    rms_px: Float[Array, ""]
    rms_px_initial: Float[Array, ""]
    residuals: Float[Array, "V N 2"]
    steps: Int[Array, ""]
    converged: Bool[Array, ""]

    @property
    def std(self) -> Float[Array, " 21"]:
        """Standard deviations of the parameters (order: :data:`PARAMETER_NAMES`)."""
        return jnp.sqrt(jnp.clip(jnp.diagonal(self.covariance), 0.0))


def _pose(T0, w, t):
    R = T0[:3, :3] @ jaxlie.SO3.exp(w).as_matrix()
    return R, T0[:3, 3] + t


def _scale(n_views, dt):
    return jnp.concatenate([jnp.asarray(_SCALE, dt), jnp.full(6 * n_views, 1e-3, dt)])


def _unpack(z, start):
    K0, d0, X0, B0 = start
    x = z[:21] * jnp.asarray(_SCALE, z.dtype)
    fx, fy, cx, cy = K0[0, 0] + x[0], K0[1, 1] + x[1], K0[0, 2] + x[2], K0[1, 2] + x[3]
    dist = d0 + x[4:9]
    R_x, t_x = _pose(X0, x[9:12], x[12:15])
    R_b, t_b = _pose(B0, x[15:18], x[18:21])
    return (fx, fy, cx, cy), dist, (R_x, t_x), (R_b, t_b)


def _robot(z, T_b_f, eye_in_hand):
    """The model's M_i from the reported flange poses and their corrections
    (``R = Exp(w_i) R_reported``, ``t = t_reported + d_i``, in the base frame).
    ``eye_in_hand`` is a traced bool (one compiled program serves both set-ups)."""
    c = (z[21:] * 1e-3).reshape(-1, 6)
    R = jax.vmap(lambda w: jaxlie.SO3.exp(w).as_matrix())(c[:, :3]) @ T_b_f[:, :3, :3]
    t = T_b_f[:, :3, 3] + c[:, 3:]
    Rt = jnp.swapaxes(R, -1, -2)  # eye-in-hand: M = T_b_f^-1
    R_m = jnp.where(eye_in_hand, Rt, R)
    t_m = jnp.where(eye_in_hand, -jnp.einsum("vij,vj->vi", Rt, t), t)
    return R_m, t_m, c


def _errors(z, start, object_points, uv, T_b_f, eye_in_hand):
    (fx, fy, cx, cy), dist, (R_x, t_x), (R_b, t_b) = _unpack(z, start)
    R_m, t_m, _ = _robot(z, T_b_f, eye_in_hand)
    p_b = object_points @ R_b.T + t_b  # (N, 3) in the frame B maps into
    p_m = jnp.einsum("vij,nj->vni", R_m, p_b) + t_m[:, None]  # (V, N, 3): M_i p_b
    p_c = (p_m - t_x) @ R_x  # X^-1 M_i p_b
    z_c = p_c[..., 2:3]
    safe = jnp.where(jnp.abs(z_c) > 1e-12, z_c, 1.0)
    xy = distort(p_c[..., :2] / safe, dist)
    pix = jnp.stack([fx * xy[..., 0] + cx, fy * xy[..., 1] + cy], -1)
    return pix - uv


def _rho_factor(s, loss, scale):
    """sqrt(rho(s) / s) for squared error norms s (1 where s = 0)."""
    if loss == "l2":
        return jnp.ones_like(s)
    c2 = scale * scale
    pos = s > 0
    safe = jnp.where(pos, s, 1.0)
    if loss == "huber":
        rho = jnp.where(safe <= c2, safe, 2 * scale * jnp.sqrt(safe) - c2)
    else:  # cauchy
        rho = c2 * jnp.log1p(safe / c2)
    return jnp.where(pos, jnp.sqrt(rho / safe), 1.0)


def _residual_fn(loss):
    def fn(z, args):
        start, object_points, uv, weights, T_b_f, sigmas, scale, eye_in_hand = args
        pixel_sigma, robot_pos_sigma, robot_rot_sigma = sigmas
        e = _errors(z, start, object_points, uv, T_b_f, eye_in_hand) / pixel_sigma
        f = _rho_factor(jnp.sum(e * e, -1), loss, scale / pixel_sigma)
        pix = (e * (jnp.sqrt(weights) * f)[..., None]).reshape(-1)
        c = (z[21:] * 1e-3).reshape(-1, 6)
        prior = jnp.concatenate([c[:, :3] / robot_rot_sigma, c[:, 3:] / robot_pos_sigma], 1)
        return jnp.concatenate([pix, prior.reshape(-1)])

    return fn


def bundle_residuals(
    object_points: Float[ArrayLike, "N 3"],
    uv: Float[ArrayLike, "V N 2"],
    T_b_f: Float[ArrayLike, "V 4 4"],
    K: Float[ArrayLike, "3 3"],
    dist: Float[ArrayLike, " 5"],
    T_x: Float[ArrayLike, "4 4"],
    T_b: Float[ArrayLike, "4 4"],
    *,
    eye_in_hand: bool = True,
) -> Float[Array, "V N 2"]:
    """Reprojection errors ``pi(K, dist, X^-1 M_i B P_j) - uv_ij`` [px] of a parameter set
    with the robot poses as given.

    Args: as :func:`refine_hand_eye` (K, dist, T_x, T_b: the parameters to evaluate).
    """
    uv = jnp.asarray(uv)
    dt = uv.dtype
    start = tuple(jnp.asarray(a, dt) for a in (K, dist, T_x, T_b))
    z = jnp.zeros(21 + 6 * uv.shape[0], dt)
    P, T = jnp.asarray(object_points, dt), jnp.asarray(T_b_f, dt)
    return _errors(z, start, P, uv, T, jnp.asarray(bool(eye_in_hand)))


@eqx.filter_jit
def _refine(start, object_points, uv, weights, T_b_f, sigmas, scale, eye_in_hand, static):
    loss, solver_name, max_steps, rtol, atol = static
    dt = uv.dtype
    V = uv.shape[0]
    args = (start, object_points, uv, weights, T_b_f, sigmas, scale, eye_in_hand)
    fn = _residual_fn(loss)
    z0 = jnp.zeros(21 + 6 * V, dt)
    solver = _SOLVERS[solver_name](rtol=rtol, atol=atol)
    sol = optx.least_squares(fn, solver, z0, args=args, max_steps=max_steps, throw=False)
    z = sol.value
    (fx, fy, cx, cy), dist, (R_x, t_x), (R_b, t_b) = _unpack(z, start)
    K = jnp.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dt)
    T_x = jnp.eye(4, dtype=dt).at[:3, :3].set(R_x).at[:3, 3].set(t_x)
    T_b = jnp.eye(4, dtype=dt).at[:3, :3].set(R_b).at[:3, 3].set(t_b)
    # Covariance from the plain (non-robust) residuals at the solution, scaled by the
    # a-posteriori variance factor (SSR / redundancy).
    plain = _residual_fn("l2")
    r = plain(z, args)
    J = jax.jacfwd(plain)(z, args)
    n = z.shape[0]
    m = 2 * jnp.sum(weights > 0) + 6 * V
    factor = jnp.sum(r * r) / jnp.maximum(m - n, 1)
    JtJ = J.T @ J
    d = 1.0 / jnp.sqrt(jnp.maximum(jnp.diagonal(JtJ), jnp.finfo(dt).tiny))
    inv = d[:, None] * jnp.linalg.inv(d[:, None] * JtJ * d[None, :]) * d[None, :]
    s = _scale(V, dt)
    cov = factor * s[:, None] * inv * s[None, :]
    cov = 0.5 * (cov + cov.T)
    e = _errors(z, start, object_points, uv, T_b_f, eye_in_hand)
    e0 = _errors(z0, start, object_points, uv, T_b_f, eye_in_hand)
    seen = weights > 0
    n_seen = jnp.maximum(jnp.sum(seen), 1)

    def rms(err):
        return jnp.sqrt(jnp.sum(jnp.where(seen, jnp.sum(err * err, -1), 0.0)) / n_seen)

    _, _, corrections = _robot(z, T_b_f, eye_in_hand)
    return HandEyeBundle(
        K=K,
        dist=dist,
        T_x=T_x,
        T_b=T_b,
        covariance=cov[:21, :21],
        variance_factor=factor,
        robot_corrections=corrections,
        rms_px=rms(e),
        rms_px_initial=rms(e0),
        residuals=jnp.where(seen[..., None], e, 0.0),
        steps=jnp.asarray(sol.stats["num_steps"]),
        converged=sol.result == optx.RESULTS.successful,
    )


def _check(name, value, shape, what):
    arr = np.asarray(value)
    ok = arr.ndim == len(shape) and all(
        s is None or s == a for s, a in zip(shape, arr.shape, strict=False)
    )
    if not ok:
        want = "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name}: expected {what} of shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: non-finite entries")
    return arr


def refine_hand_eye(
    object_points: Float[ArrayLike, "N 3"],
    uv: Float[ArrayLike, "V N 2"],
    weights: Float[ArrayLike, "V N"],
    T_b_f: Float[ArrayLike, "V 4 4"],
    K: Float[ArrayLike, "3 3"],
    dist: Float[ArrayLike, " 5"],
    T_x: Float[ArrayLike, "4 4"],
    T_b: Float[ArrayLike, "4 4"],
    *,
    eye_in_hand: bool = True,
    pixel_sigma: float = 0.2,
    robot_position_sigma: float = 0.2e-3,
    robot_rotation_sigma: float = 3.5e-4,
    loss: str = "huber",
    loss_scale: float = 1.0,
    solver: str = "lm",
    max_steps: int = 100,
    rtol: float = 1e-8,
    atol: float = 1e-8,
) -> HandEyeBundle:
    """Jointly refine intrinsics, distortion, hand-eye ``X`` and target ``B`` (module doc).

    The robot's reported poses get a 6-DoF correction each with a Gaussian prior
    (``robot_*_sigma``), so the controller's noise is modelled instead of being forced
    into the pixel residuals; the corrections are returned.

    Args:
        object_points: (N, 3) target corners in the target frame [m].
        uv: (V, N, 2) their pixels in V views [px] (any value where unobserved).
        weights: (V, N) 1 for an observed corner, 0 for one not seen (partial views).
        T_b_f: (V, 4, 4) the flange poses as the controller reports them.
        K, dist: (3, 3), (5,) start intrinsics and (k1, k2, p1, p2, k3).
        T_x, T_b: (4, 4) start hand-eye and target transforms (see the module doc).
        eye_in_hand: camera on the flange (True) or fixed in the base frame (False).
        pixel_sigma: corner noise per coordinate [px] (e.g. from ``calibrateCamera``'s RMS).
        robot_position_sigma, robot_rotation_sigma: controller pose noise [m], [rad].
        loss: ``"huber"`` (default), ``"cauchy"`` or ``"l2"``; loss_scale: its threshold on
            the corner error norm [px].
        solver: ``"lm"`` (Levenberg-Marquardt, default), ``"gauss-newton"`` or ``"dogleg"``
            (optimistix). From OpenCV's start on 12-view sets all three reached the same
            minimum (hand-eye within 1e-7 mm) in 32-48, 10-12 and 17-28 steps: Gauss-Newton
            is the fast choice from a good start, LM the safe one from a poor start.
        max_steps, rtol, atol: optimiser settings (on the parameters in the
            optimiser's units: 1 px, 1e-3, 1 mrad, 1 mm; 1e-8 moved the results by < 1e-9
            mm against 1e-10/1e-12 and halved the steps).

    Returns:
        a :class:`HandEyeBundle`; the dtype is that of ``uv``. One compiled program per
        (views rounded up to a multiple of 8, corners, loss, solver, dtype), shared by
        both set-ups.
    """
    uv = _check("uv", uv, (None, None, 2), "pixels (V views, N corners)")
    V, N = uv.shape[:2]
    _check("object_points", object_points, (N, 3), "target corners [m]")
    _check("weights", weights, (V, N), "observation weights")
    _check("T_b_f", T_b_f, (V, 4, 4), "robot poses (one per view)")
    _check("K", K, (3, 3), "a camera matrix")
    _check("dist", dist, (5,), "distortion (k1, k2, p1, p2, k3)")
    _check("T_x", T_x, (4, 4), "a rigid transform")
    _check("T_b", T_b, (4, 4), "a rigid transform")
    if loss not in _LOSSES:
        raise ValueError(f"loss: expected one of {_LOSSES}, got {loss!r}")
    if solver not in _SOLVERS:
        raise ValueError(f"solver: expected one of {tuple(_SOLVERS)}, got {solver!r}")
    for name, value in (
        ("loss_scale", loss_scale),
        ("pixel_sigma", pixel_sigma),
        ("robot_position_sigma", robot_position_sigma),
        ("robot_rotation_sigma", robot_rotation_sigma),
    ):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"{name}: expected a positive number, got {value!r}")
    if not isinstance(max_steps, int) or max_steps < 1:
        raise ValueError(f"max_steps: expected a positive int, got {max_steps!r}")
    if 2 * int(np.sum(np.asarray(weights) > 0)) <= 21:
        raise ValueError("weights: fewer than 11 observed corners for 21 parameters")
    uv = jnp.asarray(uv)
    if not jnp.issubdtype(uv.dtype, jnp.floating):
        uv = uv.astype(jnp.result_type(float))
    out_dtype = uv.dtype
    dt = least_squares_dtype(out_dtype)  # float32 under x64: solved in float64
    uv = uv.astype(dt)
    start = tuple(jnp.asarray(a, dt) for a in (K, dist, T_x, T_b))
    sigmas = tuple(
        jnp.asarray(v, dt) for v in (pixel_sigma, robot_position_sigma, robot_rotation_sigma)
    )
    # Views padded to a multiple of 8 (zero weight, a copy of the first robot pose; their
    # corrections only meet their prior and stay 0): one compiled program serves 9-16 views.
    pad = -V % _VIEW_BUCKET
    weights = np.asarray(weights, np.float64)
    T_b_f = np.asarray(T_b_f, np.float64)
    if pad:
        uv = jnp.concatenate([uv, jnp.zeros((pad, N, 2), dt)])
        weights = np.concatenate([weights, np.zeros((pad, N))])
        T_b_f = np.concatenate([T_b_f, np.repeat(T_b_f[:1], pad, 0)])
    out = _refine(
        start,
        jnp.asarray(object_points, dt),
        uv,
        jnp.asarray(weights, dt),
        jnp.asarray(T_b_f, dt),
        sigmas,
        jnp.asarray(loss_scale, dt),
        jnp.asarray(bool(eye_in_hand)),
        (loss, solver, max_steps, float(rtol), float(atol)),
    )
    if pad:
        out = eqx.tree_at(
            lambda r: (r.residuals, r.robot_corrections),
            out,
            (out.residuals[:V], out.robot_corrections[:V]),
        )
    return cast_floats(out, out_dtype)

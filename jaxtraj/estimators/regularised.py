"""Regularised DCT: a roughness penalty on the high frequencies instead of a small k.

A DCT trajectory ``x(t) = sum_u phi_u(t) beta_u`` with ``phi_u = c_u cos(pi u tau)`` on
the span ``[t0, t1]`` (length L) has the exact roughness

    int_{t0}^{t1} ||x^(m)(t)||^2 dt = sum_u c_u^2 (pi u / L)^(2m) (L / 2) ||beta_u||^2,

because the cosines are orthogonal on the span. Adding ``lam`` times this to the least
squares (``penalty = lam * roughness_penalty(basis, m)`` in :func:`jaxtraj.reconstruct`)
lets k be large - up to the number of frames - without the ill-conditioning of a large
unregularised basis: the data decide how much high-frequency motion to keep. ``lam`` is
chosen by K-fold cross-validation on held-out reprojection error over a grid, weighted
by the conditioning gain beyond a healthy value as in
:func:`jaxtraj.estimators.select_k_cv` (a weak penalty on a fast, smooth camera path
reprojects well and is still far off along the rays).

Every choice of ``lam`` fits the track at every grid value from one simultaneous
diagonalisation (:func:`_diagonalise`). The constant coefficient is free (``R_0 = 0``) and
is eliminated by its Schur complement ``S`` in the normal matrix ``A``; with the other
coefficients scaled by the penalty, ``R^-1/2 S R^-1/2 = V diag(e) V^T`` gives

    (A + lam R)^-1 = E + H diag(1 / (e + lam)) H^T

for every ``lam`` at once (``E``: the constant's block ``A11^-1``; ``H`` fixed per track),
so each weight costs one matrix product instead of a factorisation:

* K-fold (the default): one eigendecomposition per fold's training frames gives the
  held-out points at every weight, and one of all frames gives the gain at every weight:
  ``folds + 1`` eigendecompositions of ``3k - 3`` per track instead of
  ``folds x G + G`` factorisations (the same choice up to rounding);
* generalised cross-validation (``criterion="gcv"`` of the batched driver): one
  eigendecomposition, ``GCV = n RSS / (n - edf)^2`` over the ``n`` ray-constraint rows
  with ``edf = 3 + sum_i e_i / (e_i + lam)`` (the hat matrix's trace), an estimate of
  the leave-one-out prediction error that needs no refit; GCV measures the residual of
  the ray constraints (pixels times depth), not pixels;
* the conditioning gain's bound (that of :func:`jaxtraj.reconstruct`) is the top
  eigenvalue of ``K diag(h) K^T`` with ``h = (1, 1, 1, e / (e + lam)^2)`` and ``K`` fixed
  per track.

The eigendecompositions are LAPACK calls, one track and one fold per loop step on a CPU,
never a batched call. Both criteria use the same gain-weighted rule; like every
criterion on the pixels they are blind along the rays, which the gain weighting and
:func:`flag_undetermined_depth` answer.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._batching import map_points, points_per_step
from .._checks import check_finite, check_shape, check_tracks, is_concrete
from .._linalg import cholesky_small, solve_triangular_small
from .._spd import top_eigenvalue
from ..basis import DCTBasis
from ..depth import camera_centres, depth_uncertainty, with_ray_bound
from ..solve import (
    MAX_DEPTH_UNCERTAINTY,
    MAX_RELATIVE_ERROR,
    Reconstruction,
    _assemble,
    _frame_blocks,
    _frame_spread,
    _per_step,
    _points_on_cores,
    _ray_checks,
    _reprojection_rms,
    _status,
    reconstruct,
)
from ._depth import flag_undetermined_depth
from .covariance import ReconstructionCovariance, dct_covariance
from .select_k import check_rule

__all__ = [
    "PenaltyChoice",
    "reconstruct_regularised",
    "reconstruct_regularised_points",
    "regularised_covariance",
    "roughness_penalty",
    "select_penalty_cv",
]


def roughness_penalty(basis: DCTBasis, order: int = 2) -> Float[Array, " k"]:
    """Per-coefficient weights ``w_u`` with ``sum_u w_u ||beta_u||^2`` equal to the
    integral of the squared ``order``-th time derivative of the trajectory over the span
    (units: 1 / time^(2 order - 1)). The constant (and, for order >= 2, no other) column
    is free: ``w_0 = 0``."""
    if order not in (1, 2, 3):
        raise ValueError(f"order: expected 1, 2 or 3, got {order}")
    length = basis.t1 - basis.t0
    u = jnp.arange(basis.k, dtype=length.dtype)
    c2 = jnp.where(u == 0, 1.0 / basis.size, 2.0 / basis.size) if basis.orthonormal else 1.0
    return c2 * (jnp.pi * u / length) ** (2 * order) * length / 2


class PenaltyChoice(eqx.Module):
    """Cross-validation of the penalty weight: the chosen ``lam``, the grid, the mean
    held-out reprojection RMS [px], the conditioning gain on all frames and the
    minimised criterion at each grid value. From the batched driver with a shared weight,
    ``tracks`` holds the indices of the tracks that were cross-validated (None
    otherwise). With ``criterion="gcv"`` ``cv_rms_px`` holds ``sqrt(GCV)``, the
    generalised cross-validation RMS of the ray-constraint residual (pixels times depth
    in the cameras' scale, see the module notes), not pixels."""

    lam: Float[Array, ""]
    grid: Float[Array, " G"]
    cv_rms_px: Float[Array, " G"]
    gain: Float[Array, " G"]
    criterion: Float[Array, " G"]
    tracks: Int[Array, " M"] | None = None


def _fold_masks(num_frames: int, folds: int) -> np.ndarray:
    """(folds, F) boolean masks of held-out frames, interleaved so that each fold spans
    the whole time range (held-out frames are interpolated, not extrapolated)."""
    return np.arange(num_frames)[None, :] % folds == np.arange(folds)[:, None]


def select_penalty_cv(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "F 2"],
    basis: DCTBasis,
    times: Float[ArrayLike, " F"],
    weights: Float[ArrayLike, " F"] | None = None,
    *,
    order: int = 2,
    grid: Float[ArrayLike, " G"] | None = None,
    folds: int = 5,
    rule: str = "gain_weighted",
    healthy_gain: float = 20.0,
) -> PenaltyChoice:
    """Choose ``lam`` by K-fold cross-validation on held-out reprojection error.

    Each fold's fit at every grid value comes from one eigendecomposition of its training
    frames' system (module notes), the folds in a loop. ``rule="reprojection"``
    picks the value with the smallest mean held-out RMS ``e``; ``rule="gain_weighted"``
    (default) the smallest ``e * max(1, gain / healthy_gain)``, with the conditioning gain
    of the penalised solve on all frames (the rule of
    :func:`jaxtraj.estimators.select_k_cv`, on the RMS instead of the mean square). The
    default grid spans 1e-4 to 1e10 (in units of squared pixel-algebraic residual per
    unit roughness) logarithmically.
    """
    check_shape("times", times, (np.shape(P)[0],), "one timestamp per frame of P")
    if folds < 2:
        raise ValueError(f"folds: expected >= 2, got {folds}")
    check_rule(rule, healthy_gain)
    F = np.shape(P)[0]
    dtype = jnp.result_type(jnp.asarray(P).dtype, jnp.float32)
    grid = jnp.logspace(-4, 10, 15, dtype=dtype) if grid is None else jnp.asarray(grid, dtype)
    check_shape("grid", grid, (None,), "(G,) penalty weights")
    w = jnp.ones(F, dtype) if weights is None else jnp.asarray(weights, dtype)
    rough = roughness_penalty(basis, order)
    Phi = basis(jnp.asarray(times, dtype))
    held = jnp.asarray(_fold_masks(F, folds))
    P = jnp.asarray(P, dtype)
    uv = jnp.where(w[:, None] > 0, jnp.asarray(uv, dtype), 0.0)
    healthy = healthy_gain if rule == "gain_weighted" else None
    return _cv(P, uv, Phi, w, rough, grid, held, healthy)


class _Diagonal(eqx.Module):
    """The penalised fit of one track at every weight from one eigendecomposition.

    The constant column (``rough[0] = 0``, coefficients 0-2) is eliminated by its Schur
    complement ``S`` and the other coefficients are scaled by the penalty: with
    ``R^-1/2 S R^-1/2 = V diag(ev) V^T``, ``(A + lam R)^-1 = E + H diag(1 / (ev + lam)) H^T``
    for every ``lam`` (``E``: ``A11^-1`` in the constant's block), so the coefficients at
    any weight cost one matrix product and no Cholesky factor of the whole system or
    triangular solve with a full right-hand side is needed."""

    ev: Array  # (3k - 3,) eigenvalues, >= 0
    H: Array  # (3k, 3k - 3)
    Cinv: Array  # (3, 3) inverse Cholesky factor of A11
    Eb: Array  # (3k,) E b
    z: Array  # (3k - 3,) H^T b

    def coefficients(self, grid):
        """(3k, G) coefficients at the weights ``grid``."""
        return self.Eb[:, None] + self.H @ (self.z[:, None] / (self.ev[:, None] + grid[None, :]))

    def gain(self, Lg, spread_hi, grid):
        """(G,) the solver's conditioning-gain bound at each weight: the top eigenvalue of
        ``R N^-1 A N^-1 R^T = K diag(h) K^T`` (``Theta^T Theta = R^T R``, 8 Lanczos steps)."""
        n3, dtype = self.H.shape[0], self.H.dtype
        k = n3 // 3
        cols = jnp.concatenate([jnp.zeros((n3, 3), dtype).at[:3].set(self.Cinv.T), self.H], 1)
        K = jnp.einsum("ji,jan->ian", Lg, cols.reshape(k, 3, n3)).reshape(n3, n3)
        KtK = K.T @ K
        v0 = 1.0 + 0.1 * jnp.modf(jnp.arange(n3) * 0.6180339887498949)[0].astype(dtype)
        ev = self.ev

        def top(lam):
            h = jnp.concatenate([jnp.ones(3, dtype), jnp.sqrt(ev) / (ev + lam)])
            return top_eigenvalue(lambda v: h * (KtK @ (h * v)), v0, 8)

        return jnp.sqrt(jnp.maximum(jax.vmap(top)(grid), 0.0) * spread_hi)


def _diagonalise(P, uv, Phi, w, rough) -> _Diagonal:
    """:class:`_Diagonal` of one track (``uv`` zero where ``w`` is; ``rough[0] = 0``, the
    others positive, as :func:`roughness_penalty` gives). One symmetric eigendecomposition
    (LAPACK): call it unbatched on a CPU (a loop over tracks and folds)."""
    dtype = P.dtype
    eps = jnp.finfo(dtype).eps
    A, b = _assemble(P, uv, Phi, w, None)
    A11, A12, A22 = A[:3, :3], A[:3, 3:], A[3:, 3:]
    C = cholesky_small(A11 + eps * jnp.trace(A11) * jnp.eye(3, dtype=dtype))  # ridge: safety
    Cinv = solve_triangular_small(C, jnp.eye(3, dtype=dtype))
    T = Cinv.T @ (Cinv @ A12)  # A11^-1 A12
    rs = jax.lax.rsqrt(jnp.repeat(rough[1:], 3))  # R^-1/2 of the penalised coefficients
    M = (A22 - A12.T @ T) * rs[:, None] * rs[None, :]
    ev, V = jnp.linalg.eigh(0.5 * (M + M.T))
    H = jnp.concatenate([-(T * rs[None, :]) @ V, rs[:, None] * V])
    Eb = jnp.zeros(A.shape[0], dtype).at[:3].set(Cinv.T @ (Cinv @ b[:3]))
    return _Diagonal(ev=jnp.maximum(ev, 0.0), H=H, Cinv=Cinv, Eb=Eb, z=H.T @ b)


def _points_at(Phi, diag: _Diagonal, grid):
    """(F, 3, G) fitted positions and (3k, G) coefficients at every weight of ``grid``."""
    B = diag.coefficients(grid)
    return jnp.einsum("fu,uag->fag", Phi, B.reshape(Phi.shape[1], 3, -1)), B


@eqx.filter_jit
def _cv(P, uv, Phi, w, rough, grid, held, healthy_gain):
    """K-fold choice of one track: each fold's fit at every weight from one
    eigendecomposition of its training frames (:func:`_diagonalise`), the folds in a loop
    (unbatched LAPACK calls), and the gain at every weight from that of all frames."""
    Lg = jnp.linalg.cholesky(Phi.T @ Phi)  # Theta^T Theta = Lg Lg^T (k x k: negligible)

    def held_out_rms(mask):
        X, _ = _points_at(Phi, _diagonalise(P, uv, Phi, jnp.where(mask, 0.0, w), rough), grid)
        rms = jax.vmap(lambda x: _reprojection_rms(P, uv, x, mask & (w > 0)), in_axes=2)
        return rms(X)

    score = jnp.mean(jax.lax.map(held_out_rms, held), axis=0)
    _, _, Q, _ = _frame_blocks(P, uv, w)
    gain = _diagonalise(P, uv, Phi, w, rough).gain(Lg, _frame_spread(Q, w)[1], grid)
    crit = score if healthy_gain is None else score * jnp.maximum(1.0, gain / healthy_gain)
    crit = jnp.where(jnp.isfinite(crit), crit, jnp.inf)
    return PenaltyChoice(
        lam=grid[jnp.argmin(crit)], grid=grid, cv_rms_px=score, gain=gain, criterion=crit
    )


#: reprojection RMS [px] above which a regularised fit is DEGENERATE (see
#: :func:`reconstruct_regularised`). On the tests' robot scenes (F = 150, k = 60) the fits
#: with status OK reproject at up to 0.85 px RMS with 0.3 px noise and 1.6 px with 1 px
#: noise; fits collapsed towards a slow camera at 8-5986 px.
MAX_RMS_PX = 5.0


def _check_max_rms(max_rms_px) -> None:
    if isinstance(max_rms_px, bool) or not (float(max_rms_px) > 0):
        raise ValueError(
            f"max_rms_px: expected a positive number of pixels (inf turns the test off), "
            f"got {max_rms_px!r}"
        )


def reconstruct_regularised(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "F 2"],
    times: Float[ArrayLike, " F"],
    weights: Float[ArrayLike, " F"] | None = None,
    *,
    k: int | None = None,
    order: int = 2,
    lam: float | None = None,
    folds: int = 5,
    rule: str = "gain_weighted",
    max_rms_px: float = MAX_RMS_PX,
) -> tuple[Reconstruction, DCTBasis, PenaltyChoice | None]:
    """Regularised DCT reconstruction: a generous k (default ``min(F, 60)``) with a
    roughness penalty whose weight is chosen by cross-validation (``rule``: see
    :func:`select_penalty_cv`) unless ``lam`` is given.

    The status is ``DEGENERATE`` where the gain exceeds 20, where the depth
    uncertainty ``kappa`` of the penalty's order exceeds 0.08, or where the fit's
    reprojection RMS exceeds ``max_rms_px`` (:data:`MAX_RMS_PX` by default; ``inf``
    turns the test off): a fit that misses its own pixels by that much has collapsed towards
    the cameras (see :func:`flag_undetermined_depth`), not measured the point.

    Returns the :class:`~jaxtraj.Reconstruction`, the basis (evaluate it at other times
    for velocity or prediction) and the cross-validation record (None if ``lam`` given).
    """
    _check_max_rms(max_rms_px)
    F = np.shape(P)[0]
    k = min(F, 60) if k is None else k
    basis = DCTBasis.from_times(times, k)
    choice = None
    if lam is None:
        choice = select_penalty_cv(
            P, uv, basis, times, weights, order=order, folds=folds, rule=rule
        )
        lam = choice.lam
    pen = lam * roughness_penalty(basis, order)
    res = reconstruct(P, uv, basis(jnp.asarray(times)), weights, penalty=pen)
    return flag_undetermined_depth(res, P, times, order, max_rms_px=max_rms_px), basis, choice


def regularised_covariance(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "F 2"],
    times: Float[ArrayLike, " F"],
    basis: DCTBasis,
    coeffs: Float[ArrayLike, "k 3"],
    lam: Float[ArrayLike, ""],
    weights: Float[ArrayLike, " F"] | None = None,
    *,
    order: int = 2,
    pixel_sigma: float | Float[ArrayLike, " F"] = 1.0,
    pose_cov: Float[ArrayLike, "F 6 6"] | None = None,
) -> ReconstructionCovariance:
    """Covariance of a regularised DCT fit (:func:`reconstruct_regularised`: its result's
    ``coeffs``, its ``basis`` and the weight ``lam``, e.g. ``choice.lam``).

    Three parts. The penalty read as a prior on the coefficients
    (:func:`~jaxtraj.estimators.dct_covariance` with ``penalty``: the posterior form, which
    holds the penalty's spread as well as the noise's); the model-error term of
    :func:`~jaxtraj.estimators.dct_covariance`, which sees what the fit misses across the
    rays; and, along the rays, where the pixels see nothing and the penalty sets the depth,
    a standard deviation of at least ``kappa |x - c| / 2`` (``kappa``: the depth
    uncertainty of the penalty's ``order``, :func:`jaxtraj.depth.depth_uncertainty`, the
    quantity that flags the fit; :func:`jaxtraj.depth.with_ray_bound`), as
    :func:`jaxtraj.estimate_points` does. Without the last part a status-OK fit on a limb-like
    point under a 20 deg/frame orbit was 36.7 mm off with a reported 19 mm (posterior) or
    2.6 mm (noise alone); with it, 0.36 of the reported standard deviation.

    jit- and vmap-compatible (``order`` static). A negative or non-finite ``lam`` raises
    (when concrete).
    """
    if is_concrete(lam) and not np.all(np.isfinite(lam) & (np.asarray(lam) >= 0)):
        raise ValueError(f"lam: expected a finite penalty weight >= 0, got {lam!r}")
    t = jnp.asarray(times)
    rows = basis(t)
    pen = jnp.asarray(lam, rows.dtype) * roughness_penalty(basis, order)
    cov = dct_covariance(
        P, uv, rows, coeffs, weights, pixel_sigma=pixel_sigma, pose_cov=pose_cov, penalty=pen
    )
    x = rows @ jnp.asarray(coeffs, rows.dtype)
    C = camera_centres(jnp.asarray(P, rows.dtype))
    kappa = depth_uncertainty(x, C, t.astype(rows.dtype), order)
    return ReconstructionCovariance(
        coeffs=cov.coeffs, points=with_ray_bound(cov.points, x - C, 0.5 * kappa)
    )


#: tracks per step of the cross-validation loop on a CPU (one: each fold's
#: eigendecomposition is then one unbatched LAPACK call) and on an accelerator (each track
#: holds a few 3k x 3k matrices per fold, so all at once would not fit for large N)
CV_BATCH = 1
CV_BATCH_ACCELERATOR = 64
#: the conditioning gain above which the drivers' fits are DEGENERATE (the solver's default)
MAX_GAIN = 20.0
#: how the batched driver chooses the penalty weight (see reconstruct_regularised_points)
CRITERIA = ("kfold", "gcv")


@functools.partial(jax.jit, static_argnames=("healthy_gain", "cv_tracks", "cv_per_step"))
def _kfold_choice(P, uv, Phi, w, rough, grid, held, healthy_gain, cv_tracks, cv_per_step):
    """K-fold choice per track, or (``cv_tracks``: indices of the tracks whose mean
    criterion decides) one shared weight; the fits are left to the solver, which can then
    run on every core (:func:`jaxtraj._batching.on_cores`; this choice calls LAPACK and
    runs once)."""
    sel = slice(None) if cv_tracks is None else np.asarray(cv_tracks)
    choice = map_points(
        lambda a: _cv(P, a[0], Phi, a[1], rough, grid, held, healthy_gain),
        (uv[sel], w[sel]),
        cv_per_step,
    )
    return choice if cv_tracks is None else _shared(choice, grid, cv_tracks)


def _shared(choice: PenaltyChoice, grid, cv_tracks) -> PenaltyChoice:
    """One weight for all points: the grid value with the smallest criterion averaged over
    the cross-validated tracks ``cv_tracks`` (their per-track records are kept)."""
    crit = jnp.mean(jnp.where(jnp.isfinite(choice.criterion), choice.criterion, 1e300), 0)
    best = grid[jnp.argmin(crit)]
    return PenaltyChoice(
        lam=jnp.broadcast_to(best, choice.lam.shape),
        grid=choice.grid,
        cv_rms_px=choice.cv_rms_px,
        gain=choice.gain,
        criterion=choice.criterion,
        tracks=jnp.asarray(cv_tracks, jnp.int32),
    )


#: tracks per step of the GCV loop: one on a CPU (each step's eigendecomposition is then
#: one unbatched LAPACK call), 64 on an accelerator (each track holds a few 3k x 3k
#: matrices, so all at once would not fit for large N)
GCV_BATCH = 1
GCV_BATCH_ACCELERATOR = 64


def _gcv_track(P, uv, Phi, Lg, w, rough, grid, healthy_gain, max_gain):
    """Generalised cross-validation of one track over ``grid`` and its fit at the chosen
    weight (module notes; the fit at every weight from :func:`_diagonalise`):
    ``(Reconstruction, PenaltyChoice)``."""
    k = Phi.shape[1]
    observed = w > 0
    _, _, Q, q = _frame_blocks(P, uv, w)
    rows = 2 * jnp.sum(observed)
    diag = _diagonalise(P, uv, Phi, w, rough)
    X, B = _points_at(Phi, diag, grid)
    r = q[:, :, None] - jnp.sum(Q[:, :, :, None] * X[:, None, :, :], axis=2)  # (F, 2, G)
    rss = jnp.sum(w[:, None, None] * r * r, axis=(0, 1))
    edf = 3 + jnp.sum(diag.ev[:, None] / (diag.ev[:, None] + grid[None, :]), axis=0)
    dof = rows - edf
    score = jnp.sqrt(jnp.where(dof > 0, rows * rss / jnp.where(dof > 0, dof, 1.0) ** 2, jnp.inf))
    gain = diag.gain(Lg, _frame_spread(Q, w)[1], grid)
    crit = score if healthy_gain is None else score * jnp.maximum(1.0, gain / healthy_gain)
    crit = jnp.where(jnp.isfinite(crit), crit, jnp.inf)
    i = jnp.argmin(crit)
    beta = B[:, i]
    coeffs = beta.reshape(k, 3)
    points = X[:, :, i]
    finite = jnp.all(jnp.isfinite(uv), axis=1) | ~observed
    kappa, rel = _ray_checks(P, points, Q, observed, gain[i])
    degenerate = (gain[i] > max_gain) | ~jnp.isfinite(gain[i]) | ~jnp.all(jnp.isfinite(beta))
    degenerate = degenerate | ~(kappa <= MAX_DEPTH_UNCERTAINTY) | (rel > MAX_RELATIVE_ERROR)
    n_obs = jnp.sum(observed).astype(jnp.int32)
    res = Reconstruction(
        coeffs=coeffs,
        points=points,
        rms_px=_reprojection_rms(P, uv, points, observed),
        gain=gain[i],
        num_observed=n_obs,
        status=_status(finite, P, n_obs, k, True, degenerate),
        depth_uncertainty=kappa,
        relative_error=rel,
    )
    choice = PenaltyChoice(lam=grid[i], grid=grid, cv_rms_px=score, gain=gain, criterion=crit)
    return res, choice


@functools.partial(jax.jit, static_argnames=("healthy_gain", "per_step"))
def _regularised_points_gcv(P, uv, Phi, w, rough, grid, healthy_gain, per_step):
    Lg = jnp.linalg.cholesky(Phi.T @ Phi)  # Theta^T Theta = Lg Lg^T, shared by the tracks
    max_gain = jnp.asarray(MAX_GAIN, P.dtype)
    return map_points(
        lambda a: _gcv_track(P, a[0], Phi, Lg, a[1], rough, grid, healthy_gain, max_gain),
        (uv, w),
        per_step,
    )


def _spread_tracks(n: int, m: int | None) -> tuple[int, ...]:
    """Indices of ``min(m, n)`` tracks spread evenly over ``0..n-1`` (all for None)."""
    if m is None or m >= n:
        return tuple(range(n))
    return tuple(int(i) for i in np.unique(np.round(np.linspace(0, n - 1, m)).astype(int)))


def reconstruct_regularised_points(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "N F 2"],
    times: Float[ArrayLike, " F"],
    weights: Float[ArrayLike, "N F"] | None = None,
    *,
    k: int | None = None,
    order: int = 2,
    lam: float | None = None,
    shared: bool = False,
    cv_points: int | None = 16,
    grid: Float[ArrayLike, " G"] | None = None,
    folds: int = 5,
    rule: str = "gain_weighted",
    healthy_gain: float = 20.0,
    criterion: str = "kfold",
    max_rms_px: float = MAX_RMS_PX,
) -> tuple[Reconstruction, DCTBasis, PenaltyChoice | None]:
    """:func:`reconstruct_regularised` for N points seen by the same cameras: one compiled
    program per shape for the weight's choice (LAPACK eigendecompositions, one call) and
    one for the fits (on a CPU split over the cores, :func:`jaxtraj._batching.on_cores`).

    The penalty weight is chosen by cross-validation per point (``shared=False``), or once
    for all points (``shared=True``: the grid value with the smallest criterion averaged
    over ``cv_points`` tracks spread evenly over the batch, all of them if fewer or with
    ``cv_points=None``), unless ``lam`` is given. Returns the batched
    :class:`~jaxtraj.Reconstruction` (leading axis N), the basis and the
    :class:`PenaltyChoice` of each cross-validated track (None if ``lam`` given; with
    ``shared`` every ``lam`` is the shared one and ``tracks`` says which tracks were
    cross-validated).

    ``criterion``: ``"kfold"`` (default) cross-validates with ``folds`` interleaved folds
    of held-out frames; ``"gcv"`` uses generalised cross-validation from one
    eigendecomposition per track (module notes; ``folds`` is then unused), and with a
    weight per point returns the fit at the chosen weight from the same decomposition.
    ``max_rms_px``: as for :func:`reconstruct_regularised` (the statuses are the same).

    Cost: per cross-validated track, K-fold: ``folds + 1`` symmetric eigendecompositions
    of ``3k - 3`` rows (module notes) and a few matrix products per grid value; these, not
    the assembly, dominate for the default k = min(F, 60): about 26-31 ms per track at
    F = 150 on 2 cores (Intel Xeon, 5 folds, 15 grid values). GCV: one eigendecomposition
    and a few matrix products, about 5-6 ms per track. A shared weight pays the choice for
    ``cv_points`` tracks only, then one solve per point (README: per-point cost of the
    batched drivers). A shared weight suits points of one rigid workpiece (the same
    motion, the same cameras and noise); points that move differently want their own.
    """
    if np.ndim(uv) != 3:
        raise ValueError(f"uv: expected shape (N, F, 2), got {np.shape(uv)}")
    F = np.shape(P)[0]
    check_shape("P", P, (None, 3, 4), "one 3x4 projection matrix per frame")
    check_shape("uv", uv, (None, F, 2), f"(N, F, 2): one pixel per frame of P, F={F}")
    check_shape("times", times, (F,), "one timestamp per frame of P")
    if weights is not None:
        check_shape("weights", weights, np.shape(uv)[:2], "(N, F): one weight per pixel")
    check_finite("P", P, hint="Projection matrices must be finite.")
    check_tracks(uv, weights)
    if folds < 2:
        raise ValueError(f"folds: expected >= 2, got {folds}")
    if cv_points is not None and (
        isinstance(cv_points, bool) or not isinstance(cv_points, (int, np.integer)) or cv_points < 1
    ):
        raise ValueError(f"cv_points: expected a positive int or None, got {cv_points!r}")
    check_rule(rule, healthy_gain)
    if criterion not in CRITERIA:
        raise ValueError(f"criterion: expected one of {CRITERIA}, got {criterion!r}")
    _check_max_rms(max_rms_px)
    k = min(F, 60) if k is None else k
    dtype = jnp.result_type(jnp.asarray(P).dtype, jnp.float32)
    basis = DCTBasis.from_times(jnp.asarray(times, dtype), k)
    rough = roughness_penalty(basis, order)
    Phi = basis(jnp.asarray(times, dtype))
    P = jnp.asarray(P, dtype)
    w = jnp.ones(np.shape(uv)[:2], dtype) if weights is None else jnp.asarray(weights, dtype)
    uv = jnp.where(w[..., None] > 0, jnp.asarray(uv, dtype), 0.0)
    per_step = _per_step(uv)

    def flagged(res, choice):
        return flag_undetermined_depth(res, P, times, order, max_rms_px=max_rms_px), basis, choice

    def solved(pen, choice):  # every point with the penalty ``pen``: shared (k,) or (N, k)
        max_gain = jnp.asarray(MAX_GAIN, dtype)
        res = _points_on_cores(P, uv, Phi, w, max_gain, 1, True, pen, per_step)
        return flagged(res, choice)

    if lam is not None:
        return solved(jnp.asarray(lam, dtype) * rough, None)
    grid = jnp.logspace(-4, 10, 15, dtype=dtype) if grid is None else jnp.asarray(grid, dtype)
    check_shape("grid", grid, (None,), "(G,) penalty weights")
    held = jnp.asarray(_fold_masks(F, folds))
    healthy = float(healthy_gain) if rule == "gain_weighted" else None
    tracks = _spread_tracks(np.shape(uv)[0], cv_points) if shared else None
    if criterion == "gcv":
        gcv_per_step = points_per_step(GCV_BATCH, GCV_BATCH_ACCELERATOR, uv)
        if tracks is None:
            return flagged(
                *_regularised_points_gcv(P, uv, Phi, w, rough, grid, healthy, gcv_per_step)
            )
        sel = np.asarray(tracks)
        _, choice = _regularised_points_gcv(
            P, uv[sel], Phi, w[sel], rough, grid, healthy, gcv_per_step
        )
        choice = _shared(choice, grid, tracks)
        return solved(choice.lam[0] * rough, choice)
    cv_per_step = points_per_step(CV_BATCH, CV_BATCH_ACCELERATOR, uv)
    choice = _kfold_choice(P, uv, Phi, w, rough, grid, held, healthy, tracks, cv_per_step)
    if tracks is None:
        return solved(choice.lam[:, None] * rough[None, :], choice)  # a weight per point
    return solved(choice.lam[0] * rough, choice)

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

* K-fold (the default, 5 interleaved folds of frames): the fit on the other frames
  follows from the fit on all of them by the exact update for leaving a block of rows
  out (:func:`_held_out_rms`), one factorisation of the fold's ``2m`` held-out rows per
  weight: one eigendecomposition of ``3k - 3`` per track for all folds and weights (the
  same choice as refitting each fold up to rounding). ``folds = F`` is
  leave-one-frame-out: 2 x 2 blocks, all solved at once without LAPACK, about as cheap as
  GCV;
* generalised cross-validation (``criterion="gcv"`` of the batched driver): one
  eigendecomposition, ``GCV = n RSS / (n - edf)^2`` over the ``n`` ray-constraint rows
  with ``edf = 3 + sum_i e_i / (e_i + lam)`` (the hat matrix's trace), an estimate of
  the leave-one-out prediction error that needs no refit; GCV measures the residual of
  the ray constraints (pixels times depth), not pixels;
* the conditioning gain's bound (that of :func:`jaxtraj.reconstruct`) is the top
  eigenvalue of ``K diag(h) K^T`` with ``h = (1, 1, 1, e / (e + lam)^2)`` and ``K`` fixed
  per track.

The eigendecompositions are LAPACK calls, one track per loop step on a CPU, never a
batched call, and so are the held-out factorisations of folds of more than 8 frames (one
fold and weight per step); the batched driver splits its tracks over the CPU cores and
runs them with one BLAS thread (:mod:`jaxtraj._batching`). Both criteria use the same
gain-weighted rule; like every criterion on the pixels they are blind along the rays,
which the gain weighting and :func:`flag_undetermined_depth` answer.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._batching import map_points, on_cores, points_per_step, with_one_blas_thread
from .._checks import check_finite, check_shape, check_tracks, is_concrete
from .._linalg import cholesky_small, solve_spd_small, solve_triangular_small
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
    _sym_index,
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


def _fold_frames(num_frames: int, folds: int) -> tuple[np.ndarray, np.ndarray]:
    """(folds, m) indices of each fold's held-out frames and (folds, m) which are real
    (``m = ceil(F / folds)``; a shorter fold is padded with frame 0, not real). Folds are
    interleaved (frame ``f`` is in fold ``f % folds``), so that each spans the whole time
    range (held-out frames are interpolated, not extrapolated)."""
    m = -(-num_frames // folds)
    frames = np.arange(folds)[:, None] + folds * np.arange(m)[None, :]
    real = frames < num_frames
    return np.where(real, frames, 0), real


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

    Each fold's fit at every grid value follows from the fit on all frames (one
    eigendecomposition, module notes). ``folds`` interleaved folds of frames, 2 to F
    (``folds = F``: leave-one-frame-out, the cheapest); the score is the mean over the
    folds holding an observed frame. ``rule="reprojection"``
    picks the value with the smallest mean held-out RMS ``e``; ``rule="gain_weighted"``
    (default) the smallest ``e * max(1, gain / healthy_gain)``, with the conditioning gain
    of the penalised solve on all frames (the rule of
    :func:`jaxtraj.estimators.select_k_cv`, on the RMS instead of the mean square). The
    default grid spans 1e-4 to 1e10 (in units of squared pixel-algebraic residual per
    unit roughness) logarithmically.
    """
    check_shape("times", times, (np.shape(P)[0],), "one timestamp per frame of P")
    F = np.shape(P)[0]
    _check_folds(folds, F)
    check_rule(rule, healthy_gain)
    dtype = jnp.result_type(jnp.asarray(P).dtype, jnp.float32)
    grid = jnp.logspace(-4, 10, 15, dtype=dtype) if grid is None else jnp.asarray(grid, dtype)
    check_shape("grid", grid, (None,), "(G,) penalty weights")
    w = jnp.ones(F, dtype) if weights is None else jnp.asarray(weights, dtype)
    rough = roughness_penalty(basis, order)
    Phi = basis(jnp.asarray(times, dtype))
    P = jnp.asarray(P, dtype)
    uv = jnp.where(w[:, None] > 0, jnp.asarray(uv, dtype), 0.0)
    healthy = healthy_gain if rule == "gain_weighted" else None
    return with_one_blas_thread(_cv, P, uv, Phi, w, rough, grid, folds, healthy)


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

    def factor(self):
        """(3k, 3k) ``K`` with ``(A + lam R)^-1 = K diag(h) K^T``, ``h = (1, 1, 1,
        1 / (ev + lam))``: the constant's inverse Cholesky factor beside ``H``."""
        n3 = self.H.shape[0]
        return jnp.concatenate(
            [jnp.zeros((n3, 3), self.H.dtype).at[:3].set(self.Cinv.T), self.H], 1
        )

    def gain(self, Lg, spread_hi, grid):
        """(G,) the solver's conditioning-gain bound at each weight: the top eigenvalue of
        ``R N^-1 A N^-1 R^T = K diag(h) K^T`` (``Theta^T Theta = R^T R``, 8 Lanczos steps)."""
        n3, dtype = self.H.shape[0], self.H.dtype
        k = n3 // 3
        K = jnp.einsum("ji,jan->ian", Lg, self.factor().reshape(k, 3, n3)).reshape(n3, n3)
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


#: largest held-out block (2 rows per frame of a fold) solved by the written-out Cholesky
#: of :mod:`jaxtraj._linalg` instead of LAPACK: folds of up to 8 frames
SMALL_FOLD_ROWS = 16
#: folds of up to this many frames form their blocks from products of row pairs, one
#: matrix product for all folds and weights (leave-one-frame-out: 5.2 against 5.6 ms per
#: track at F = 150, k = 60; slower than the batched products from 5 frames a fold)
PAIRED_FOLD_FRAMES = 2


def _held_out_rms(P, uv, Phi, w, Q, q, diag: _Diagonal, X, grid, folds: int):
    """(folds, G) held-out reprojection RMS [px] of each fold at each weight and (folds,)
    whether the fold holds an observed frame (the mean is over those), from the fit
    on all frames (:func:`_diagonalise`, ``X`` its points at the weights; ``Q, q`` the
    frames' ray constraints, :func:`jaxtraj.solve._frame_blocks`) by the exact
    update for leaving out a block of rows: with ``M = A + lam R`` and ``B`` the fold's
    weighted ray-constraint rows (2 per frame), the fit on the other frames is

        beta_-h = beta - M^-1 B^T (I - B M^-1 B^T)^-1 (y - B beta),

    and ``M^-1 = K diag(h) K^T`` (``K``: the constant's inverse Cholesky factor beside
    ``H``, :meth:`_Diagonal.factor`) for every weight. Per fold and weight this is
    one factorisation of ``2m`` rows (m: the fold's frames) instead of an
    eigendecomposition of ``3k - 3`` rows per fold. Where the held-out frames are needed
    to determine the fit, ``I - B M^-1 B^T`` is singular and the RMS is inf."""
    k = Phi.shape[1]
    n3, dtype = 3 * k, P.dtype
    frames, real = _fold_frames(P.shape[0], folds)  # (folds, m), static
    m = frames.shape[1]
    U = jnp.einsum("fu,uan->fan", Phi, diag.factor().reshape(k, 3, n3))  # Theta_f K: (F, 3, 3k)
    sw = jnp.sqrt(w)
    B = sw[:, None, None] * jnp.sum(Q[:, :, :, None] * U[:, None, :, :], axis=2)  # (F, 2, 3k)
    r = sw[:, None, None] * (q[:, :, None] - jnp.sum(Q[:, :, :, None] * X[:, None], axis=2))
    h = jnp.concatenate(
        [jnp.ones((grid.shape[0], 3), dtype), 1.0 / (diag.ev[None, :] + grid[:, None])], 1
    )  # (G, 3k)
    real_rows = jnp.asarray(np.repeat(real, 2, axis=1), dtype)  # (folds, 2m)
    Bh = B[frames].reshape(folds, 2 * m, n3) * real_rows[:, :, None]
    rh = jnp.moveaxis(r[frames].reshape(folds, 2 * m, -1), 2, 1) * real_rows[:, None, :]
    G, eye = grid.shape[0], jnp.eye(2 * m, dtype=dtype)
    Uh = U[frames].reshape(folds, 3 * m, n3)
    if m <= PAIRED_FOLD_FRAMES:  # every entry needed, at every weight, in one product
        i, j = np.triu_indices(2 * m)  # the distinct entries of B M^-1 B^T
        prods = jnp.concatenate(
            [Bh[:, i] * Bh[:, j], (Uh[:, :, None] * Bh[:, None]).reshape(folds, -1, n3)], 1
        )
        vals = jnp.moveaxis((prods.reshape(-1, n3) @ h.T).reshape(folds, -1, G), 2, 1)
        Hh = vals[..., : i.size][..., _sym_index(2 * m)]  # (folds, G, 2m, 2m)
        cross = vals[..., i.size :].reshape(folds, G, 3 * m, 2 * m)  # Theta M^-1 B^T
    else:
        Hh = jnp.einsum("sin,gn,sjn->sgij", Bh, h, Bh)
    systems = (eye - Hh.reshape(-1, 2 * m, 2 * m), rh.reshape(-1, 2 * m))
    if 2 * m <= SMALL_FOLD_ROWS:  # written-out Cholesky, all folds and weights at once
        s = jax.vmap(solve_spd_small)(*systems)
    else:  # one fold and weight per step: an unbatched LAPACK call

        def solve(a):
            return jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(a[0]), True), a[1])

        s = jax.lax.map(solve, systems)
    s = s.reshape(folds, G, 2 * m)
    if m <= PAIRED_FOLD_FRAMES:
        shift = jnp.sum(cross * s[:, :, None, :], axis=3)
    else:
        shift = jnp.einsum("sin,sgn->sgi", Uh, h * jnp.einsum("sin,sgi->sgn", Bh, s))
    shift = shift.reshape(folds, G, m, 3)
    Xh = jnp.moveaxis(X[frames], 3, 1) - shift  # (folds, G, m, 3)
    observed = jnp.asarray(real) & (w[frames] > 0)
    rms = jax.vmap(
        jax.vmap(_reprojection_rms, in_axes=(None, None, 0, None)), in_axes=(0, 0, 0, 0)
    )(P[frames], uv[frames], Xh, observed)
    return jnp.where(jnp.isfinite(rms), rms, jnp.inf), jnp.any(observed, axis=1)


class _Scored(eqx.Module):
    """One track's criterion over the grid and its fit at every weight."""

    X: Array  # (F, 3, G) points
    B: Array  # (3k, G) coefficients
    Q: Array  # (F, 2, 3) ray constraints
    score: Array  # (G,) held-out RMS [px] (K-fold) or sqrt(GCV)
    gain: Array  # (G,)
    criterion: Array  # (G,)

    def choice(self, grid) -> PenaltyChoice:
        return PenaltyChoice(
            lam=grid[jnp.argmin(self.criterion)],
            grid=grid,
            cv_rms_px=self.score,
            gain=self.gain,
            criterion=self.criterion,
        )


def _score(P, uv, Phi, Lg, w, rough, grid, healthy_gain, folds: int | None) -> _Scored:
    """K-fold (``folds``, static) or, for None, generalised cross-validation of one track
    over ``grid``, all from one eigendecomposition of all frames (:func:`_diagonalise`):
    the fit and the gain at every weight, each fold's held-out points by
    :func:`_held_out_rms`, GCV as in the module notes."""
    diag = _diagonalise(P, uv, Phi, w, rough)
    X, B = _points_at(Phi, diag, grid)
    _, _, Q, q = _frame_blocks(P, uv, w)
    if folds is None:
        rows = 2 * jnp.sum(w > 0)
        r = q[:, :, None] - jnp.sum(Q[:, :, :, None] * X[:, None, :, :], axis=2)  # (F, 2, G)
        rss = jnp.sum(w[:, None, None] * r * r, axis=(0, 1))
        edf = 3 + jnp.sum(diag.ev[:, None] / (diag.ev[:, None] + grid[None, :]), axis=0)
        dof = rows - edf
        gcv = rows * rss / jnp.where(dof > 0, dof, 1.0) ** 2
        score = jnp.sqrt(jnp.where(dof > 0, gcv, jnp.inf))
    else:
        rms, counted = _held_out_rms(P, uv, Phi, w, Q, q, diag, X, grid, folds)
        score = jnp.sum(jnp.where(counted[:, None], rms, 0.0), 0) / jnp.maximum(jnp.sum(counted), 1)
    gain = diag.gain(Lg, _frame_spread(Q, w)[1], grid)
    crit = score if healthy_gain is None else score * jnp.maximum(1.0, gain / healthy_gain)
    crit = jnp.where(jnp.isfinite(crit), crit, jnp.inf)
    return _Scored(X, B, Q, score, gain, crit)


@eqx.filter_jit
def _cv(P, uv, Phi, w, rough, grid, folds, healthy_gain):
    """K-fold choice of one track (``folds`` static; :func:`_score`)."""
    Lg = jnp.linalg.cholesky(Phi.T @ Phi)  # Theta^T Theta = Lg Lg^T (k x k: negligible)
    return _score(P, uv, Phi, Lg, w, rough, grid, healthy_gain, folds).choice(grid)


#: reprojection RMS [px] above which a regularised fit is DEGENERATE (see
#: :func:`reconstruct_regularised`). On the tests' robot scenes (F = 150, k = 60) the fits
#: with status OK reproject at up to 0.85 px RMS with 0.3 px noise and 1.6 px with 1 px
#: noise; fits collapsed towards a slow camera at 8-5986 px.
MAX_RMS_PX = 5.0


def _check_folds(folds, num_frames: int) -> None:
    if isinstance(folds, bool) or not isinstance(folds, (int, np.integer)):
        raise ValueError(f"folds: expected an int, got {folds!r}")
    if not 2 <= folds <= num_frames:
        raise ValueError(
            f"folds: expected 2 <= folds <= F = {num_frames} (F: leave-one-frame-out), got {folds}"
        )


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


#: tracks per step of the choice's loop on a CPU (one: each eigendecomposition is then one
#: unbatched LAPACK call) and on an accelerator (each track holds a few 3k x 3k matrices,
#: so all at once would not fit for large N)
CV_BATCH = 1
CV_BATCH_ACCELERATOR = 64
#: the conditioning gain above which the drivers' fits are DEGENERATE (the solver's default)
MAX_GAIN = 20.0
#: how the batched driver chooses the penalty weight (see reconstruct_regularised_points)
CRITERIA = ("kfold", "gcv")


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


def _chosen_track(P, uv, Phi, Lg, w, rough, grid, healthy_gain, max_gain, folds):
    """The choice of one track (:func:`_score`; ``folds`` None for GCV) and its fit at the
    chosen weight from the same decomposition: ``(Reconstruction, PenaltyChoice)``."""
    k = Phi.shape[1]
    observed = w > 0
    sc = _score(P, uv, Phi, Lg, w, rough, grid, healthy_gain, folds)
    i = jnp.argmin(sc.criterion)
    gain, beta, points = sc.gain[i], sc.B[:, i], sc.X[:, :, i]
    finite = jnp.all(jnp.isfinite(uv), axis=1) | ~observed
    kappa, rel = _ray_checks(P, points, sc.Q, observed, gain)
    degenerate = (gain > max_gain) | ~jnp.isfinite(gain) | ~jnp.all(jnp.isfinite(beta))
    degenerate = degenerate | ~(kappa <= MAX_DEPTH_UNCERTAINTY) | (rel > MAX_RELATIVE_ERROR)
    n_obs = jnp.sum(observed).astype(jnp.int32)
    res = Reconstruction(
        coeffs=beta.reshape(k, 3),
        points=points,
        rms_px=_reprojection_rms(P, uv, points, observed),
        gain=gain,
        num_observed=n_obs,
        status=_status(finite, P, n_obs, k, True, degenerate),
        depth_uncertainty=kappa,
        relative_error=rel,
    )
    return res, sc.choice(grid)


@functools.partial(jax.jit, static_argnames=("healthy_gain", "folds", "per_step"))
def _chosen_points(P, uv, Phi, w, rough, grid, healthy_gain, folds, per_step):
    """:func:`_chosen_track` over the tracks (``folds`` None for GCV). Its LAPACK calls
    (eigendecompositions, held-out factorisations) are unbatched on a CPU (``per_step``
    1), which is why :func:`_choose` may run it from several threads."""
    Lg = jnp.linalg.cholesky(Phi.T @ Phi)  # Theta^T Theta = Lg Lg^T, shared by the tracks
    max_gain = jnp.asarray(MAX_GAIN, P.dtype)
    return map_points(
        lambda a: _chosen_track(P, a[0], Phi, Lg, a[1], rough, grid, healthy_gain, max_gain, folds),
        (uv, w),
        per_step,
    )


#: fewest tracks per core for which the per-track choice is split over the cores (each
#: costs milliseconds, so two tracks a thread already pay for the thread)
MIN_TRACKS_PER_CORE = 2


def _choose(P, uv, Phi, w, rough, grid, healthy_gain, folds, per_step):
    """:func:`_chosen_points` with the tracks split over the CPU cores
    (:func:`jaxtraj._batching.on_cores`, one loop step per track when ``per_step`` is 1)."""

    def kernel(tracks):
        u, wt = tracks
        return _chosen_points(P, u, Phi, wt, rough, grid, healthy_gain, folds, per_step)

    align = max(per_step, 1)
    return on_cores(kernel, (uv, w), (P,), min_per_core=MIN_TRACKS_PER_CORE, align=align)


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
    program per shape for the weight's choice (unbatched LAPACK eigendecompositions) and
    one for the fits, each on a CPU split over the cores
    (:func:`jaxtraj._batching.on_cores`).

    The penalty weight is chosen by cross-validation per point (``shared=False``), or once
    for all points (``shared=True``: the grid value with the smallest criterion averaged
    over ``cv_points`` tracks spread evenly over the batch, all of them if fewer or with
    ``cv_points=None``), unless ``lam`` is given. Returns the batched
    :class:`~jaxtraj.Reconstruction` (leading axis N), the basis and the
    :class:`PenaltyChoice` of each cross-validated track (None if ``lam`` given; with
    ``shared`` every ``lam`` is the shared one and ``tracks`` says which tracks were
    cross-validated).

    ``criterion``: ``"kfold"`` (default) cross-validates with ``folds`` interleaved folds
    of held-out frames (2 to F; ``folds = F``: leave-one-frame-out); ``"gcv"`` uses
    generalised cross-validation (module notes; ``folds`` is then unused). Both come from
    one eigendecomposition per track, and with a weight per point the fit at the chosen
    weight comes from the same decomposition (its gain is the eigenbasis bound, within a
    few per cent of the solver's). ``max_rms_px``: as for :func:`reconstruct_regularised`
    (the statuses are the same).

    Cost per cross-validated track at F = 150, k = 60, 15 grid values, batched over 2000
    tracks on a 2-core Intel Xeon (the tracks split over the cores, one BLAS thread each):
    5 folds about 4.1 ms (one eigendecomposition of ``3k - 3`` rows and 75 factorisations
    of the 60 held-out rows), leave-one-frame-out about 2 ms, GCV about 1.6 ms. A shared
    weight pays the choice for ``cv_points`` tracks only, then one solve per point
    (README: per-point cost of the batched drivers). A shared weight suits points of one
    rigid workpiece (the same motion, the same cameras and noise); points that move
    differently want their own.
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
    if criterion == "kfold":
        _check_folds(folds, F)
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
    healthy = float(healthy_gain) if rule == "gain_weighted" else None
    tracks = _spread_tracks(np.shape(uv)[0], cv_points) if shared else None
    cv_per_step = points_per_step(CV_BATCH, CV_BATCH_ACCELERATOR, uv)
    folds_ = None if criterion == "gcv" else folds
    sel = slice(None) if tracks is None else np.asarray(tracks)
    chosen = with_one_blas_thread(
        _choose, P, uv[sel], Phi, w[sel], rough, grid, healthy, folds_, cv_per_step
    )
    if tracks is None:  # a weight per point: the fits come from the choice's decomposition
        return flagged(*chosen)
    choice = _shared(chosen[1], grid, tracks)
    return solved(choice.lam[0] * rough, choice)

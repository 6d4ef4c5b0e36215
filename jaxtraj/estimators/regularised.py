"""Regularised DCT: a roughness penalty on the high frequencies instead of a small k.

A DCT trajectory ``x(t) = sum_u phi_u(t) beta_u`` with ``phi_u = c_u cos(pi u tau)`` on
the span ``[t0, t1]`` (length L) has the exact roughness

    int_{t0}^{t1} ||x^(m)(t)||^2 dt = sum_u c_u^2 (pi u / L)^(2m) (L / 2) ||beta_u||^2,

because the cosines are orthogonal on the span. Adding ``lam`` times this to the least
squares (``penalty = lam * roughness_penalty(basis, m)`` in :func:`jaxtraj.reconstruct`)
lets k be large - up to the number of frames - without the ill-conditioning of a large
unregularised basis: the data decide how much high-frequency motion to keep. ``lam`` is
chosen by K-fold cross-validation on held-out reprojection error, batched over a grid,
weighted by the conditioning gain beyond a healthy value as in
:func:`jaxtraj.estimators.select_k_cv` (a weak penalty on a fast, smooth camera path
reprojects well and is still far off along the rays).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._batching import map_points, points_per_step
from .._checks import check_finite, check_shape, check_tracks
from ..basis import DCTBasis
from ..solve import (
    Reconstruction,
    _per_step,
    _reconstruct_points,
    _reprojection_rms,
    reconstruct,
)
from ._depth import flag_undetermined_depth
from .select_k import check_rule

__all__ = [
    "PenaltyChoice",
    "reconstruct_regularised",
    "reconstruct_regularised_points",
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
    otherwise)."""

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

    Every (fold, grid value) pair is one batched solve (vmapped). ``rule="reprojection"``
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


@eqx.filter_jit
def _cv(P, uv, Phi, w, rough, grid, held, healthy_gain):
    def held_out_rms(lam, mask):
        train = jnp.where(mask, 0.0, w)
        res = reconstruct(P, uv, Phi, train, penalty=lam * rough, diagnostics=False)
        return _reprojection_rms(P, uv, res.points, mask & (w > 0))

    per = jax.vmap(lambda lam: jax.vmap(lambda m: held_out_rms(lam, m))(held))(grid)
    score = jnp.mean(per, axis=1)
    gain = jax.vmap(lambda lam: reconstruct(P, uv, Phi, w, penalty=lam * rough).gain)(grid)
    crit = score if healthy_gain is None else score * jnp.maximum(1.0, gain / healthy_gain)
    crit = jnp.where(jnp.isfinite(crit), crit, jnp.inf)
    return PenaltyChoice(
        lam=grid[jnp.argmin(crit)], grid=grid, cv_rms_px=score, gain=gain, criterion=crit
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
) -> tuple[Reconstruction, DCTBasis, PenaltyChoice | None]:
    """Regularised DCT reconstruction: a generous k (default ``min(F, 60)``) with a
    roughness penalty whose weight is chosen by cross-validation (``rule``: see
    :func:`select_penalty_cv`) unless ``lam`` is given.

    Returns the :class:`~jaxtraj.Reconstruction`, the basis (evaluate it at other times
    for velocity or prediction) and the cross-validation record (None if ``lam`` given).
    """
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
    return flag_undetermined_depth(res, P, times, order), basis, choice


#: tracks per step of the cross-validation loop on a CPU and on an accelerator: under one
#: vmap every track's folds x grid systems (3k x 3k each) would be held at once (18 GB for
#: 256 tracks at k = 60), so the accelerator's groups are bounded too
CV_BATCH = 4
CV_BATCH_ACCELERATOR = 64


@functools.partial(
    jax.jit, static_argnames=("healthy_gain", "cv_tracks", "cv_per_step", "per_step")
)
def _regularised_points(
    P, uv, Phi, w, rough, grid, held, healthy_gain, cv_tracks, cv_per_step, per_step
):
    # cv_tracks: None (a weight per point) or the indices of the tracks whose mean
    # criterion chooses one shared weight.
    sel = slice(None) if cv_tracks is None else np.asarray(cv_tracks)
    choice = map_points(
        lambda a: _cv(P, a[0], Phi, a[1], rough, grid, held, healthy_gain),
        (uv[sel], w[sel]),
        cv_per_step,
    )
    if cv_tracks is None:
        lam = choice.lam
    else:  # one weight for all points: the smallest mean criterion
        crit = jnp.mean(jnp.where(jnp.isfinite(choice.criterion), choice.criterion, 1e300), 0)
        best = grid[jnp.argmin(crit)]
        lam = jnp.broadcast_to(best, uv.shape[:1])
        choice = PenaltyChoice(
            lam=jnp.broadcast_to(best, choice.lam.shape),
            grid=choice.grid,
            cv_rms_px=choice.cv_rms_px,
            gain=choice.gain,
            criterion=choice.criterion,
            tracks=jnp.asarray(cv_tracks, jnp.int32),
        )
    pen = lam[:, None] * rough[None, :]
    max_gain = jnp.asarray(20.0, P.dtype)
    return _reconstruct_points(P, uv, Phi, w, max_gain, 1, True, pen, per_step), choice


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
) -> tuple[Reconstruction, DCTBasis, PenaltyChoice | None]:
    """:func:`reconstruct_regularised` for N points seen by the same cameras, in one
    compiled program per shape.

    The penalty weight is chosen by cross-validation per point (``shared=False``), or once
    for all points (``shared=True``: the grid value with the smallest criterion averaged
    over ``cv_points`` tracks spread evenly over the batch, all of them if fewer or with
    ``cv_points=None``), unless ``lam`` is given. Returns the batched
    :class:`~jaxtraj.Reconstruction` (leading axis N), the basis and the
    :class:`PenaltyChoice` of each cross-validated track (None if ``lam`` given; with
    ``shared`` every ``lam`` is the shared one and ``tracks`` says which tracks were
    cross-validated).

    Cost: per cross-validated track ``folds * G`` penalised solves of the ``3k x 3k``
    system and ``G`` gain bounds (G = 15 grid values by default), each about ``(3k)^3``
    multiply-adds for its factorisation; this, not the assembly, dominates for the
    default k = min(F, 60): about 65-140 ms per track at F = 150 on 2 cores (AMD EPYC,
    Intel Xeon). A shared weight pays it for ``cv_points`` tracks only, then one solve
    per point (README: per-point cost of the batched drivers). A shared weight suits
    points of one rigid workpiece (the same motion, the same cameras and noise); points
    that move differently want their own.
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
    k = min(F, 60) if k is None else k
    dtype = jnp.result_type(jnp.asarray(P).dtype, jnp.float32)
    basis = DCTBasis.from_times(jnp.asarray(times, dtype), k)
    rough = roughness_penalty(basis, order)
    Phi = basis(jnp.asarray(times, dtype))
    P = jnp.asarray(P, dtype)
    w = jnp.ones(np.shape(uv)[:2], dtype) if weights is None else jnp.asarray(weights, dtype)
    uv = jnp.where(w[..., None] > 0, jnp.asarray(uv, dtype), 0.0)
    per_step = _per_step(uv)
    if lam is not None:
        pen = jnp.asarray(lam, dtype) * rough
        gain = jnp.asarray(20.0, dtype)
        res = _reconstruct_points(P, uv, Phi, w, gain, 1, True, pen, per_step)
        return flag_undetermined_depth(res, P, times, order), basis, None
    grid = jnp.logspace(-4, 10, 15, dtype=dtype) if grid is None else jnp.asarray(grid, dtype)
    check_shape("grid", grid, (None,), "(G,) penalty weights")
    held = jnp.asarray(_fold_masks(F, folds))
    healthy = float(healthy_gain) if rule == "gain_weighted" else None
    tracks = _spread_tracks(np.shape(uv)[0], cv_points) if shared else None
    cv_per_step = points_per_step(CV_BATCH, CV_BATCH_ACCELERATOR, uv)
    res, choice = _regularised_points(
        P, uv, Phi, w, rough, grid, held, healthy, tracks, cv_per_step, per_step
    )
    return flag_undetermined_depth(res, P, times, order), basis, choice

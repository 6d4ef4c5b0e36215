"""Automatic choice of the number of DCT basis vectors k.

* :func:`select_k_cv` - K-fold cross-validation on held-out reprojection error (Park et
  al., IJCV 2015): fit on the other folds' frames, reproject the fitted trajectory into
  the held-out frames, pick the k with the smallest mean squared error.
* :func:`select_k_gain` - the largest k whose conditioning gain stays below a bound
  (Valmadre & Lucey, CVPR 2012): the gain bounds the amplification of the
  basis-truncation error, so beyond it a larger k no longer pays.

Both are batched: the normal equations are assembled and factorised once per fold for the
largest k, and every candidate k is solved from the leading block of that factor (the
factor of a leading block is the leading block of the factor), all under one ``vmap``,
without LAPACK calls. A held-out reprojection error cannot see a collapse of the estimate along
the viewing rays (degenerate camera paths reproject perfectly): with fast cameras it keeps
falling with k while the conditioning gain, and with it the 3D error, rise steeply.
``select_k_cv`` therefore weights the held-out error by the squared gain beyond a healthy
value (``rule="gain_weighted"``, the default) and only considers candidates whose gain is
below ``max_gain``.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._batching import map_points, on_cores, points_per_step
from .._checks import check_tracks
from .._spd import matvec, vecmat
from ..basis import dct_basis
from ..solve import _factorise, _frame_blocks, _frame_spread, _gain_bound, _kron_sum
from ._common import as_float, homogeneous, validate_track

__all__ = ["KSelection", "select_k_cv", "select_k_gain", "select_k_points"]


class KSelection(eqx.Module):
    """Result of a k selection (one trajectory; leading axes from vmap).

    Attributes:
        k: the chosen number of basis vectors (int32; 0 if no candidate qualified).
        ks: (K,) the candidates.
        score: (K,) mean held-out squared reprojection error [px^2] (inf where not
            admissible); for :func:`select_k_gain` equal to ``gain``.
        gain: (K,) conditioning gain of each candidate on all frames.
        criterion: (K,) the value minimised by the rule (inf where not admissible); for
            :func:`select_k_gain` equal to ``gain``.
    """

    k: Int[Array, ""]
    ks: Int[Array, " K"]
    score: Float[Array, " K"]
    gain: Float[Array, " K"]
    criterion: Float[Array, " K"]


RULES = ("gain_weighted", "reprojection")


def check_rule(rule: str, healthy_gain: float) -> None:
    """Validate the selection rule options shared with ``select_penalty_cv``."""
    if rule not in RULES:
        raise ValueError(f"rule: expected one of {RULES}, got {rule!r}")
    if not (np.ndim(healthy_gain) == 0 and healthy_gain >= 1):
        raise ValueError(f"healthy_gain: expected a number >= 1, got {healthy_gain!r}")


def _check(P, uv, times, weights, ks, folds=2):
    validate_track(P, uv, times, weights)
    ks = np.asarray(ks)
    if ks.ndim != 1 or ks.size < 1 or np.any(ks < 1) or not np.issubdtype(ks.dtype, np.integer):
        raise ValueError(f"ks: expected a 1-D sequence of positive ints, got {ks!r}")
    if not isinstance(folds, int) or folds < 2:
        raise ValueError(f"folds: expected an int >= 2, got {folds!r}")
    return tuple(int(k) for k in ks)


#: points per step of the batched driver's loop on a CPU and on an accelerator (0: all at
#: once; see :mod:`jaxtraj._batching`)
MAP_BATCH = 8
MAP_BATCH_ACCELERATOR = 0


def _prefix_solve(W, d, N, b, k):
    """Solve the leading ``3k x 3k`` block of ``N beta = b`` (the fit with the first k
    basis vectors) from the factor ``(W, d)`` of the whole N (:func:`jaxtraj.solve._factorise`).

    The leading block of an (inverse) Cholesky factor is the factor of the leading block, and
    the equilibration is diagonal, so one factorisation serves every candidate k: each solve
    is two masked triangular products, plus one step of iterative refinement as in
    :func:`jaxtraj.reconstruct`. Entries beyond ``3k`` are zero.
    """
    mask = (jnp.arange(N.shape[0]) < 3 * k).astype(N.dtype)

    def solve(rhs):
        y = matvec(W, d * rhs * mask)  # rows < 3k only involve columns < 3k
        return d * vecmat(y * mask, W) * mask

    bm = b * mask
    beta = solve(bm)
    return beta + solve(bm - matvec(N, beta))


def _gains(P, uv, basis, w, ks):
    """Conditioning gain of every candidate k, from one factorisation of the K-column system.

    The same bound as the solver's (:func:`jaxtraj.solve._gain_bound`, equal to it up to
    rounding): with ``Theta^T Theta = R^T R``, ``sqrt(beta lambda_max(R N^-1 R^T))`` with
    the leading blocks of ``R`` and of the factor of ``N`` for each k.
    """
    QtQ, _, Q, _ = _frame_blocks(P, uv, w)
    N = _kron_sum(basis, QtQ)
    W, d = _factorise(N)
    spread_hi = _frame_spread(Q, w)[1]
    return jax.vmap(lambda k: _gain_bound(basis, W, d, spread_hi, k=k))(jnp.asarray(ks))


def select_k_cv(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "F 2"],
    times: Float[ArrayLike, " F"],
    ks=tuple(range(3, 21)),
    weights: Float[ArrayLike, " F"] | None = None,
    *,
    folds: int = 5,
    max_gain: float = 100.0,
    rule: str = "gain_weighted",
    healthy_gain: float = 20.0,
) -> KSelection:
    """Choose k by ``folds``-fold cross-validation on held-out reprojection error.

    Frame ``i`` belongs to fold ``i mod folds`` (interleaved, so every fold spans the
    whole recording). jit- and vmap-compatible (``ks``, ``folds`` and ``rule`` are
    static). Among the candidates whose gain is at most ``max_gain``:

    * ``rule="reprojection"`` (Park et al.) takes the k with the smallest mean held-out
      squared reprojection error ``e(k)``;
    * ``rule="gain_weighted"`` (default) takes the k with the smallest
      ``e(k) * max(1, gain(k) / healthy_gain)^2``. The 3D error is at most the gain
      times the part of the trajectory the basis misses (Valmadre & Lucey), and ``e(k)``
      sees that part only across the rays. Up to ``healthy_gain`` the rule is the plain
      held-out error (random camera paths, gains 1.5-3, are unaffected); beyond it each
      doubling of the gain must buy a fourfold smaller held-out error. On fast smooth
      camera paths (gains 5-1000 over k = 4-20) this brought the choice from 8-70 %
      worse than the best fixed k to level with it: over 32 paired scenes per cell
      (``benchmarks/bench_estimators.py --k-choice``) the difference from the k picked
      with the truth is +0.7 (-0.5 to +1.8) mm and -1.3 (-5.9 to +3.3) mm (95 %
      intervals), where the plain rule is +5.3 and +3.3 mm worse.

    Args:
        P: (F, 3, 4) projection matrices; uv: (F, 2) pixels [px]; times: (F,) [s].
        ks: candidate numbers of basis vectors.
        weights: (F,) weights, 0 for missing detections.
        folds: number of folds (>= 2).
        max_gain: candidates whose conditioning gain (all frames) exceeds this are
            not admissible (see the module notes).
        rule: ``"gain_weighted"`` or ``"reprojection"`` (see above).
        healthy_gain: the gain up to which ``"gain_weighted"`` trusts the held-out error.

    Returns:
        A :class:`KSelection`; build the basis with ``dct_basis(times, int(sel.k))``.
    """
    ks = _check(P, uv, times, weights, ks, folds)
    check_rule(rule, healthy_gain)
    P, uv, times, weights = as_float(P, uv, times, weights)
    F = P.shape[0]
    w = jnp.ones(F, P.dtype) if weights is None else weights
    obs = w > 0
    uv = jnp.where(obs[:, None], uv, 0.0)
    K = max(ks)
    basis = dct_basis(times, K)
    fold_of = jnp.arange(F) % folds

    def fold_error(f):
        held = fold_of == f
        w_train = jnp.where(held, 0.0, w)
        QtQ, Qtq, _, _ = _frame_blocks(P, uv, w_train)
        N = _kron_sum(basis, QtQ)
        b = (basis.T @ Qtq).reshape(-1)
        W, d = _factorise(N)  # one factorisation for every candidate k
        n_train = jnp.sum(w_train > 0)

        def err(k):
            beta = _prefix_solve(W, d, N, b, k)
            h = homogeneous(P, basis @ beta.reshape(K, 3))
            e = h[:, :2] / h[:, 2:3] - uv
            sq = jnp.where(held & obs, jnp.sum(e * e, axis=1), 0.0)
            return jnp.where(2 * n_train >= 3 * k, jnp.sum(sq), jnp.inf)

        return jax.vmap(err)(jnp.asarray(ks))

    total = jnp.sum(jax.vmap(fold_error)(jnp.arange(folds)), axis=0)
    score = total / jnp.maximum(jnp.sum(obs), 1)
    gain = _gains(P, uv, basis, w, ks)
    admissible = (gain <= max_gain) & jnp.isfinite(score)
    if rule == "gain_weighted":
        crit = score * jnp.maximum(1.0, gain / healthy_gain) ** 2
    else:
        crit = score
    crit = jnp.where(admissible, crit, jnp.inf)
    k = jnp.where(jnp.any(admissible), jnp.asarray(ks)[jnp.argmin(crit)], 0)
    return KSelection(
        k=k.astype(jnp.int32),
        ks=jnp.asarray(ks, jnp.int32),
        score=jnp.where(jnp.isfinite(score), score, jnp.inf),
        gain=gain,
        criterion=crit,
    )


def select_k_gain(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "F 2"],
    times: Float[ArrayLike, " F"],
    ks=tuple(range(3, 21)),
    weights: Float[ArrayLike, " F"] | None = None,
    *,
    max_gain: float = 10.0,
) -> KSelection:
    """Choose the largest candidate k whose conditioning gain is at most ``max_gain``.

    The gain ``||Pi||_2 >= 1`` (see :mod:`jaxtraj.solve`) grows with k; healthy problems
    sit at 1-10. jit- and vmap-compatible (``ks`` static). Returns a :class:`KSelection`
    whose ``score`` is the gain; ``k = 0`` when no candidate qualifies.
    """
    ks = _check(P, uv, times, weights, ks)
    P, uv, times, weights = as_float(P, uv, times, weights)
    F = P.shape[0]
    w = jnp.ones(F, P.dtype) if weights is None else weights
    uv = jnp.where((w > 0)[:, None], uv, 0.0)
    K = max(ks)
    basis = dct_basis(times, K)
    gain = _gains(P, uv, basis, w, ks)
    n_obs = jnp.sum(w > 0)
    ok = (gain <= max_gain) & (2 * n_obs >= 3 * jnp.asarray(ks))
    k = jnp.max(jnp.where(ok, jnp.asarray(ks), 0))
    return KSelection(
        k=k.astype(jnp.int32),
        ks=jnp.asarray(ks, jnp.int32),
        score=gain,
        gain=gain,
        criterion=gain,
    )


@functools.partial(
    jax.jit, static_argnames=("ks", "folds", "max_gain", "rule", "healthy_gain", "per_step")
)
def _select_k_points(P, uv, times, weights, ks, folds, max_gain, rule, healthy_gain, per_step):
    def one(u, w):
        return select_k_cv(
            P,
            u,
            times,
            ks,
            w,
            folds=folds,
            max_gain=max_gain,
            rule=rule,
            healthy_gain=healthy_gain,
        )

    return map_points(lambda a: one(*a), (uv, weights), per_step)


def select_k_points(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "N F 2"],
    times: Float[ArrayLike, " F"],
    ks=tuple(range(3, 21)),
    weights: Float[ArrayLike, "N F"] | None = None,
    *,
    folds: int = 5,
    max_gain: float = 100.0,
    rule: str = "gain_weighted",
    healthy_gain: float = 20.0,
) -> KSelection:
    """:func:`select_k_cv` for N points seen by the same cameras: one compiled program per
    shape (jit of the vmap), fields with a leading axis of size N.

    Per point it assembles and factorises one ``3K x 3K`` system per fold
    (``K = max(ks)``), solves every candidate from the leading blocks of that factor, and
    bounds every candidate's gain with a few Lanczos steps: about
    ``folds * (F K^2 + 2 (3K)^3 / 3) + len(ks) * (folds + 8) * (3K)^2`` multiply-adds, no
    LAPACK call. Validated on the host like :func:`select_k_cv` (first point's track).
    Called eagerly on a CPU with several cores, the points are split into one chunk per
    core, each from its own thread (:func:`jaxtraj._batching.on_cores`).
    """
    if np.ndim(uv) != 3:
        raise ValueError(f"uv: expected shape (N, F, 2), got {np.shape(uv)}")
    if weights is not None and np.shape(weights) != np.shape(uv)[:2]:
        raise ValueError(
            f"weights: expected shape {np.shape(uv)[:2]} (one per pixel), got {np.shape(weights)}"
        )
    ks = _check(P, uv[0], times, None if weights is None else weights[0], ks, folds)
    check_tracks(uv, weights)  # every point's pixels and weights
    check_rule(rule, healthy_gain)
    P, uv, times, weights = as_float(P, uv, times, weights)
    w = jnp.ones(uv.shape[:2], P.dtype) if weights is None else weights
    per_step = points_per_step(MAP_BATCH, MAP_BATCH_ACCELERATOR, uv)
    args = (ks, folds, float(max_gain), rule, float(healthy_gain), per_step)
    return on_cores(  # one chunk of points per CPU core, each from a thread (eager calls)
        lambda a: _select_k_points(P, a[0], times, a[1], *args), (uv, w), (P, times)
    )

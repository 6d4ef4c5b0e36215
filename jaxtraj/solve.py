"""Weighted least-squares reconstruction of a point trajectory (paper eq. 6).

Solves ``min_beta sum_i w_i ||Q_i (Phi_i beta) - q_i||^2`` for the (k, 3) coefficients
``beta`` of one point trajectory without ever building the dense (2F, 3F) system. The
normal matrix is assembled from per-frame 3x3 blocks::

    N = sum_i w_i (phi_i phi_i^T) (x) (Q_i^T Q_i),    b = sum_i w_i phi_i (x) (Q_i^T q_i)

which costs O(F k^2). Written for one point; under ``jax.vmap`` over points that share
cameras and basis, the sum over frames becomes a single (k^2, F) x (F, 9N) matrix
product. The normal equations are equilibrated (unit diagonal), solved by Cholesky,
and corrected with one step of iterative refinement on the original residuals
(corrected semi-normal equations), which restores the accuracy of a QR solve on
well-posed problems (tests compare against a dense ``numpy.linalg.lstsq``). The small
factorisation makes no LAPACK call (:mod:`jaxtraj._spd`), so a batch of points never
becomes a batched LAPACK call (slow, and seen to hang on 2 cores, with jaxlib 0.10).

Degeneracy is judged by the *conditioning gain* ``||Pi||_2`` of the oblique projector
``Pi = Theta N^-1 Theta^T Q^T W Q``: the noise-free estimate is ``Pi x`` and
``||x_hat - x|| <= ||Pi|| dist(x, span Theta)``, so the gain is exactly the factor by
which the basis-truncation error is amplified (1 = orthogonal; infinite when the
camera path makes the system singular, e.g. a camera that follows the point). The solver
reports a cheap upper bound of it (:func:`_gain_bound`); :func:`jaxtraj.conditioning_gain`
computes it exactly.
"""

from __future__ import annotations

import enum
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._batching import map_points, on_cores, points_per_step
from ._checks import check_finite, check_shape, check_tracks, is_concrete
from ._linalg import cholesky_small
from ._spd import inverse_cholesky, matvec, top_eigenvalue, vecmat
from .depth import _on_rays, camera_centres, depth_uncertainty

__all__ = ["Reconstruction", "Status", "normal_equations", "reconstruct", "reconstruct_points"]


class Status(enum.IntEnum):
    """Outcome of a reconstruction, stored as an int32 in ``Reconstruction.status``."""

    OK = 0
    #: fewer observed frames than unknowns: ``2 F' < 3 k``.
    UNDERDETERMINED = 1
    #: the conditioning gain exceeds ``max_gain`` (the camera path is, nearly, inside the
    #: basis span relative to the point) or the data do not determine the depth along the
    #: rays (``depth_uncertainty`` above its bound): the answer is not trustworthy.
    DEGENERATE = 2
    #: NaN or inf in the data entered the solve (only possible under ``jit``).
    NONFINITE = 3


class Reconstruction(eqx.Module):
    """Result of :func:`reconstruct` (one trajectory; leading axes come from ``vmap``).

    Attributes:
        coeffs: (k, 3) basis coefficients ``beta``.
        points: (F, 3) reconstructed positions ``Phi beta`` at the frame times [m].
        rms_px: reprojection RMS over the observed frames [px].
        gain: conditioning gain ``||Pi||_2`` (>= 1; about 1.5-5 on healthy problems): an
            upper bound, within a per cent of the exact value with equal weights and at
            most ``sqrt(max w / min w)`` above it otherwise (exact:
            :func:`jaxtraj.conditioning_gain`); NaN with ``diagnostics=False``.
        num_observed: number of frames with non-zero weight.
        status: a :class:`Status` code as int32.
        depth_uncertainty: relative depth uncertainty ``kappa`` of the fit moved onto its
            viewing rays (:func:`jaxtraj.depth.ray_depth_uncertainty`, second differences
            over the frames): how far the depths could slide along the rays, relative to
            the distance from the cameras, without the trajectory becoming rougher.
            0.001-0.05 under fast or random cameras, near 1 when the camera moves less
            than the point (slow orbits, a camera that follows it).
        relative_error: the gain times the RMS angle [rad] between the fit and the observed
            rays: a scale of the 3D error relative to the distance from the cameras (the
            angle shows the error across the rays; the gain, how much larger it can be
            along them). On the trust benchmark's scenes (DCT, k = 4-20, 8304 fits) the
            error over the distance was 0.73x it at the median and at most 1.57x it.
            NaN with ``diagnostics=False``.
    """

    coeffs: Float[Array, "k 3"]
    points: Float[Array, "F 3"]
    rms_px: Float[Array, ""]
    gain: Float[Array, ""]
    num_observed: Int[Array, ""]
    status: Int[Array, ""]
    depth_uncertainty: Float[Array, ""]
    relative_error: Float[Array, ""]

    @property
    def ok(self) -> Array:
        """Boolean (batched like ``status``): ``status == Status.OK``."""
        return self.status == Status.OK

    def check(self) -> Reconstruction:
        """Raise ``RuntimeError`` (host side) if any trajectory did not solve cleanly."""
        status = np.asarray(self.status)
        bad = np.flatnonzero(status.reshape(-1) != Status.OK)
        if bad.size:
            codes = sorted({Status(int(s)).name for s in status.reshape(-1)[bad]})
            gains = np.asarray(self.gain).reshape(-1)[bad]
            raise RuntimeError(
                f"{bad.size} of {status.size} trajectories failed ({', '.join(codes)}); "
                f"first index {bad[0]}, conditioning gain {gains[0]:.3g}. An under-determined "
                "problem needs 2 F' >= 3 k; a degenerate one needs a smaller k, a smoothness "
                "prior, or a camera path that moves relative to the point."
            )
        return self


def _frame_blocks(P, uv, weights):
    """Weighted per-frame ``Q^T Q`` (F, 3, 3), ``Q^T q`` (F, 3) and ``(Q, q)``."""
    p3 = P[:, 2, :]
    rows = P[:, :2, :] - uv[:, :, None] * p3[:, None, :]  # (F, 2, 4)
    Q, q = rows[:, :, :3], -rows[:, :, 3]
    # Broadcast-and-sum rather than einsum: contractions over axes of size 2-4 become
    # batched matrix products on CPU, which XLA runs far slower than a fused loop.
    QtQ = jnp.sum(Q[:, :, :, None] * Q[:, :, None, :], axis=1) * weights[:, None, None]
    Qtq = jnp.sum(Q * q[:, :, None], axis=1) * weights[:, None]
    return QtQ, Qtq, Q, q


def _sym_index(n: int) -> np.ndarray:
    """(n, n) map from a symmetric matrix entry to its index in the packed upper triangle."""
    iu, ju = np.triu_indices(n)
    idx = np.empty((n, n), np.int32)
    idx[iu, ju] = np.arange(iu.size)
    idx[ju, iu] = np.arange(iu.size)
    return idx


def _kron_sum(basis, blocks):
    """``sum_i (phi_i phi_i^T) (x) blocks_i`` as a (3k, 3k) matrix in one matrix product.

    ``blocks`` (F, 3, 3) must be symmetric. Only the k(k+1)/2 distinct products
    ``phi_iu phi_iv`` and the 6 distinct block entries enter the product, a 2.7x saving
    over the full Kronecker layout; the result is unpacked by a gather.
    """
    return _kron_sums(basis, blocks)[0]


def _kron_sums(basis, *blocks):
    """:func:`_kron_sum` of several (F, 3, 3) symmetric block sets in one matrix product."""
    k = basis.shape[1]
    iu, ju = np.triu_indices(k)
    ia, ja = np.triu_indices(3)
    cols = jnp.concatenate([b[:, ia, ja] for b in blocks], axis=1)  # (F, 6 m)
    packed = (basis[:, iu] * basis[:, ju]).T @ cols  # (k(k+1)/2, 6 m)
    out = []
    for j in range(len(blocks)):
        full = packed[:, 6 * j : 6 * j + 6][_sym_index(k)][:, :, _sym_index(3)]  # (k, k, 3, 3)
        out.append(full.transpose(0, 2, 1, 3).reshape(3 * k, 3 * k))
    return out


def _factorise(N):
    """Inverse Cholesky factor of the equilibrated ``D N D`` (unit diagonal), and ``d``.

    Returns ``(W, d)`` with ``N^-1 = D W^T W D`` (``W`` lower triangular). A ridge at
    round-off level lets singular (degenerate) systems factorise too; their status is set
    from the conditioning, and iterative refinement removes the ridge's bias on healthy ones.

    Every later solve is two triangular matrix-vector products with ``W``. The factor is
    computed without LAPACK (:func:`jaxtraj._spd.inverse_cholesky`): under ``vmap`` over
    points it becomes elementwise operations and reductions, where a batched LAPACK call
    runs on XLA's thread pool with jaxlib 0.10 (slower for small matrices, and seen to
    deadlock on 2 cores).
    """
    eps = jnp.finfo(N.dtype).eps
    n = N.shape[0]
    d = jax.lax.rsqrt(jnp.maximum(jnp.diag(N), jnp.finfo(N.dtype).tiny))
    Ns = N * d[:, None] * d[None, :] + 16 * eps * jnp.eye(n, dtype=N.dtype)
    return inverse_cholesky(Ns), d


def _solve_with(W, d, rhs):
    """``N^-1 rhs`` from the factor of :func:`_factorise`."""
    return d * vecmat(matvec(W, d * rhs), W)


def normal_equations(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "F 2"],
    basis: Float[ArrayLike, "F k"],
    weights: Float[ArrayLike, " F"] | None = None,
) -> tuple[Float[Array, "3k 3k"], Float[Array, " 3k"]]:
    """Structured normal equations ``(N, b)`` of eq. 6 for coefficients flattened (k, 3)."""
    P, uv, basis, weights = _as_arrays(P, uv, basis, weights)
    uv = jnp.where(weights[:, None] > 0, uv, 0.0)
    QtQ, Qtq, _, _ = _frame_blocks(P, uv, weights)
    return _kron_sum(basis, QtQ), (basis.T @ Qtq).reshape(-1)


def _as_arrays(P, uv, basis, weights):
    P = jnp.asarray(P)
    dtype = jnp.result_type(P.dtype, jnp.float32)
    P = P.astype(dtype)
    uv = jnp.asarray(uv, dtype)
    basis = jnp.asarray(basis, dtype)
    weights = jnp.ones(P.shape[0], dtype) if weights is None else jnp.asarray(weights, dtype)
    return P, uv, basis, weights


def _validate(P, uv, basis, weights, batch: tuple = (), count_check: bool = True) -> None:
    """Host-side checks with messages that name the argument.

    ``batch`` is the tuple of leading batch sizes of ``uv`` and ``weights`` (points).
    """
    check_shape("P", P, (None, 3, 4), "one 3x4 projection matrix per frame")
    F = P.shape[0]
    lead = "".join("N, " if n is None else f"{n}, " for n in batch)
    check_shape("uv", uv, (*batch, F, 2), f"({lead}F, 2): one pixel per frame of P, F={F}")
    if jnp.ndim(basis) != 2 or jnp.shape(basis)[0] != F:
        raise ValueError(
            f"basis: expected shape ({F}, k) (one row per frame of P), got "
            f"{tuple(jnp.shape(basis))}; build it with dct_basis(times, k) at the frame times"
        )
    if weights is not None:
        check_shape("weights", weights, (*batch, F), "one non-negative weight per pixel")
    check_finite("P", P, hint="Projection matrices must be finite.")
    n_obs = check_tracks(uv, weights)  # None under tracing
    if n_obs is None or not count_check:
        return
    k = jnp.shape(basis)[1]
    if 2 * n_obs < 3 * k:
        raise ValueError(
            f"basis: k={k} is too large for {n_obs} observed frame(s); the system "
            f"needs 2 F' >= 3 k, i.e. k <= {2 * n_obs // 3} (or more observed frames)"
        )


#: default ``max_depth_uncertainty`` of the solver's status (see :func:`reconstruct`).
#: Checked on the trust benchmark's scenes (simulated cell, two motion-capture takes, all
#: 70 cells, DCT k = 4-20, 9140 fits OK by the gain) with a seed other than the one it was
#: chosen on: 156 of the 160 fits more than 1 m off have 0.31-1.34; good fits (within
#: 0.1 m) under random, fast and 10-90 deg/frame orbiting cameras at most 0.29.
MAX_DEPTH_UNCERTAINTY = 0.3
#: default ``max_relative_error`` of the solver's status (see :func:`reconstruct`). On the
#: same fits, the 4 more than 1 m off that the depth test passes (fixed k = 6-8, the fast
#: robot-like camera about a walking person, gain 11.4-12.5, 59-71 px RMS) have 0.85-1.07;
#: no fit within 0.1 m is above 0.33 (8304 fits).
MAX_RELATIVE_ERROR = 0.5
#: the solver's default status bounds: gain, depth uncertainty, relative error
DEFAULT_BOUNDS = (20.0, MAX_DEPTH_UNCERTAINTY, MAX_RELATIVE_ERROR)


def reconstruct(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "F 2"],
    basis: Float[ArrayLike, "F k"],
    weights: Float[ArrayLike, " F"] | None = None,
    *,
    max_gain: float = 20.0,
    max_depth_uncertainty: float = MAX_DEPTH_UNCERTAINTY,
    max_relative_error: float = MAX_RELATIVE_ERROR,
    refine: int = 1,
    diagnostics: bool = True,
    penalty: Float[ArrayLike, " k"] | None = None,
) -> Reconstruction:
    """Reconstruct one moving point's trajectory from its pixel track (paper eq. 6).

    jit-, vmap- and grad-compatible. Batch over points that share cameras with
    ``jax.vmap(reconstruct, in_axes=(None, 0, None, 0))`` (or :func:`reconstruct_points`)
    and over recordings with a further ``vmap``.

    Args:
        P: (F, 3, 4) projection matrices of undistorted cameras (undistort pixels first).
        uv: (F, 2) pixel coordinates [px]. Entries with weight 0 are ignored and may be
            NaN.
        basis: (F, k) trajectory basis at the frame times, e.g. ``dct_basis(times, k)``.
        weights: (F,) non-negative weights on the squared residuals (inverse pixel
            variances up to scale); 0 marks a missing detection. Default: all 1.
        max_gain: conditioning gain above which the result is flagged ``DEGENERATE``.
        max_depth_uncertainty: ``Reconstruction.depth_uncertainty`` above which the
            result is flagged ``DEGENERATE``: the depths along the rays come from the
            basis, not from the data (:mod:`jaxtraj.depth`). ``inf`` turns the test off.
        max_relative_error: ``Reconstruction.relative_error`` above which the result is
            flagged ``DEGENERATE`` (not judged with ``diagnostics=False``, which has no
            gain). ``inf`` turns the test off.
        refine: iterative-refinement steps after the Cholesky solve (0 disables).
        diagnostics: compute the conditioning gain bound (a few Lanczos steps with the
            factor of the normal matrix; see ``Reconstruction.gain``). With ``False``
            the gain is reported as NaN ("not computed") and ``DEGENERATE`` is judged
            from a Cholesky condition estimate, which catches singular systems (a camera
            that follows the point) but not every amplified basis error; use it for
            throughput once a camera set-up is known to be healthy.
        penalty: optional (k,) non-negative weights of a quadratic penalty
            ``sum_u penalty[u] ||beta_u||^2`` added to the least squares (a regularised
            DCT; see :func:`jaxtraj.estimators.roughness_penalty`). Default: none.

    Returns:
        A :class:`Reconstruction`. Check ``status`` (or call ``.check()``): a
        degenerate or under-determined problem has a finite but meaningless answer.

    Raises:
        ValueError: on wrong shapes, negative weights, or, for concrete inputs,
            non-finite pixels with non-zero weight and ``2 F' < 3 k``.
    """
    _validate(P, uv, basis, weights, count_check=penalty is None)
    _check_bound("max_depth_uncertainty", max_depth_uncertainty)
    _check_bound("max_relative_error", max_relative_error)
    if penalty is not None:
        check_shape("penalty", penalty, (jnp.shape(basis)[1],), "one weight per basis vector")
        p = np.asarray(penalty) if is_concrete(penalty) else None
        if p is not None and not (np.all(np.isfinite(p)) and np.all(p >= 0)):
            raise ValueError("penalty: must be finite and >= 0")
    P, uv, basis, weights = _as_arrays(P, uv, basis, weights)
    pen = None if penalty is None else jnp.asarray(penalty, P.dtype)
    # One compiled program (inlined under an outer jit): run eagerly, the unrolled small
    # factorisation would otherwise dispatch hundreds of operations one by one.
    bounds = jnp.asarray([max_gain, max_depth_uncertainty, max_relative_error], P.dtype)
    return _reconstruct_jit(P, uv, basis, weights, bounds, pen, refine, diagnostics)


@functools.partial(jax.jit, static_argnames=("refine", "diagnostics"))
def _reconstruct_jit(P, uv, basis, weights, bounds, penalty, refine, diagnostics):
    return _reconstruct(P, uv, basis, weights, bounds, penalty, refine, diagnostics)


def _reconstruct(P, uv, basis, weights, bounds, penalty, refine, diagnostics):
    """The traceable body of :func:`reconstruct` (arrays already validated and cast;
    ``bounds``: the status's ``max_gain``, ``max_depth_uncertainty``, ``max_relative_error``)."""
    N, b = _assemble(P, uv, basis, weights, penalty)
    return _finish(P, uv, basis, weights, N, b, bounds, penalty, refine, diagnostics)


def _check_bound(name: str, v) -> None:
    if isinstance(v, bool) or not (isinstance(v, (int, float)) and v > 0):
        raise ValueError(f"{name}: must be a number > 0 (inf disables), got {v!r}")


def _assemble(P, uv, basis, weights, penalty):
    """Normal matrix ``N`` (penalty included) and right-hand side ``b`` of one point: the
    per-frame sums, which under ``vmap`` over points become one large matrix product."""
    uv = jnp.where((weights > 0)[:, None], uv, 0.0)
    QtQ, Qtq, _, _ = _frame_blocks(P, uv, weights)
    N = _kron_sum(basis, QtQ)
    if penalty is not None:
        N = N + jnp.diag(jnp.repeat(penalty, 3))  # per flattened coefficient
    return N, (basis.T @ Qtq).reshape(-1)


def _solve_refined(P, uv, basis, weights, N, b, penalty, refine):
    """Factorise ``N`` and solve for the flattened coefficients with ``refine`` steps of
    iterative refinement; returns ``(beta, W, d, Q)`` (the factor of :func:`_factorise`,
    reusable for covariances, and the frames' ray constraints). ``uv`` must be zero where
    the weight is."""
    k = basis.shape[1]
    p3 = P[:, 2, :]
    rows = P[:, :2, :] - uv[:, :, None] * p3[:, None, :]  # (F, 2, 4)
    Q, q = rows[:, :, :3], -rows[:, :, 3]
    W, d = _factorise(N)
    beta = _solve_with(W, d, b)
    pen3 = None if penalty is None else jnp.repeat(penalty, 3)
    for _ in range(refine):
        T = basis @ beta.reshape(k, 3)
        r = (q - jnp.sum(Q * T[:, None, :], axis=2)) * weights[:, None]  # weighted residual
        rhs = (basis.T @ jnp.sum(Q * r[:, :, None], axis=1)).reshape(-1)
        if pen3 is not None:
            rhs = rhs - pen3 * beta
        beta = beta + _solve_with(W, d, rhs)
    return beta, W, d, Q


def _finish(P, uv, basis, weights, N, b, bounds, penalty, refine, diagnostics, centres=None):
    """Factorise, solve, refine and judge one point from its assembled normal equations
    (``bounds``: ``max_gain``, ``max_depth_uncertainty`` and ``max_relative_error``, or
    ``max_gain`` alone with the defaults for the others; ``centres``: the cameras'
    centres, computed once by a batched caller)."""
    bounds = jnp.asarray(bounds, P.dtype)
    if bounds.ndim == 0:
        bounds = jnp.stack([bounds, *jnp.asarray(DEFAULT_BOUNDS[1:], P.dtype)])
    max_gain, max_kappa, max_rel = bounds
    k = basis.shape[1]
    dtype = P.dtype
    eps = jnp.finfo(dtype).eps
    observed = weights > 0
    finite = jnp.all(jnp.isfinite(uv), axis=1) | ~observed
    uv = jnp.where(observed[:, None], uv, 0.0)
    pen3 = None if penalty is None else jnp.repeat(penalty, 3)
    beta, W, d, Q = _solve_refined(P, uv, basis, weights, N, b, penalty, refine)
    coeffs = beta.reshape(k, 3)
    points = basis @ coeffs

    if diagnostics:
        gain = _gain_bound(basis, W, d, _frame_spread(Q, weights)[1], pen3=pen3)
        degenerate = (gain > max_gain) | ~jnp.isfinite(gain)
    else:
        gain = jnp.full((), jnp.nan, dtype)
        diag = jnp.diag(W)  # reciprocals of the Cholesky diagonal
        # Lower bound on cond(Ns); a singular system leaves only the ridge on the diagonal.
        degenerate = (jnp.max(diag) / jnp.min(diag)) ** 2 > 1.0 / jnp.sqrt(eps)
    rms = _reprojection_rms(P, uv, points, observed)
    kappa, rel = _ray_checks(P, points, Q, observed, gain, centres)
    degenerate = degenerate | ~(kappa <= max_kappa) | (rel > max_rel)
    n_obs = jnp.sum(observed).astype(jnp.int32)
    status = _status(finite, P, n_obs, k, penalty is not None, degenerate)
    return Reconstruction(
        coeffs=coeffs,
        points=points,
        rms_px=rms,
        gain=gain,
        num_observed=n_obs,
        status=status,
        depth_uncertainty=kappa,
        relative_error=rel,
    )


def _ray_checks(P, points, Q, observed, gain, centres=None):
    """``(depth_uncertainty, relative_error)`` of one fit (see :class:`Reconstruction`)
    from its frames' ray constraints ``Q`` (any scale) and its conditioning gain."""
    dtype = points.dtype
    C = camera_centres(P) if centres is None else centres
    y = _on_rays(points, Q, C, observed)
    kappa = depth_uncertainty(y, C, jnp.arange(points.shape[0], dtype=dtype), 2)
    return kappa, gain * jnp.sqrt(_angular_miss2(points, y, C, observed))


def _angular_miss2(points, y, C, observed):
    """Mean over the observed frames of the squared sine of the angle between each fitted
    point and the same point moved onto its ray (``y``), seen from the camera ``C``."""
    dist = jnp.maximum(jnp.linalg.norm(points - C, axis=1), jnp.finfo(points.dtype).tiny)
    miss2 = jnp.sum((points - y) ** 2, axis=1) / dist**2
    n = jnp.maximum(jnp.sum(observed), 1)
    return jnp.sum(jnp.where(observed, miss2, 0.0)) / n


def _status(finite, P, n_obs, k, penalised, degenerate):
    """Status code (int32) of one solve: NONFINITE if a pixel (``finite``: per frame,
    observed frames only) or a camera is not finite, UNDERDETERMINED if an unpenalised fit
    has fewer than ``3 k / 2`` observed frames, else DEGENERATE or OK."""
    return jnp.where(
        ~jnp.all(finite) | ~jnp.all(jnp.isfinite(P)),
        Status.NONFINITE,
        jnp.where(
            (2 * n_obs < 3 * k) & (not penalised),
            Status.UNDERDETERMINED,
            jnp.where(degenerate, Status.DEGENERATE, Status.OK),
        ),
    ).astype(jnp.int32)


def _square_blocks(QtQ):
    """Per-frame ``(Q^T Q)^2`` (F, 3, 3), as a broadcast-and-sum (see :func:`_frame_blocks`)."""
    return jnp.sum(QtQ[:, :, :, None] * QtQ[:, None, :, :], axis=2)


#: Lanczos steps of the solver's gain bound (see :func:`_gain_bound`)
GAIN_STEPS = 8


def _conditioning_gain(basis, H, W, d):
    """Exact ``||Pi||_2`` with ``Pi = Theta N^-1 Theta^T A`` from the factorised normal matrix.

    With ``Theta^T Theta = R^T R`` (``Theta = U R``, U with orthonormal columns) the
    non-zero eigenvalues of ``Pi^T Pi`` are those of the symmetric ``S = Z H Z^T``, where
    ``Z = R N^-1`` and ``H = Theta^T A^2 Theta`` (:func:`_kron_sum` of the squared frame
    blocks). Only the factor of N is used, so a singular (degenerate) system gives a huge
    but finite gain. Forms S and calls a symmetric eigensolver (LAPACK): for
    :func:`jaxtraj.conditioning_gain`, not for the batched solver (see :func:`_gain_bound`).
    """
    R = jnp.kron(cholesky_small(basis.T @ basis).T, jnp.eye(3, dtype=basis.dtype))
    Zt = jax.vmap(lambda v: _solve_with(W, d, v), in_axes=1, out_axes=1)(R.T)  # N^-1 R^T
    S = Zt.T @ H @ Zt
    lam = jnp.linalg.eigvalsh(0.5 * (S + S.T))[-1]
    return jnp.sqrt(jnp.maximum(lam, 0.0))


def _frame_spread(Q, weights):
    """Smallest and largest non-zero eigenvalue of the weighted frame blocks
    ``A_i = w_i Q_i^T Q_i`` over the observed frames (closed form: ``Q_i Q_i^T`` is 2x2)."""
    a = jnp.sum(Q[:, 0] * Q[:, 0], axis=1)
    b = jnp.sum(Q[:, 0] * Q[:, 1], axis=1)
    c = jnp.sum(Q[:, 1] * Q[:, 1], axis=1)
    mid = 0.5 * (a + c)
    rad = jnp.sqrt(0.25 * (a - c) ** 2 + b * b)
    obs = weights > 0
    hi = jnp.max(jnp.where(obs, weights * (mid + rad), 0.0))
    lo = jnp.min(jnp.where(obs, weights * jnp.maximum(mid - rad, 0.0), jnp.inf))
    return lo, hi


def _gain_bound(basis, W, d, spread_hi, steps: int = GAIN_STEPS, k=None, pen3=None):
    """Upper bound ``sqrt(beta lambda_max(R N^-1 R^T))`` on the conditioning gain.

    With ``alpha A_i <= A_i^2 <= beta A_i`` (``alpha``, ``beta``: the smallest and largest
    non-zero eigenvalue of the frame blocks, :func:`_frame_spread`) the matrix
    ``H = Theta^T A^2 Theta`` lies between ``alpha Theta^T A Theta`` and ``beta N``, so the
    squared gain (the top eigenvalue of ``R N^-1 H N^-1 R^T``, see
    :func:`_conditioning_gain`) is at most ``beta`` and (without a penalty) at least
    ``alpha`` times the top eigenvalue of ``R N^-1 R^T`` (``Theta^T Theta = R^T R``). That
    eigenvalue needs only the factor of N, no second Kronecker sum: ``steps`` Lanczos steps
    (:func:`jaxtraj._spd.top_eigenvalue`). For a pinhole camera both non-zero eigenvalues
    of ``Q_i^T Q_i`` are about ``f^2``, so with equal weights ``alpha ~ beta`` and the bound
    is within a per cent of the exact gain; unequal weights loosen it by at most
    ``sqrt(max w / min w)``.

    ``k`` (traced, optional): the bound of the fit with only the first k basis vectors, from
    the leading blocks of the factors (used by the k selection). ``pen3`` (3k,): the
    penalty on the diagonal of N; the bound then uses ``Theta^T A Theta = N - pen`` between
    the two inverses (``R (N^-1 - N^-1 pen N^-1) R^T``), which stays tight when the penalty
    dominates the weakly observed directions.
    """
    kk = basis.shape[1]
    n = W.shape[0]
    Lg = cholesky_small(basis.T @ basis)
    idx = jnp.arange(n)
    mask = jnp.ones(n, W.dtype) if k is None else (idx < 3 * k).astype(W.dtype)

    def ninv(u):  # N^-1 u (leading block)
        return d * vecmat(matvec(W, d * u * mask) * mask, W) * mask

    def apply(v):
        u = ninv((Lg @ (v * mask).reshape(kk, 3)).reshape(-1))  # N^-1 R^T v
        if pen3 is not None:
            u = u - ninv(pen3 * u)
        return (Lg.T @ u.reshape(kk, 3)).reshape(-1) * mask  # R u

    # Start where N^-1 is large (the weakly determined directions), plus a fixed spread so
    # that the start is never orthogonal to the dominant eigenvector in practice.
    ninv_diag = d * d * jnp.sum(W * W * mask[:, None], axis=0)
    spread = 0.1 + 0.1 * jnp.modf(idx * 0.6180339887498949)[0].astype(W.dtype)
    v0 = (ninv_diag / jnp.max(ninv_diag * mask) + spread) * mask
    lam = top_eigenvalue(apply, v0, steps)
    return jnp.sqrt(jnp.maximum(lam, 0.0) * spread_hi)


@jax.jit
def _gain_only(P, uv, basis, weights):
    """Exact conditioning gain of one problem (used by :func:`jaxtraj.conditioning_gain`)."""
    P, uv, basis, weights = _as_arrays(P, uv, basis, weights)
    uv = jnp.where(weights[:, None] > 0, uv, 0.0)
    QtQ, _, _, _ = _frame_blocks(P, uv, weights)
    N, H = _kron_sums(basis, QtQ, _square_blocks(QtQ))
    W, d = _factorise(N)
    return _conditioning_gain(basis, H, W, d)


def _reprojection_rms(P, uv, points, observed):
    homog = jnp.sum(P[:, :, :3] * points[:, None, :], axis=2) + P[:, :, 3]
    proj = homog[:, :2] / homog[:, 2:3]
    err2 = jnp.sum((proj - uv) ** 2, axis=1)
    n = jnp.maximum(jnp.sum(observed), 1)
    return jnp.sqrt(jnp.sum(jnp.where(observed, err2, 0.0)) / n)


#: points per step of the batched driver's loop over points on a CPU (see
#: :func:`reconstruct_points` and :mod:`jaxtraj._batching`; 8 was 1.3-2.2x faster than 0 (a
#: plain vmap) and 1 at F = 150, k = 10, N = 2000 on 2 cores)
MAP_BATCH = 8
#: the same on a GPU or other accelerator (0: one vmap over all points)
MAP_BATCH_ACCELERATOR = 0


def _per_step(like) -> int:
    """The kernel's group size (:data:`MAP_BATCH` or :data:`MAP_BATCH_ACCELERATOR`) for the
    platform of the array ``like``."""
    return points_per_step(MAP_BATCH, MAP_BATCH_ACCELERATOR, like)


@functools.partial(jax.jit, static_argnames=("refine", "diagnostics", "map_batch"))
def _reconstruct_points(P, uv, basis, weights, bounds, refine, diagnostics, penalty, map_batch):
    """The batched kernel; ``penalty`` is None, shared (k,) or one per point (N, k);
    ``bounds`` as for :func:`_finish`."""
    n = uv.shape[0]
    if penalty is not None and penalty.ndim == 1:
        penalty = jnp.broadcast_to(penalty, (n, penalty.shape[0]))
    N, b = jax.vmap(lambda u, w, p: _assemble(P, u, basis, w, p))(uv, weights, penalty)
    C = camera_centres(P)

    def finish(args):
        u, w, N, b, p = args
        return _finish(P, u, basis, w, N, b, bounds, p, refine, diagnostics, C)

    return map_points(finish, (uv, weights, N, b, penalty), map_batch)


def reconstruct_points(
    P: Float[ArrayLike, "F 3 4"],
    uv: Float[ArrayLike, "N F 2"],
    basis: Float[ArrayLike, "F k"],
    weights: Float[ArrayLike, "N F"] | None = None,
    *,
    max_gain: float = 20.0,
    max_depth_uncertainty: float = MAX_DEPTH_UNCERTAINTY,
    max_relative_error: float = MAX_RELATIVE_ERROR,
    refine: int = 1,
    diagnostics: bool = True,
    penalty: Float[ArrayLike, " k"] | None = None,
) -> Reconstruction:
    """Reconstruct N point trajectories seen by the same cameras (jit-compiled, batched).

    Equivalent to a loop of :func:`reconstruct` over points. The per-frame sums of all
    points are one large matrix product; the small per-point work (factorisation, solve,
    refinement, gain) then runs, on a CPU, as a loop over groups of :data:`MAP_BATCH` points
    (``lax.map``), which keeps each group's matrices in cache and lets XLA:CPU compile the
    loop body into one kernel (see :mod:`jaxtraj._xla`); ``jax.vmap(reconstruct)`` gives the
    same numbers but runs every step of the factorisation over all N points in turn. On a
    GPU the points go in groups of :data:`MAP_BATCH_ACCELERATOR` (0: all at once), since
    there a loop of small groups leaves the device idle (:mod:`jaxtraj._batching`).
    Called eagerly on a CPU with several cores, the points are split into one chunk per
    core, each solved from its own thread (:func:`jaxtraj._batching.on_cores`; the same
    result per point). Fields of the result gain a leading axis of size N.
    """
    batch = (jnp.shape(uv)[0] if jnp.ndim(uv) == 3 else None,)
    _validate(P, uv, basis, weights, batch=batch, count_check=penalty is None)
    _check_bound("max_depth_uncertainty", max_depth_uncertainty)
    _check_bound("max_relative_error", max_relative_error)
    P_, uv_, basis_, _ = _as_arrays(P, uv, basis, None)
    w = jnp.ones(uv_.shape[:2], P_.dtype) if weights is None else jnp.asarray(weights, P_.dtype)
    pen = None if penalty is None else jnp.asarray(penalty, P_.dtype)
    bounds = jnp.asarray([max_gain, max_depth_uncertainty, max_relative_error], P_.dtype)
    return _points_on_cores(P_, uv_, basis_, w, bounds, refine, diagnostics, pen, _per_step(uv_))


def _points_on_cores(P, uv, basis, weights, bounds, refine, diagnostics, penalty, per_step):
    """:func:`_reconstruct_points` through :func:`jaxtraj._batching.on_cores`: on a CPU one
    chunk of points per core; a penalty per point (N, k) is split with the points, a
    shared one (k,) is not."""
    per_point = penalty is not None and penalty.ndim == 2

    def kernel(pts):
        u, w, p = pts
        p = p if per_point else penalty
        return _reconstruct_points(P, u, basis, w, bounds, refine, diagnostics, p, per_step)

    return on_cores(kernel, (uv, weights, penalty if per_point else None), (P, basis, penalty))

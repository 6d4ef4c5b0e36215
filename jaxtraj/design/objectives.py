"""Differentiable measures of how well a camera path measures a workpiece trajectory.

* :func:`expected_error` - the RMS error of the DCT reconstruction that the path would
  give: the noise-free reconstruction's error (basis truncation amplified by the
  conditioning, through the batched solve) plus the pixel-noise variance from the
  solver's first-order covariance, ``E = sqrt(mean_i ||x_hat_i - x_i||^2 + tr Cov_i)``.
  Averaged over a set of plausible workpiece trajectories (vmapped).
  With ``metric="mean"`` the same per-frame terms give a mean Euclidean error (the
  paper's metric), ``mean_i sqrt(||x_hat_i - x_i||^2 + tr Cov_i)``, by Jensen's
  inequality an upper bound on the expected mean error; it weighs a large error in a few
  frames less than the RMS does.
* :func:`path_reconstructibility` - Park et al.'s eta of the path for the same set
  (geometric mean).

The camera always looks at the *predicted* trajectory; the plausible trajectories are
what the workpiece may actually do (e.g. the prediction plus smooth random deviations).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ..analysis import reconstructibility
from ..basis import DCTBasis
from ..estimators.covariance import _pixel_blocks, _sandwich
from ..solve import _assemble, _kron_sum, _solve_refined, reconstruct
from .path import CameraPathModel

__all__ = [
    "expected_error",
    "expected_error_for_cameras",
    "expected_errors_for_cameras",
    "monte_carlo_error",
    "path_reconstructibility",
    "plausible_trajectories",
    "project_points",
    "sampled_limits",
]


def project_points(P: Float[Array, "F 3 4"], X: Float[Array, "F 3"]) -> Float[Array, "F 2"]:
    """Pixels (F, 2) of one point per frame under (F, 3, 4) projection matrices."""
    h = jnp.einsum("fij,fj->fi", P[:, :, :3], X) + P[:, :, 3]
    return h[:, :2] / h[:, 2:3]


def _frame_errors(P, x, basis, pixel_sigma):
    """(F,) expected squared error per frame: noise-free error^2 plus the noise variance.

    The reconstruction (:func:`jaxtraj.reconstruct`, one refinement step) and its
    first-order covariance (:func:`jaxtraj.estimators.dct_covariance`) share one
    factorisation of the normal matrix: in the design's gradient the factorisation and its
    adjoint are the dearest part."""
    F, k = basis.shape
    uv = project_points(P, x)
    w = jnp.ones(F, P.dtype)
    N, b = _assemble(P, uv, basis, w, None)
    beta, W, d, _ = _solve_refined(P, uv, basis, w, N, b, None, 1)
    points = basis @ beta.reshape(k, 3)
    bias2 = jnp.sum((points - x) ** 2, axis=-1)
    sig2 = jnp.broadcast_to(jnp.asarray(pixel_sigma, P.dtype) ** 2, (F,))
    cov = _sandwich(W, d, _kron_sum(basis, _pixel_blocks(P, uv, points, w, sig2)))
    # trace of each frame's (phi_i^T (x) I_3) Cov (phi_i (x) I_3)
    C = jnp.trace(cov.reshape(k, 3, k, 3), axis1=1, axis2=3)
    traces = jnp.einsum("fu,uv,fv->f", basis, C, basis)
    return bias2 + traces


def _sample_errors(P, samples, basis, pixel_sigma):
    """(S, F) expected squared error per sample and frame (checked counts, matched dtypes)."""
    P = jnp.asarray(P)
    basis = jnp.asarray(basis, P.dtype)
    _check_counts(P.shape[0], basis.shape[-1])
    return jax.vmap(lambda x: _frame_errors(P, x, basis, pixel_sigma))(
        jnp.asarray(samples, P.dtype)
    )


def _metrics(e2):
    """(rms, mean) errors [m] from (S, F) squared errors; +inf when the path is exactly
    degenerate (e.g. a camera riding with the workpiece), rather than the NaN of the
    singular solve."""

    def finite_or_inf(v):
        return jnp.where(jnp.isnan(v), jnp.inf, v)

    return finite_or_inf(jnp.sqrt(jnp.mean(e2))), finite_or_inf(jnp.mean(jnp.sqrt(e2)))


def expected_errors_for_cameras(
    P: Float[ArrayLike, "F 3 4"],
    samples: Float[ArrayLike, "S F 3"],
    basis: Float[ArrayLike, "F kb"],
    pixel_sigma: float = 0.3,
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Both metrics of :func:`expected_error_for_cameras`, ``(rms, mean)`` [m], from one
    reconstruction and covariance per sample."""
    return _metrics(_sample_errors(P, samples, basis, pixel_sigma))


METRICS = ("rms", "mean")


def expected_error(
    model: CameraPathModel,
    theta: Float[ArrayLike, "k 3"],
    K: Float[ArrayLike, "3 3"],
    predicted: Float[ArrayLike, "F 3"],
    samples: Float[ArrayLike, "S F 3"],
    basis: Float[ArrayLike, "F kb"],
    pixel_sigma: float = 0.3,
    metric: str = "rms",
) -> Float[Array, ""]:
    """Expected reconstruction error [m] of the DCT method for the path ``theta``.

    Args:
        model: the camera path model; theta: (k, 3) its parameters.
        K: (3, 3) camera matrix.
        predicted: (F, 3) predicted workpiece point (where the camera looks).
        samples: (S, F, 3) plausible true trajectories (S >= 1; may include ``predicted``).
        basis: (F, kb) the reconstruction's trajectory basis at the image times.
        pixel_sigma: detection noise [px].
        metric: ``"rms"``: ``sqrt(mean_s mean_i E||x_hat_i - x_i||^2)``; ``"mean"``: the
            mean Euclidean error ``mean_s mean_i sqrt(E||x_hat_i - x_i||^2)``, an upper
            bound (Jensen) on ``E mean_i ||x_hat_i - x_i||``, the paper's metric, which
            :func:`monte_carlo_error` estimates by simulation.

    Returns:
        The error [m], differentiable in ``theta``; +inf for an exactly degenerate path.
    """
    P = model.projection_matrices(theta, K, predicted)
    return expected_error_for_cameras(P, samples, basis, pixel_sigma, metric)


def expected_error_for_cameras(
    P: Float[ArrayLike, "F 3 4"],
    samples: Float[ArrayLike, "S F 3"],
    basis: Float[ArrayLike, "F kb"],
    pixel_sigma: float = 0.3,
    metric: str = "rms",
) -> Float[Array, ""]:
    """:func:`expected_error` for given cameras (F, 3, 4), e.g. a heuristic path."""
    if metric not in METRICS:
        raise ValueError(f"metric: expected one of {METRICS}, got {metric!r}")
    rms, mean = expected_errors_for_cameras(P, samples, basis, pixel_sigma)
    return rms if metric == "rms" else mean


def _check_counts(F: int, k: int) -> None:
    if 2 * F < 3 * k:
        raise ValueError(
            f"basis: {k} vectors need at least {-(-3 * k // 2)} images (2F >= 3k), got F = {F}"
        )


def path_reconstructibility(
    model: CameraPathModel,
    theta: Float[ArrayLike, "k 3"],
    samples: Float[ArrayLike, "S F 3"],
    basis: Float[ArrayLike, "F kb"],
) -> Float[Array, ""]:
    """Geometric mean over the samples of eta (Park et al.) of the camera path."""
    c = model.centres(theta)
    etas = jax.vmap(lambda x: reconstructibility(c, x, basis))(jnp.asarray(samples, c.dtype))
    return jnp.exp(jnp.mean(jnp.log(etas)))


def plausible_trajectories(
    key: Array,
    predicted: Float[ArrayLike, "F 3"],
    times: Float[ArrayLike, " F"],
    n: int,
    extent: float = 0.05,
    n_terms: int = 4,
) -> Float[Array, "n+1 F 3"]:
    """The prediction and ``n`` smooth random deviations from it, a simple prior on what
    the workpiece may do: ``predicted + d_j`` with ``d_j`` a random combination of the
    DCT vectors 1..``n_terms`` (no constant), scaled to a largest excursion of ``extent``
    [m] per axis. Row 0 is the prediction itself."""
    predicted = jnp.asarray(predicted)
    times = jnp.asarray(times, predicted.dtype)
    rows = DCTBasis.from_times(times, n_terms + 1)(times)[:, 1:]
    coef = jax.random.normal(key, (n, n_terms, 3), predicted.dtype)
    dev = jnp.einsum("fk,nkc->nfc", rows, coef)
    dev = dev * (extent / jnp.max(jnp.abs(dev), axis=1, keepdims=True))
    return jnp.concatenate([predicted[None], predicted[None] + dev], 0)


def monte_carlo_error(
    key: Array,
    P: Float[ArrayLike, "F 3 4"],
    samples: Float[ArrayLike, "S F 3"],
    basis: Float[ArrayLike, "F kb"],
    pixel_sigma: float = 0.3,
    draws: int = 64,
) -> Float[Array, ""]:
    """Mean Euclidean error [m] of the DCT reconstruction over ``draws`` noisy pixel sets
    per sample trajectory (the simulated counterpart of :func:`expected_error`)."""
    P = jnp.asarray(P)
    basis = jnp.asarray(basis, P.dtype)
    samples = jnp.asarray(samples, P.dtype)

    def one(k, x):
        uv = project_points(P, x) + pixel_sigma * jax.random.normal(k, (x.shape[0], 2), P.dtype)
        return jnp.mean(jnp.linalg.norm(reconstruct(P, uv, basis).points - x, axis=1))

    keys = jax.random.split(key, (samples.shape[0], draws))
    errs = jax.vmap(lambda ks, x: jax.vmap(lambda k: one(k, x))(ks))(keys, samples)
    return jnp.mean(errs)


def sampled_limits(centres: Float[ArrayLike, "F 3"], times: Float[ArrayLike, " F"]):
    """Peak speed [m/s] and acceleration [m/s^2] implied by camera centres at the image
    times (finite differences; for paths given only at the images, e.g. the paper's random
    discontinuous camera)."""
    c, t = jnp.asarray(centres), jnp.asarray(times)
    v = jnp.diff(c, axis=0) / jnp.diff(t)[:, None]
    tm = 0.5 * (t[1:] + t[:-1])
    a = jnp.diff(v, axis=0) / jnp.diff(tm)[:, None]
    return jnp.max(jnp.linalg.norm(v, axis=1)), jnp.max(jnp.linalg.norm(a, axis=1))

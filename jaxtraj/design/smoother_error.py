"""Expected error of the smoothness-prior smoother for a camera path (design objective).

The per-point estimator (:func:`jaxtraj.estimate_points`) fits a smoothness prior of order
``m`` (white noise on the ``m``-th derivative, density ``q``) to the pixels. Linearised
about the true trajectory ``x`` (exact where the pixels are noise-free: the residual is
zero there), the estimate of the states ``z`` (positions and their first ``m - 1``
derivatives) is the solution of

    (H + Lambda / q) z_hat = H x + J^T W eps,

with ``H = J^T W J`` (block diagonal, ``J`` the pixel Jacobians, ``W = 1 / sigma^2``),
``Lambda`` the prior's (block-tridiagonal) precision and ``eps`` the pixel noise. So the
error has two parts, both exact for the linearised model:

* the prior's bias ``z_hat(0) - x``: how far the prior pulls the noise-free estimate
  towards smoother trajectories. Along the viewing rays the pixels are blind (``J`` has
  the ray in its null space), so only the prior sets the depth there: a slow camera,
  whose scale family ``c + s (x - c)`` is nearly as smooth as ``x``, gets a large bias,
  which is the failure that the posterior covariance alone does not show;
* the noise covariance ``D^-1 H D^-1`` (``D = H + Lambda / q``), whose diagonal blocks
  come exactly from a forward and a backward recursion over the block-tridiagonal factor
  (:func:`jaxtraj.estimators._blocktri.diag_sandwich`).

``q`` is the one the estimator would choose: the minimiser of the expected marginal
likelihood of the noisy pixels over :func:`jaxtraj.estimators.default_psd_grid` (the
noise-free value plus the expected noise term ``-tr(D^-1 H)``), refined by a parabola in
``log q``, held fixed for gradients. The criterion is evaluated on 8 of the 10 decades,
found in two passes, which gives the full grid's ``q`` wherever the criterion has one
minimum along the grid (:func:`_search_density`).
Everything is O(F) per trajectory and differentiable with respect to the cameras.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._checks import is_concrete
from ..estimators import _blocktri as bt
from ..estimators._common import gauss_newton_blocks, normalise_cameras
from ..estimators.smoothness import _argmin_log, _assemble, _transition, default_psd_grid
from .objectives import _metrics, project_points

__all__ = ["expected_smoother_errors_for_cameras", "smoother_error_terms"]


def smoother_error_terms(
    P: Float[ArrayLike, "F 3 4"],
    x: Float[ArrayLike, "F 3"],
    times: Float[ArrayLike, " F"],
    pixel_sigma: float = 0.3,
    order: int = 2,
    process_psd: float | None = None,
) -> tuple[Float[Array, " F"], Float[Array, " F"], Float[Array, ""]]:
    """Squared bias, noise variance per frame [m^2] and the density ``q`` of one trajectory.

    Args:
        P: (F, 3, 4) cameras; x: (F, 3) the true trajectory [m]; times: (F,) [s].
        pixel_sigma: pixel noise [px].
        order: the prior's order (1: white-noise velocity, 2: acceleration, 3: jerk).
        process_psd: the density in :func:`jaxtraj.estimators.smooth_trajectory`'s units
            (m^2 / s^(2 order - 1)); default: the expected marginal-likelihood choice.

    Returns:
        ``(bias2, noise_var, q)``: ``|E x_hat_i - x_i|^2`` and ``tr Cov x_hat_i`` (F,) of
        the linearised smoother, and the density used (physical units).
    """
    if order not in (1, 2, 3):
        raise ValueError(f"order: expected 1, 2 or 3, got {order!r}")
    P = jnp.asarray(P)
    dtype = P.dtype
    psd = None if process_psd is None else jnp.asarray(process_psd, dtype)
    return _terms(P, jnp.asarray(x, dtype), jnp.asarray(times, dtype), pixel_sigma, order, psd)


@functools.partial(jax.jit, static_argnames=("order", "full_grid"))
def _terms(P, x, times, pixel_sigma, order, process_psd, full_grid=False):
    """The traceable body of :func:`smoother_error_terms` (one compiled program when
    called on its own; inlined under an outer jit). ``full_grid``: evaluate the density's
    criterion on the whole grid instead of :func:`_search_density` (a reference)."""
    setup = _setup(P, x, times, pixel_sigma, order)
    grid, qscale = setup[-2:]
    if process_psd is None:
        criterion = _criterion(setup, order)
        if full_grid:
            values = criterion(grid)
        else:
            values = _search_density(lambda idx: criterion(grid[idx[0]])[None], grid, 1)[0]
        q = _argmin_log(grid, values)
    else:
        q = process_psd * qscale
    bias2, noise_var = _errors_at(setup, x, q, order)
    return bias2, noise_var, q / qscale


def _setup(P, x, times, pixel_sigma, order):
    """What the errors of one trajectory ``x`` need: the Gauss-Newton blocks ``(H, g, c)``
    of its pixels, the prior's transition ``(A, Qinv)`` in the smoother's time unit, the
    density grid in that unit and the unit's scale of the density."""
    dtype = P.dtype
    F = x.shape[0]
    Pn = normalise_cameras(P)
    uv = project_points(Pn, x)
    ww = jnp.full(F, 1.0, dtype) / jnp.asarray(pixel_sigma, dtype) ** 2
    H, g, c, _, _ = gauss_newton_blocks(Pn, uv, ww, x)
    tau = (times[-1] - times[0]) / (F - 1)  # the smoother's time unit
    A, Qinv = _transition(jnp.diff(times) / tau, order)
    qscale = tau ** (2 * order - 1)
    grid = jnp.asarray(default_psd_grid(order), dtype) * qscale
    return H, g, c, A, Qinv, grid, qscale


def _criterion(setup, order):
    """The density's criterion at a vector of densities (in the smoother's time unit),
    held fixed for gradients: its search sees no tangents."""
    H, g, c, A, Qinv = setup[:5]
    blocks = jax.lax.stop_gradient((H, g, c))

    def values(qs):
        return jax.vmap(lambda q: _expected_neg2_log_evidence(blocks, A, Qinv, q, order))(qs)

    return values


def _errors_at(setup, x, q, order):
    """Squared bias and noise variance per frame of the smoother at the density ``q``."""
    H, g, _, A, Qinv = setup[:5]
    D, E, b = _assemble(H, g, A, Qinv, 1 / q, order)
    chol = bt.factor(D, E)
    z = bt.solve(chol, b)
    bias2 = jnp.sum((z[:, :3] - x) ** 2, axis=1)
    # noise: the covariance of D^-1 J^T W eps is D^-1 H D^-1, its diagonal blocks in O(F)
    cov = bt.diag_sandwich(chol, H)
    return bias2, jnp.trace(cov[:, :3, :3], axis1=1, axis2=2)


def _expected_neg2_log_evidence(blocks, A, Qinv, q, order):
    """Expected -2 log marginal likelihood of the noisy pixels at the density ``q`` (in the
    smoother's time unit): the noise-free value plus the expected noise term
    ``-tr(D^-1 H)``; ``blocks``: the Gauss-Newton ``(H, g, c)`` at the true trajectory."""
    H, g, c = blocks
    F = H.shape[0]
    D, E, b = _assemble(H, g, A, Qinv, 1 / q, order)
    chol, y = bt.factor_forward(D, E, b)
    edf = jnp.einsum("fij,fji->", H, bt.diag_inverse(chol)[:, :3, :3])
    return c - jnp.sum(y * y) - edf + bt.logdet(chol) + (F - 1) * 3 * order * jnp.log(q)


_AROUND = (-2, -1, 1, 2)  # the second pass, about the first's best


def _search_density(values_at, grid, n_samples):
    """The density criterion of ``n_samples`` trajectories where it decides
    :func:`_argmin_log`'s answer, ``inf`` elsewhere: (S, n) values.

    ``values_at(idx)`` evaluates the criterion of every trajectory at its own grid indices
    ``idx`` (S, 4). Two passes of 4 evaluations, in one loop (so a program holds the
    criterion once): every third decade and the last, then the two decades either side
    of the first pass's best. Wherever the criterion has one minimum along the grid, it
    lies within two decades of the first pass's best, so the minimum and its two
    neighbours, all that :func:`_argmin_log` reads, are those of the full grid (8 of the
    10 evaluations of the default grid).
    """
    n = grid.shape[0]
    coarse = np.unique(np.append(np.arange(0, n, 3), n - 1))
    first = jnp.broadcast_to(jnp.asarray(np.resize(coarse, 4)), (n_samples, 4))

    def one_pass(p, values):
        j = jnp.asarray(coarse)[jnp.argmin(values[:, coarse], axis=1)]
        around = jnp.clip(j[:, None] + jnp.asarray(_AROUND), 0, n - 1)
        idx = jnp.where(p == 0, first, around)
        got = values_at(idx)
        got = jnp.where(jnp.isfinite(got), got, jnp.inf)
        return jax.vmap(lambda v, i, u: v.at[i].set(u))(values, idx, got)

    return jax.lax.fori_loop(0, 2, one_pass, jnp.full((n_samples, n), jnp.inf, grid.dtype))


def expected_smoother_errors_for_cameras(
    P: Float[ArrayLike, "F 3 4"],
    samples: Float[ArrayLike, "S F 3"],
    times: Float[ArrayLike, " F"],
    pixel_sigma: float = 0.3,
    order: int = 2,
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Expected ``(rms, mean)`` errors [m] of the order-``order`` smoother over the sample
    trajectories, as :func:`jaxtraj.design.expected_errors_for_cameras` for the DCT: the
    RMS ``sqrt(mean (bias^2 + var))`` and the mean ``mean sqrt(bias^2 + var)`` (Jensen: an
    upper bound on the expected mean Euclidean error)."""
    if order not in (1, 2, 3):
        raise ValueError(f"order: expected 1, 2 or 3, got {order!r}")
    P = jnp.asarray(P)
    samples = jnp.asarray(samples, P.dtype)
    if samples.ndim != 3 or samples.shape[1:] != (P.shape[0], 3):
        raise ValueError(
            f"samples: expected shape (S, {P.shape[0]}, 3) (one point per camera), got "
            f"{samples.shape}"
        )
    t = np.asarray(times) if is_concrete(times) else None
    if t is not None and (t.shape != (P.shape[0],) or np.any(np.diff(t) <= 0)):
        raise ValueError(f"times: expected {P.shape[0]} strictly increasing times")

    return _metrics(_frame_errors2(P, samples, jnp.asarray(times, P.dtype), pixel_sigma, order))


@functools.partial(jax.jit, static_argnames=("order",))
def _frame_errors2(P, samples, times, pixel_sigma, order):
    """(S, F) expected squared error per sample and frame, ``bias^2 + var``."""
    return frame_errors2_held(P, samples, times, pixel_sigma, order)[0]


def frame_errors2_held(P, samples, times, pixel_sigma, order, held=None):
    """:func:`_frame_errors2` for the design's search: ``(errors2, q)``, the (S, F)
    errors and the (S,) densities used (in the smoother's time unit).

    ``held = (q, hold)``: where the traced bool ``hold`` is true, the (S,) densities ``q``
    (as returned earlier) are used as they are and nothing is searched (the design holds a
    round's densities through its line search); otherwise, and with ``held=None``, each
    sample's density is searched (:func:`_search_density`).
    """
    setups = jax.vmap(lambda x: _setup(P, x, times, pixel_sigma, order))(samples)
    grid = setups[-2][0]

    def values_at(idx):
        return jax.vmap(lambda st, i: _criterion(st, order)(grid[i]))(setups, idx)

    def search():
        values = _search_density(values_at, grid, samples.shape[0])
        return jax.vmap(lambda v: _argmin_log(grid, v))(values)

    if held is None:
        q = search()
    else:
        q_held, hold = held
        q = jax.lax.cond(hold, lambda: jnp.asarray(q_held, grid.dtype), search)

    def one(setup, x, qi):
        bias2, var = _errors_at(setup, x, qi, order)
        return bias2 + var

    return jax.vmap(one)(setups, samples, q), q

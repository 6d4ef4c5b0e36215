"""The DCT trajectory basis as a candidate model of :func:`jaxtraj.estimate_points`.

A track is modelled as ``x(t) = Theta(t) beta`` (``Theta``: the orthonormal (F, k) DCT
basis of :func:`jaxtraj.dct_basis`, ``beta``: (k, 3)), with a Gaussian prior on ``beta``:
the constant coefficient within 1 m of the track's mean position (the smoother's start
prior, ``START_SD[0]``), every other coefficient ``N(0, s^2)``. On the reprojection error
linearised at a trajectory ``x_lin`` (Gauss-Newton blocks ``H_f, g_f, c`` per frame) the
marginal likelihood is Gaussian and exact::

    -2 log p(pixels | k, s) = c + mu' S^-1 mu - b' N^-1 b + log det N + log det S
    N = Theta' H Theta + S^-1,   b = Theta' g + S^-1 mu

which is the same expression, on the same linearised data and with the same normalising
terms, as the smoother's evidence in :mod:`.estimate`: the DCT sizes and the smoother
orders compare on one scale. ``s`` is chosen per track by the marginal likelihood on half
decades (as the smoother's noise density) on the data linearised at the best smoother's
estimate; each size's likelihood is then evaluated on the data linearised at its own
estimate (one relinearisation), so that no model is judged at another's trajectory.

The evidence is trusted only where its factor is: a candidate whose precision ``N`` has a
pivot below ``sqrt(eps)`` of its diagonal entry (``L_ii^2 < sqrt(eps) N_ii``: half the
digits lost, or a pivot clamped by :func:`jaxtraj._spd.inverse_cholesky`) has no evidence
(``inf``). Such an ``N`` arises where the data are linearised at a trajectory passing
close to a camera (a 300 m wrong fit once won on ``log det N`` of clamped pivots, status
OK). The scale grid skips such scales too.

Only the choice between models is made here; whether the depth is determined is decided
by the smoothness priors' ``kappa`` (:mod:`._depth`): a DCT fit is admissible only where
some smoothness order is (the pixels are blind along the rays for every model alike).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._spd import inverse_cholesky, matvec, vecmat
from ..basis import dct_basis
from ..solve import _reprojection_rms
from ._common import gauss_newton_blocks

#: Prior standard deviation of a non-constant coefficient's contribution per frame
#: (``s / sqrt(F)``) [m]: 1 mm to 3 m in half decades.
AMPLITUDE_GRID = 10.0 ** np.arange(-3.0, 0.51, 0.5)


def data_blocks(Pn, uv, w, X, sigma2):
    """Gauss-Newton blocks ``H, g, c`` of the reprojection error linearised at ``X``."""
    return gauss_newton_blocks(Pn, uv, w / sigma2, X)[:3]


def _prior(theta, x_lin, s, dc_sd):
    """Precision (3k,) and mean (3k,) of the coefficients, k-major."""
    F, k = theta.shape
    prec = jnp.full((k, 3), 1.0 / s**2).at[0].set(1.0 / (F * dc_sd**2))
    mean = jnp.zeros((k, 3), x_lin.dtype).at[0].set(jnp.sqrt(F) * jnp.mean(x_lin, axis=0))
    return prec.reshape(-1), mean.reshape(-1)


def _coefficient_blocks(theta, H, g):
    """The data's normal equations in the coefficients, k-major: (3k, 3k) and (3k,)."""
    k = theta.shape[1]
    Hb = jnp.einsum("fj,fl,fab->jalb", theta, theta, H).reshape(3 * k, 3 * k)
    return Hb, jnp.einsum("fj,fa->ja", theta, g).reshape(-1)


def _posterior(Hb, gb, c, prec, mean):
    """-2 log evidence (``inf`` where the factor is not trusted, see the module notes),
    coefficients (3k,) and ``W = L^-1``, the inverse Cholesky factor of their precision
    ``L L^T`` (no LAPACK call: batched over tracks and scales, LAPACK's Cholesky
    deadlocked on 2 cores with jaxlib 0.10, see :mod:`jaxtraj._spd`)."""
    b = gb + prec * mean
    N = Hb + jnp.diag(prec)
    # the rows' loop, not unrolled: estimate_points holds 4 sizes x 9 of these factors,
    # and unrolled they made half its compile time (first call at F = 40, 6 tracks:
    # 32-35 -> 15-16 s; warm, F = 150, 256 tracks: 2.46 -> 2.44-2.59 ms per point)
    W = inverse_cholesky(N, unroll=False)
    y = matvec(W, b)
    beta = vecmat(y, W)
    neg2 = (
        c
        + jnp.sum(prec * mean * mean)
        - jnp.sum(y * y)
        - 2.0 * jnp.sum(jnp.log(jnp.diagonal(W)))
        - jnp.sum(jnp.log(prec))
    )
    return jnp.where(_pivots_healthy(N, W), neg2, jnp.inf), beta, W


def _pivots_healthy(N, W):
    """Whether every pivot ``L_ii^2 = 1 / W_ii^2`` of ``N = L L^T`` keeps at least half
    the digits of its diagonal entry: ``L_ii^2 >= sqrt(eps) N_ii``."""
    floor = jnp.sqrt(jnp.finfo(N.dtype).eps)
    d = jnp.diagonal(W)
    return jnp.all(1.0 >= floor * jnp.diagonal(N) * d * d)


def _best_scale(theta, Hb, gb, c, x_lin, dc_sd):
    grid = jnp.asarray(AMPLITUDE_GRID, Hb.dtype) * jnp.sqrt(theta.shape[0])

    def at(s):
        return _posterior(Hb, gb, c, *_prior(theta, x_lin, s, dc_sd))[0]

    crit = jax.vmap(at)(grid)
    return grid[jnp.argmin(jnp.where(jnp.isfinite(crit), crit, jnp.inf))]


def dct_fit(Pn, uv, w, times, sigma2, x_lin, blocks, k, dc_sd):
    """The DCT model of size ``k`` for one track: (-2 log evidence, points (F, 3),
    covariance (F, 3, 3), rms_px). The coefficient scale ``s`` is chosen on the data
    linearised at ``x_lin`` (``blocks``: its ``data_blocks``, shared by every size); the
    estimate, its evidence and covariance are then those of the data linearised at the
    first estimate (one relinearisation)."""
    theta = dct_basis(times, k).astype(x_lin.dtype)
    Hb, gb = _coefficient_blocks(theta, *blocks[:2])
    c = blocks[2]
    s = _best_scale(theta, Hb, gb, c, x_lin, dc_sd)
    _, beta, _ = _posterior(Hb, gb, c, *_prior(theta, x_lin, s, dc_sd))
    x = theta @ beta.reshape(k, 3)
    H, g, c = data_blocks(Pn, uv, w, x, sigma2)
    Hb, gb = _coefficient_blocks(theta, H, g)
    neg2, beta, Linv = _posterior(Hb, gb, c, *_prior(theta, x, s, dc_sd))
    x = theta @ beta.reshape(k, 3)
    # covariance of the coefficients N^-1, then of each x_f = (theta_f kron I3)' beta
    cov_b = (Linv.T @ Linv).reshape(k, 3, k, 3)
    cov = jnp.einsum("fj,jalb,fl->fab", theta, cov_b, theta)
    return neg2, x, cov, _reprojection_rms(Pn, uv, x, w > 0)

"""Trajectory bases evaluated at arbitrary timestamps.

The paper (eq. 3) samples the DCT-II basis at frame midpoints,
``Phi[x, u] = cos(pi (2x + 1) u / (2F))`` for ``x = 0..F-1`` and ``u = 0..k-1``.
In normalised time ``tau = (2x + 1) / (2F)`` this is ``cos(pi u tau)``, which is defined
for any timestamp. :class:`DCTBasis` maps real times onto ``tau`` through a *span*
``[t0, t1]`` so that

* irregular ("discontinuous") image times are handled exactly,
* the fitted trajectory can be evaluated between and slightly past the frames,
* velocity and acceleration are analytic derivatives of the same basis.

For uniformly spaced times the default span extends half a sample beyond the first and
last time, which reproduces the paper's eq. 3 exactly (up to column scaling).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

__all__ = ["DCTBasis", "dct_basis"]


class DCTBasis(eqx.Module):
    """A DCT-II trajectory basis on the time span ``[t0, t1]``.

    Attributes:
        t0, t1: the span in seconds (or any time unit); ``tau = (t - t0) / (t1 - t0)``.
        size: the number of samples ``F`` that sets the orthonormal scaling
            (``1/sqrt(F)`` for the constant column, ``sqrt(2/F)`` for the others). With
            uniform samples over the span the columns are then orthonormal.
        k: number of basis vectors (static).
        orthonormal: ``False`` gives the paper's unscaled eq. 3 (static).
    """

    t0: Float[Array, ""]
    t1: Float[Array, ""]
    size: Float[Array, ""]
    k: int = eqx.field(static=True)
    orthonormal: bool = eqx.field(static=True, default=True)

    @classmethod
    def from_times(
        cls,
        times: ArrayLike,
        k: int,
        *,
        span: tuple[float, float] | None = None,
        orthonormal: bool = True,
    ) -> DCTBasis:
        """Build the basis that fits the given sample times.

        Args:
            times: (F,) sample times, increasing.
            k: number of basis vectors, ``1 <= k``.
            span: ``(t0, t1)``; by default half a mean sample spacing beyond the first and
                last time, which reproduces the paper's eq. 3 for uniform samples.
            orthonormal: scale columns to unit norm (default) or use eq. 3 as printed.
        """
        times = jnp.asarray(times)
        if times.ndim != 1:
            raise ValueError(f"times: expected shape (F,), got {times.shape}")
        _check_k(k)
        n = times.shape[0]
        if span is None:
            if n < 2:
                raise ValueError("times: need at least 2 samples to infer a span; pass span=")
            half = 0.5 * (times[-1] - times[0]) / (n - 1)
            t0, t1 = times[0] - half, times[-1] + half
        else:
            t0, t1 = span
        dtype = jnp.result_type(times.dtype, jnp.float32)
        return cls(
            t0=jnp.asarray(t0, dtype),
            t1=jnp.asarray(t1, dtype),
            size=jnp.asarray(n, dtype),
            k=int(k),
            orthonormal=orthonormal,
        )

    def _scale(self, dtype) -> Float[Array, " k"]:
        u = jnp.arange(self.k)
        if not self.orthonormal:
            return jnp.ones(self.k, dtype)
        return jnp.where(u == 0, jnp.sqrt(1.0 / self.size), jnp.sqrt(2.0 / self.size)).astype(dtype)

    def __call__(self, times: ArrayLike, derivative: int = 0) -> Float[Array, "F k"]:
        """Evaluate the basis (or its ``derivative``-th time derivative) at ``times``.

        Returns an (F, k) matrix; row ``i`` is ``phi(times[i])``. Derivatives are in
        units of ``1 / time**derivative``.
        """
        if derivative not in (0, 1, 2):
            raise ValueError(f"derivative: expected 0, 1 or 2, got {derivative}")
        times = jnp.asarray(times, self.t0.dtype)
        length = self.t1 - self.t0
        tau = (times - self.t0) / length
        w = jnp.pi * jnp.arange(self.k, dtype=times.dtype)  # angular frequency in tau
        arg = tau[:, None] * w
        if derivative == 0:
            vals = jnp.cos(arg)
        elif derivative == 1:
            vals = -jnp.sin(arg) * (w / length)
        else:
            vals = -jnp.cos(arg) * (w / length) ** 2
        return vals * self._scale(times.dtype)


def dct_basis(
    times: ArrayLike,
    k: int,
    *,
    span: tuple[float, float] | None = None,
    derivative: int = 0,
    orthonormal: bool = True,
) -> Float[Array, "F k"]:
    """The (F, k) DCT trajectory basis at ``times`` (paper eq. 3, orthonormal by default).

    ``dct_basis(jnp.arange(F), k)`` equals the paper's eq. 3 with columns scaled to unit
    norm; ``orthonormal=False`` gives eq. 3 as printed. For irregular times the basis is
    ``cos(pi u tau)`` with ``tau`` the normalised time (see :class:`DCTBasis`).

    Args:
        times: (F,) sample times.
        k: number of basis vectors.
        span: optional ``(t0, t1)`` of the normalised time axis.
        derivative: 0 for positions, 1 for velocity, 2 for acceleration bases.
        orthonormal: column scaling, see above.
    """
    basis = DCTBasis.from_times(times, k, span=span, orthonormal=orthonormal)
    return basis(times, derivative)


def paper_dct_matrix(F: int, k: int) -> np.ndarray:
    """Eq. 3 of the paper exactly as printed, in NumPy (a reference for tests and docs)."""
    x = np.arange(F)[:, None]
    u = np.arange(1, k + 1)[None, :]
    return np.cos(np.pi * (2 * x + 1) * (u - 1) / (2 * F))


def _check_k(k) -> None:
    if not isinstance(k, (int, np.integer)) or isinstance(k, bool) or k < 1:
        raise ValueError(f"k: expected a positive integer number of basis vectors, got {k!r}")


def max_k(num_observed_frames: int) -> int:
    """The largest k with ``2 F' >= 3 k`` (the counting bound of paper eq. 6)."""
    return (2 * int(num_observed_frames)) // 3

"""A camera path with few parameters that a robot can execute.

The camera centre is a smooth curve ``c(t) = c_start + (phi(t) - phi(t_0)) theta``, with
``phi`` a DCT basis of ``k`` vectors over the recording and ``theta`` (k, 3) the design
parameters, so the path starts exactly at ``c_start``. The camera looks at the predicted
workpiece point at every image (``look_at``), which keeps the point near the image centre.
Velocity and acceleration follow analytically from the basis derivatives; they are
checked on a fine time grid, not only at the image times.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._checks import check_shape
from ..basis import DCTBasis
from ..camera import look_at, projection_matrix

__all__ = ["CameraPathModel"]


class CameraPathModel(eqx.Module):
    """The camera path model for one recording (a pytree; ``theta`` is passed separately).

    Attributes:
        times: (F,) image times [s].
        grid: (G,) times at which velocity and acceleration limits are checked [s].
        basis: the DCT basis of the camera centre (``k`` vectors over the span).
        c_start: (3,) camera centre at ``times[0]`` [m].
        up: (3,) world direction that appears "up" in the images (not along a view ray).
    """

    times: Float[Array, " F"]
    grid: Float[Array, " G"]
    basis: DCTBasis
    c_start: Float[Array, " 3"]
    up: Float[Array, " 3"]

    @classmethod
    def create(
        cls,
        times: Float[ArrayLike, " F"],
        k: int,
        c_start: Float[ArrayLike, " 3"],
        *,
        grid_size: int = 200,
        up: Float[ArrayLike, " 3"] = (0.0, 1.0, 0.0),
    ) -> CameraPathModel:
        """A model with ``k`` basis vectors over ``[times[0], times[-1]]``.

        Args:
            times: (F,) increasing image times [s].
            k: DCT vectors of the camera centre (>= 2); more is more agile.
            c_start: (3,) start position of the camera [m].
            grid_size: samples of the limit checks.
            up: world "up" direction of the images; default +y (cameras look down -z).
        """
        times = jnp.asarray(times)
        check_shape("times", times, (None,), "(F,) image times")
        check_shape("c_start", c_start, (3,), "start position of the camera")
        if not isinstance(k, int) or k < 2:
            raise ValueError(f"k: expected an int >= 2, got {k!r}")
        dtype = jnp.result_type(times.dtype, jnp.float32)
        times = times.astype(dtype)
        t0, t1 = times[0], times[-1]
        basis = DCTBasis.from_times(times, k, span=(t0, t1))
        grid = jnp.linspace(t0, t1, grid_size, dtype=dtype)
        return cls(times, grid, basis, jnp.asarray(c_start, dtype), jnp.asarray(up, dtype))

    @property
    def k(self) -> int:
        return self.basis.k

    def _rows(self, t, derivative: int = 0):
        return self.basis(t, derivative=derivative)

    def centres(self, theta: Float[ArrayLike, "k 3"], t=None) -> Float[Array, "T 3"]:
        """Camera centres (T, 3) at times ``t`` (default: the image times) [m]."""
        t = self.times if t is None else jnp.asarray(t)
        start = self._rows(self.times[:1])
        return self.c_start + (self._rows(t) - start) @ jnp.asarray(theta)

    def velocity(self, theta, t=None) -> Float[Array, "T 3"]:
        """Camera-centre velocity (T, 3) [m/s] at ``t`` (default: the limit grid)."""
        t = self.grid if t is None else jnp.asarray(t)
        return self._rows(t, 1) @ jnp.asarray(theta)

    def acceleration(self, theta, t=None) -> Float[Array, "T 3"]:
        """Camera-centre acceleration (T, 3) [m/s^2] at ``t`` (default: the limit grid)."""
        t = self.grid if t is None else jnp.asarray(t)
        return self._rows(t, 2) @ jnp.asarray(theta)

    def poses(self, theta, targets: Float[ArrayLike, "F 3"]) -> tuple[Array, Array]:
        """World-to-camera poses ``(R_c_w (F, 3, 3), t_c_w (F, 3))`` looking at ``targets``."""
        c = self.centres(theta)
        return jax.vmap(lambda p, x: look_at(p, x, self.up))(c, jnp.asarray(targets, c.dtype))

    def projection_matrices(self, theta, K: Float[ArrayLike, "3 3"], targets) -> Array:
        """(F, 3, 4) projection matrices of the path looking at ``targets``."""
        R, t = self.poses(theta, targets)
        K = jnp.asarray(K, R.dtype)
        return jax.vmap(lambda RR, tt: projection_matrix(K, RR, tt))(R, t)

    def fit(self, centres: Float[ArrayLike, "F 3"]) -> Float[Array, "k 3"]:
        """Parameters whose path is closest (least squares) to given centres at the image
        times, with the start fixed at ``c_start`` (e.g. an initial guess from a heuristic
        path)."""
        A = self._rows(self.times) - self._rows(self.times[:1])
        return jnp.linalg.lstsq(A, jnp.asarray(centres) - self.c_start)[0]

"""float32 with x64 enabled: the dtype optimistix's least-squares solvers can run in.

optimistix's Levenberg-Marquardt keeps its damping factor in the default float dtype, so
with x64 enabled float32 residuals fail (lineax: "Vector and operator structures do not
match"). Callers with float32 inputs solve in float64 there and cast their results back.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["cast_floats", "least_squares_dtype"]


def least_squares_dtype(dtype):
    """The dtype in which optimistix's Levenberg-Marquardt runs for inputs of ``dtype``.
    With x64 enabled its damping factor is float64, and float32 residuals then fail
    (lineax: "Vector and operator structures do not match"); such inputs are solved in
    float64 and the results cast back (:func:`cast_floats`)."""
    return jnp.promote_types(dtype, jnp.float64) if jax.config.jax_enable_x64 else dtype


def cast_floats(tree, dtype):
    """Every floating-point array of ``tree`` cast to ``dtype`` (other leaves unchanged)."""
    return jax.tree.map(
        lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, tree
    )

"""Clamped uniform B-spline basis and its derivatives at given times (host-side NumPy).

The joint-space camera path is a B-spline (:mod:`.joint_path`); its basis matrices are
constant for a problem's time grid, so they are computed once, on the host, by the
Cox-de Boor recursion, and enter the JAX core as plain arrays:

    B_{i,0}(t) = [k_i <= t < k_{i+1}],
    B_{i,p}(t) = (t - k_i) / (k_{i+p} - k_i) B_{i,p-1}(t)
               + (k_{i+p+1} - t) / (k_{i+p+1} - k_{i+1}) B_{i+1,p-1}(t),
    d/dt B_{i,p} = p (B_{i,p-1} / (k_{i+p} - k_i) - B_{i+1,p-1} / (k_{i+p+1} - k_{i+1})),

with 0/0 = 0. Clamped knots (``degree + 1``-fold at both ends) make the curve start at its
first control point with derivatives set by the first few control points only.
"""

from __future__ import annotations

import numpy as np

__all__ = ["bspline_basis", "clamped_knots"]


def clamped_knots(t0: float, t1: float, n_control: int, degree: int) -> np.ndarray:
    """Knot vector (n_control + degree + 1,) of a clamped uniform B-spline on [t0, t1]."""
    if n_control < degree + 1:
        raise ValueError(
            f"n_control: a degree-{degree} B-spline needs at least {degree + 1} control "
            f"points, got {n_control}"
        )
    if not t1 > t0:
        raise ValueError(f"times: expected t1 > t0, got [{t0}, {t1}]")
    inner = np.linspace(t0, t1, n_control - degree + 1)
    return np.concatenate([np.full(degree, t0), inner, np.full(degree, t1)])


def _divide(a, b):
    return np.divide(a, b, out=np.zeros_like(a), where=b != 0)


def bspline_basis(t, knots, degree: int, derivative: int = 0) -> np.ndarray:
    """(T, n_control) B-spline basis (or its ``derivative``-th time derivative) at ``t``.

    Times outside ``[knots[0], knots[-1]]`` are clamped to it; the right end belongs to the
    last span (the basis sums to 1 there too).
    """
    t = np.clip(np.asarray(t, float), knots[0], knots[-1])
    k = np.asarray(knots, float)
    n_control = len(k) - degree - 1
    if derivative > degree:
        return np.zeros((t.size, n_control))
    if degree == 0:
        last = np.flatnonzero(k[1:] > k[:-1]).max()  # last non-empty span
        span = np.searchsorted(k, t, side="right") - 1
        span = np.where(t >= k[-1], last, span)
        return (span[:, None] == np.arange(len(k) - 1)[None, :]).astype(float)
    lower = bspline_basis(t, k, degree - 1, max(derivative - 1, 0))  # (T, n_control + 1)
    i = np.arange(n_control)
    left = k[i + degree] - k[i]
    right = k[i + degree + 1] - k[i + 1]
    if derivative == 0:
        a = _divide(t[:, None] - k[i], np.broadcast_to(left, (t.size, n_control)))
        b = _divide(k[i + degree + 1] - t[:, None], np.broadcast_to(right, (t.size, n_control)))
        return a * lower[:, :-1] + b * lower[:, 1:]
    return degree * (
        _divide(lower[:, :-1], np.broadcast_to(left, lower[:, :-1].shape))
        - _divide(lower[:, 1:], np.broadcast_to(right, lower[:, 1:].shape))
    )

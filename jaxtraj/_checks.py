"""Host-side input validation shared by the public drivers.

Shape checks run at trace time (shapes are static). Value checks (NaN pixels, too few
observed frames) run only on concrete arrays; under ``jit`` the same conditions are
reported through the result's ``status`` instead.
"""

from __future__ import annotations

import jax
import numpy as np


def is_concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


def check_shape(name: str, x, expected: tuple, what: str) -> None:
    """Raise ``ValueError`` unless ``x.shape`` matches ``expected`` (None = any size)."""
    shape = np.shape(x)
    ok = len(shape) == len(expected) and all(
        e is None or e == s for e, s in zip(expected, shape, strict=True)
    )
    if not ok:
        parts = ["?" if e is None else str(e) for e in expected]
        exp = "(" + ", ".join(parts) + ("," if len(parts) == 1 else "") + ")"
        raise ValueError(f"{name}: expected shape {exp} ({what}), got {tuple(shape)}")


def check_finite(name: str, x, mask=None, hint: str = "") -> None:
    """Raise ``ValueError`` if a concrete array has NaN/inf entries (where ``mask``)."""
    if not is_concrete(x, mask):
        return
    arr = np.asarray(x)
    bad = ~np.isfinite(arr)
    if bad.ndim > 1:
        bad = bad.reshape(bad.shape[0], -1).any(axis=1)
    if mask is not None:
        bad = bad & np.asarray(mask, bool)
    if bad.any():
        idx = np.flatnonzero(bad)
        shown = ", ".join(map(str, idx[:8])) + (" ..." if idx.size > 8 else "")
        raise ValueError(f"{name}: {idx.size} non-finite entr(y/ies) at index {shown}. {hint}")


def check_tracks(uv, weights) -> None:
    """Value checks of pixel tracks (..., F, 2) and weights (..., F) on concrete arrays.

    Weights must be finite and >= 0 (0 marks a missing detection); pixels with non-zero
    weight must be finite. Under ``jit`` nothing is checked here: solvers report such
    data through their status instead.
    """
    if not is_concrete(uv, weights):
        return
    w = np.ones(np.shape(uv)[:-1]) if weights is None else np.asarray(weights)
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError("weights: must be finite and >= 0 (0 marks a missing detection)")
    bad = ~np.all(np.isfinite(np.asarray(uv)), axis=-1) & (w > 0)
    if bad.any():
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(
            f"uv: {int(bad.sum())} non-finite pixel(s) with non-zero weight, first at index "
            f"{where} (track, frame). Give a missing detection weight 0."
        )

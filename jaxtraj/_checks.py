"""Host-side input validation shared by the public drivers.

Shape checks run at trace time (shapes are static). Value checks (NaN pixels, too few
observed frames) run only on concrete arrays; under ``jit`` the same conditions are
reported through the result's ``status`` instead. Tracks that live on an accelerator are
checked there, and only a few numbers come back to the host (copying the tracks to the
host cost 4-5 us per point on a GPU, several times the solve); the tracks are copied only
to word the error message once a check fails.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ._batching import platform_of


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


def on_accelerator(*xs) -> bool:
    """True if any argument is a concrete ``jax.Array`` on a device other than the CPU."""
    return any(isinstance(x, jax.Array) and is_concrete(x) and platform_of(x) != "cpu" for x in xs)


@jax.jit
def _track_summary(uv, weights):
    # (weights finite and >= 0, count of non-finite pixels with weight > 0, fewest
    # observed frames of a track), computed where the tracks live
    w = jnp.ones(uv.shape[:-1], uv.dtype) if weights is None else weights
    w_ok = jnp.all(jnp.isfinite(w) & (w >= 0))
    n_bad = jnp.sum(~jnp.all(jnp.isfinite(uv), axis=-1) & (w > 0))
    return w_ok, n_bad, jnp.min(jnp.sum(w > 0, axis=-1))


def check_tracks(uv, weights) -> int | None:
    """Value checks of pixel tracks (..., F, 2) and weights (..., F) on concrete arrays.

    Weights must be finite and >= 0 (0 marks a missing detection); pixels with non-zero
    weight must be finite. Under ``jit`` nothing is checked here (returns None): solvers
    report such data through their status instead. Returns the smallest number of frames
    with non-zero weight over the tracks (for the solvers' count checks).
    """
    if not is_concrete(uv, weights):
        return None
    if on_accelerator(uv, weights):
        w_ok, n_bad, n_obs = jax.device_get(_track_summary(jnp.asarray(uv), weights))
        if w_ok and n_bad == 0:
            return int(n_obs)  # else: the host copy below words the message
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
    return int(np.min(np.sum(w > 0, axis=-1)))

"""Target corners detected elsewhere: a CSV ``view,id,u,v`` (one row per corner).

``view`` names the view (an image file name or any label; views are paired with robot
poses by :func:`jaxtraj.io.robot_poses.pair_views`), ``id`` is the corner's index in the
target's :meth:`~jaxtraj.vision.calibration.CalibrationTarget.object_points` (chessboard:
row-major from the top-left inner corner; ChArUco: the ChArUco id; circle grid: OpenCV's
order), ``u, v`` its pixel [px] (OpenCV's convention: (0, 0) is the centre of the top-left
pixel). Views may list any subset of the corners (partial views).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .tables import read_table, write_table

__all__ = ["read_corners", "write_corners"]


def read_corners(path: str | Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Read a corners CSV.

    Returns:
        ``{view: (ids (n,) int64 ascending, uv (n, 2) float64)}`` in order of appearance.

    Raises:
        RecordingError: a bad row (naming its line), a negative id, an id repeated within
            a view.
    """
    tab = read_table(path, {"view": "str", "id": "int", "u": "float", "v": "float"})
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    views = [str(v) for v in tab["view"]]
    first: dict[tuple[str, int], int] = {}
    for r, (view, i) in enumerate(zip(views, tab["id"].tolist(), strict=True)):
        if i < 0:
            raise tab.error(r, f"id {i}: expected a corner index >= 0")
        if (view, i) in first:
            raise tab.error(r, f"corner id {i} of view {view!r} repeated (first on line "
                            f"{first[(view, i)]})")  # fmt: skip
        first[(view, i)] = int(tab.lines[r])
    for view in dict.fromkeys(views):
        rows = np.flatnonzero(np.asarray(views) == view)
        ids = tab["id"][rows].astype(np.int64)
        order = np.argsort(ids)
        uv = np.stack([tab["u"][rows], tab["v"][rows]], 1)[order]
        out[view] = (ids[order], uv)
    return out


def write_corners(path: str | Path, corners: dict) -> None:
    """Write ``{view: (ids, uv)}`` as a corners CSV (``read_corners`` reads it back)."""
    view, ids, u, v = [], [], [], []
    for name, (i, uv) in corners.items():
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        view += [str(name)] * len(uv)
        ids += [int(k) for k in np.ravel(i)]
        u += uv[:, 0].tolist()
        v += uv[:, 1].tolist()
    write_table(
        path,
        ["view", "id", "u", "v"],
        [np.asarray(view), np.asarray(ids, np.int64), np.asarray(u), np.asarray(v)],
    )

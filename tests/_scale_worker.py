"""Run by tests/test_scale.py in a subprocess (XLA_FLAGS must be set before JAX starts).

Usage: python _scale_worker.py shard OUT_JSON
       python _scale_worker.py make N DATASET_DIR
       python _scale_worker.py memory DATASET_DIR OUT_DIR OUT_JSON
"""

from __future__ import annotations

import json
import resource
import sys
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from jaxtraj import dct_basis, reconstruct_points  # noqa: E402
from jaxtraj.scale import (  # noqa: E402
    point_mesh,
    reconstruct_recordings_sharded,
    reconstruct_sharded,
    run_batch,
    write_dataset,
)


def many_points(rng, n, F=30, k=5):
    """n point tracks (n, F, 2) seen by one random camera path, plus P, times."""
    times = np.sort(rng.uniform(0.0, 2.0, F))
    basis = np.asarray(dct_basis(times, k))
    X = np.einsum("fk,nkc->nfc", basis, rng.normal(size=(n, k, 3)) * 0.1)
    C = rng.uniform(-1, 1, (F, 3)) * 0.6 + np.array([0, 0, 1.5])
    K = np.array([[700.0, 0, 320], [0, 700.0, 240], [0, 0, 1]])
    P = []
    for c in C:
        z = -c / np.linalg.norm(c)
        x = np.cross(z, [0, 1.0, 0])
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        P.append(K @ np.c_[R, -R @ c])
    P = np.asarray(P)
    h = np.einsum("fij,nfj->nfi", P[:, :, :3], X) + P[:, :, 3]
    uv = h[..., :2] / h[..., 2:] + rng.normal(0, 0.3, (n, F, 2))
    return P, times, uv, X


def shard(out_json):
    rng = np.random.default_rng(0)
    P, times, uv, _ = many_points(rng, 101)
    w = (rng.uniform(size=uv.shape[:2]) > 0.1).astype(float)
    basis = dct_basis(times, 5)
    one = reconstruct_points(P, uv, basis, w)
    many = reconstruct_sharded(P, uv, basis, w, mesh=point_mesh())
    shards = len(many.points.sharding.device_set)
    # chunked on disk, sharded over the 4 devices, against the one-shot call
    tmp = Path(out_json).parent
    write_dataset(tmp / "ds", P, times, uv, w)
    run_batch(tmp / "ds", tmp / "out", k=5, chunk_size=32, mesh=point_mesh())
    pts = np.load(tmp / "out" / "points.npy")
    single = np.asarray(one.points)
    result = {
        "devices": len(jax.devices()),
        "shards": shards,
        "sharded_vs_single": float(
            np.max(np.abs(np.asarray(many.points) - np.asarray(one.points)))
        ),
        "status_equal": bool(np.array_equal(np.asarray(many.status), np.asarray(one.status))),
        "chunked_sharded_vs_single": float(np.max(np.abs(pts - single))),
    }
    # many recordings (each with its own cameras), recording axis sharded
    recs = [many_points(np.random.default_rng(10 + r), 9) for r in range(6)]
    Ps = np.stack([r[0] for r in recs])
    uvs = np.stack([r[2] for r in recs])
    rs = reconstruct_recordings_sharded(Ps, uvs, basis, mesh=point_mesh())
    loop = np.stack(
        [np.asarray(reconstruct_points(p, u, basis).points) for p, u in zip(Ps, uvs, strict=True)]
    )
    result["recordings_vs_loop"] = float(np.max(np.abs(np.asarray(rs.points) - loop)))
    # design candidates split over the devices
    result["design_vs_single"] = _design_check()
    Path(out_json).write_text(json.dumps(result))


def _design_check():
    import jax.numpy as jnp

    from jaxtraj.design import CameraPathModel, CellLimits, design_camera_path

    times = jnp.linspace(0.0, 3.0, 16)
    pred = jnp.stack([0.2 * jnp.sin(times), 0.1 * jnp.cos(times), 0.0 * times], 1)
    model = CameraPathModel.create(times, 10, pred[0] + jnp.array([0.0, 0.0, 0.8]))
    limits = CellLimits(workspace_lo=(-2.0, -2.0, 0.2), workspace_hi=(2.0, 2.0, 2.0))
    K = jnp.array([[700.0, 0, 320], [0, 700.0, 240], [0, 0, 1]])
    base = model.fit(pred + jnp.array([0.0, 0.0, 0.8]))
    inits = base + 0.01 * jax.random.normal(jax.random.PRNGKey(0), (5, *base.shape))
    args = (model, K, pred, pred[None], dct_basis(times, 4), limits, inits)
    one = design_camera_path(*args, objective="eta", max_steps=20)[1]
    many = design_camera_path(*args, objective="eta", max_steps=20, mesh=point_mesh())[1]
    return float(jnp.max(jnp.abs(one.theta - many.theta)))


def make(n, dataset):
    rng = np.random.default_rng(1)
    P, times, uv, _ = many_points(rng, 1, F=60, k=8)
    # n tracks written in blocks so that the writer's memory does not depend on n
    write_dataset(dataset, P, times, np.zeros((0, 60, 2)))
    f = np.lib.format.open_memmap(Path(dataset) / "tracks.npy", "w+", np.float64, (n, 60, 2))
    for a in range(0, n, 4096):
        b = min(n, a + 4096)
        f[a:b] = uv[0] + rng.normal(0, 0.3, (b - a, 60, 2))
    f.flush()


def memory(dataset, out, out_json):
    """Peak resident memory of a process that only runs the batch."""
    summary = run_batch(dataset, out, k=8, chunk_size=2048)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    Path(out_json).write_text(json.dumps({"peak_kib": peak, "computed": summary.computed}))


if __name__ == "__main__":
    if sys.argv[1] == "shard":
        shard(sys.argv[2])
    elif sys.argv[1] == "make":
        make(int(sys.argv[2]), sys.argv[3])
    else:
        memory(sys.argv[2], sys.argv[3], sys.argv[4])

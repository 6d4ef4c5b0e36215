"""``jaxtraj demo``: the paper's experiment (section 5) in a simulated robot cell.

1. One robot moves a workpiece along an arbitrary smooth 3D curve; a second robot
   carries the camera and moves randomly and discontinuously around it; images are
   taken at irregular times (``jaxtraj.sim.paper_experiment``).
2. The assembly point's trajectory is reconstructed with the DCT basis (paper eq. 6).
3. A rigid workpiece with five markers is reconstructed marker by marker and its 6-DoF
   pose fitted per frame (Kabsch).
4. Errors are printed; Fig. 3/4 of the paper and a JSON summary are written.
"""

from __future__ import annotations

import json
import os
import time
from argparse import Namespace
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ._cli_common import EXIT_FAILED, EXIT_OK, UsageError
from .analysis import reconstructibility
from .basis import DCTBasis
from .pipeline.evaluate import rotation_error_deg
from .rigid import fit_rigid
from .solve import Status, reconstruct_points

#: Default number of DCT vectors for 150 images over 10 s (the noise floor is reached at
#: about k = 20-25 on the simulated cell; see README, "Choosing k").
DEFAULT_K = 20


def _cast(tree, dtype):
    """Floating-point leaves of a pytree in ``dtype`` (the demo's --float32 switch)."""
    return jax.tree_util.tree_map(
        lambda x: x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x, tree
    )


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    os.replace(tmp, path)


def _estimate(method: str, P, uv, times, weights, k: int, noise: float):
    """Reconstruct N tracks (N, F, 2) seen by the same cameras with the chosen method.

    Returns points (N, F, 3), reprojection RMS (N,), conditioning gain (N,) or None,
    a per-track OK flag (N,) and a label for the printout.
    """
    if method == "dct":
        res = reconstruct_points(P, uv, DCTBasis.from_times(times, k)(times), weights)
        return res.points, res.rms_px, res.gain, res.status == Status.OK, f"DCT k={k}"
    if method == "auto-k":
        from .estimators import select_k_cv

        # candidates up to 60 (as for the regularised DCT) and at most what every fold's
        # training frames (4/5 of them) can fit
        k_max = max(4, min(60, (8 * times.shape[0]) // 15))
        ks = tuple(range(4, k_max + 1, 2))
        # cameras and times as arguments, not as constants baked into the program
        choose = jax.jit(
            jax.vmap(lambda P, u, t, w: select_k_cv(P, u, t, ks, w).k, (None, 0, None, 0))
        )
        chosen = np.sort(np.asarray(choose(P, uv, times, weights)))
        # the (lower) median over the tracks; 0 (no admissible candidate): the smallest
        k_auto = int(chosen[(chosen.size - 1) // 2]) or ks[0]
        *fit, _ = _estimate("dct", P, uv, times, weights, k_auto, noise)
        return (*fit, f"DCT k={k_auto} (cross-validated, gain-weighted)")
    if method == "regularised":
        from .estimators import roughness_penalty, select_penalty_cv

        basis = DCTBasis.from_times(times, min(times.shape[0], 60))
        lam = select_penalty_cv(P, uv[0], basis, times, weights[0]).lam
        pen = lam * roughness_penalty(basis)
        res = reconstruct_points(P, uv, basis(times), weights, penalty=pen)
        label = f"regularised DCT k={basis.k}, lambda={float(lam):.2g} (cross-validated)"
        return res.points, res.rms_px, res.gain, res.status == Status.OK, label
    from .estimators import smooth_points

    sm = smooth_points(P, uv, times, weights, pixel_sigma=max(noise, 0.05), covariance=False)
    ok = jnp.all(jnp.isfinite(sm.points), axis=(-2, -1))
    return sm.points, sm.rms_px, None, ok, "smoothness prior (white-noise acceleration)"


def run_demo(args: Namespace) -> int:
    """Run the demo with parsed CLI options; returns the process exit code."""
    from .sim.scene import make_rigid_scene, make_scene

    if args.float32:
        dtype = jnp.float32
    else:
        jax.config.update("jax_enable_x64", True)  # host-side program, not library code
        dtype = jnp.float64
    F = args.frames
    k = DEFAULT_K if args.k is None else args.k
    if args.method == "dct" and 2 * F < 3 * k:
        raise UsageError(f"--k {k} is too large for --frames {F}: need 2*frames >= 3*k")
    key = jax.random.PRNGKey(args.seed)
    k_point, k_rigid = jax.random.split(key)
    t_start = time.perf_counter()

    scene = make_scene(
        k_point,
        camera="random",
        n_frames=F,
        duration=10.0,
        noise_px=args.noise,
        standoff=(0.5, 1.5),
        extent=0.3,
    )
    scene = _cast(scene, dtype)
    points, rms, gain, ok_point, label = _estimate(
        args.method, scene.P, scene.uv[None], scene.times, scene.weights[None], k, args.noise
    )
    points, rms, ok_point = points[0], float(rms[0]), bool(ok_point[0])
    gain = None if gain is None else float(gain[0])
    err = np.linalg.norm(np.asarray(points - scene.points), axis=1) * 1e3
    Phi = DCTBasis.from_times(scene.times, k)(scene.times)
    eta = float(reconstructibility(scene.camera_centres, scene.points, Phi))

    rigid = make_rigid_scene(k_rigid, camera="random", n_frames=F, noise_px=args.noise)
    rigid = _cast(rigid, dtype)
    marker_points, _, _, ok_markers, _ = _estimate(
        args.method,
        rigid.P,
        jnp.swapaxes(rigid.uv, 0, 1),
        rigid.times,
        jnp.swapaxes(rigid.weights, 0, 1),
        k,
        args.noise,
    )
    pts = jnp.swapaxes(marker_points, 0, 1)  # (F, M, 3)
    R_hat, p_hat = fit_rigid(rigid.model_points, pts)
    pos_err = np.linalg.norm(np.asarray(p_hat - rigid.p_w_o), axis=1) * 1e3
    ang_err = rotation_error_deg(np.asarray(R_hat), np.asarray(rigid.R_w_o))
    elapsed = time.perf_counter() - t_start

    ok = ok_point and bool(np.all(np.asarray(ok_markers)))
    summary = {
        "frames": F,
        "method": args.method,
        "estimator": label,
        "noise_px": args.noise,
        "seed": args.seed,
        "dtype": str(jnp.dtype(dtype)),
        "point": {
            "mean_error_mm": float(err.mean()),
            "max_error_mm": float(err.max()),
            "reprojection_rms_px": rms,
            "conditioning_gain": gain,
            "reconstructibility_eta_dct_k": eta,
            "ok": ok_point,
        },
        "pose_6dof": {
            "markers": int(rigid.model_points.shape[0]),
            "mean_position_error_mm": float(pos_err.mean()),
            "max_position_error_mm": float(pos_err.max()),
            "mean_orientation_error_deg": float(ang_err.mean()),
            "max_orientation_error_deg": float(ang_err.max()),
        },
        "seconds": elapsed,
    }

    print(
        f"jaxtraj demo: {F} images at irregular times over {float(scene.times[-1]):.1f} s, "
        f"random discontinuous camera at 0.5-1.5 m, {args.noise} px noise, {label}"
    )
    gain_txt = "" if gain is None else f", conditioning gain {gain:.1f}"
    print(
        f"  assembly point: mean error {err.mean():.2f} mm, max {err.max():.2f} mm "
        f"(reprojection RMS {rms:.2f} px{gain_txt}, eta {eta:.3g}, "
        f"{'OK' if ok_point else 'NOT OK'})"
    )
    print(
        f"  6-DoF pose ({summary['pose_6dof']['markers']} markers): position mean "
        f"{pos_err.mean():.2f} mm, max {pos_err.max():.2f} mm; orientation mean "
        f"{ang_err.mean():.3f} deg, max {ang_err.max():.3f} deg"
    )
    print("  paper (real cell, section 5): mean Euclidean error < 6 mm")

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    if not args.no_plots:
        from .io.plots import plot_errors, plot_trajectory

        plot_trajectory(
            out / "fig3_trajectory.png",
            np.asarray(scene.points),
            np.asarray(points),
            title=f"Measured (red +) vs true trajectory, {args.method}",
        )
        plot_errors(
            out / "fig4_errors.png",
            np.asarray(scene.times),
            np.asarray(scene.points),
            np.asarray(points),
        )
        print(f"  wrote {out / 'fig3_trajectory.png'} and {out / 'fig4_errors.png'}")
    _write_json(out / "summary.json", summary)
    print(f"  wrote {out / 'summary.json'} ({elapsed:.1f} s)")
    if not ok:
        print("  WARNING: a reconstruction was not OK (see status); results are unreliable")
        return EXIT_FAILED
    return EXIT_OK

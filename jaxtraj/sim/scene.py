"""Simulated robot cells: a moving workpiece seen by a moving camera, with detector noise.

:func:`make_scene` builds one point's trajectory, camera poses and noisy pixel track;
:func:`make_rigid_scene` does the same for several markers on a rigid workpiece;
:func:`paper_experiment` is the paper's section-5 set-up (150 images at irregular times,
random discontinuous camera at 0.5-1.5 m, 640x480 camera, 0.3 px noise).

All scene functions take an explicit ``jax.random`` key, are jit-compiled and vmap over
keys, e.g. ``jax.vmap(lambda k: make_scene(k, camera="smooth"))(jax.random.split(key, 9))``.
Structural options (camera kind, frame count, ``irregular``, ``camera_options``) are
static; numbers (noise, rates, extent, stand-off, speed) are traced, so sweeping them
does not recompile.
The world is Z-up, metres and seconds; cameras follow OpenCV conventions.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, PRNGKeyArray

from .._checks import check_shape
from .._linalg import det3
from ..basis import dct_basis
from .camera_paths import (
    CameraPath,
    following_camera,
    orbit_camera,
    random_discontinuous_camera,
    smooth_random_camera,
    static_camera,
)
from .trajectories import rigid_motion, sample_times, smooth_random_curve, transform_points

__all__ = [
    "CAMERA_KINDS",
    "DEFAULT_MARKERS",
    "IMAGE_SIZE",
    "Observation",
    "RigidScene",
    "Scene",
    "default_intrinsics",
    "make_rigid_scene",
    "make_scene",
    "observe",
    "paper_experiment",
]

#: (width, height) of the default camera image [px].
IMAGE_SIZE = (640, 480)
CAMERA_KINDS = ("static", "following", "random", "orbit", "smooth")
#: Five non-coplanar markers in the object frame [m], centred near the origin.
DEFAULT_MARKERS = (
    (0.10, 0.00, 0.00),
    (-0.05, 0.08, 0.00),
    (-0.05, -0.08, 0.00),
    (0.00, 0.00, 0.10),
    (0.03, 0.04, -0.06),
)
_ELEVATION = 0.6  # rad, viewpoint elevation of the static and following cameras


def default_intrinsics(
    focal: float = 700.0, image_size: tuple[int, int] = IMAGE_SIZE, dtype=None
) -> Float[Array, "3 3"]:
    """Camera matrix K with focal length ``focal`` [px] and the principal point at the
    image centre, ``((W - 1) / 2, (H - 1) / 2)`` (pixel centres at integers, as in OpenCV)."""
    w, h = image_size
    return jnp.array(
        [[focal, 0.0, (w - 1) / 2], [0.0, focal, (h - 1) / 2], [0.0, 0.0, 1.0]],
        dtype=dtype if dtype is not None else float,
    )


class Observation(eqx.Module):
    """Detections of points in the images (leading axes as the points given to observe).

    Attributes:
        uv: (F, 2) or (F, M, 2) pixels [px]; NaN where not detected.
        weights: (F,) or (F, M): 1 for a detection, 0 for a missing one.
        outliers: (F,) or (F, M) bool: detections replaced by an outlier.
    """

    uv: Float[Array, "F *M 2"]
    weights: Float[Array, " F *M"]
    outliers: Bool[Array, " F *M"]


def observe(
    key: PRNGKeyArray,
    P: Float[ArrayLike, "F 3 4"],
    points: Float[ArrayLike, "F *M 3"],
    *,
    noise_px: float = 0.3,
    drop_rate: float = 0.0,
    outlier_rate: float = 0.0,
    outlier_px: float = 20.0,
    image_size: tuple[int, int] = IMAGE_SIZE,
) -> Observation:
    """Simulate a point detector: project, add noise, drop and corrupt detections.

    Each pixel is the projection plus isotropic Gaussian noise of ``noise_px`` per axis.
    With probability ``outlier_rate`` it is instead the projection displaced by
    ``outlier_px * U(0.5, 1)`` in a random direction (flagged in ``outliers``). A
    detection is missing (weight 0, pixel NaN) with probability ``drop_rate``, and
    always when the point is not in front of the camera or its pixel falls outside the
    image ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``.

    Args:
        key: a ``jax.random`` key.
        P: (F, 3, 4) projection matrices.
        points: (F, 3) one point, or (F, M, 3) M points, per image [m].
        noise_px: pixel noise standard deviation [px], >= 0.
        drop_rate, outlier_rate: probabilities in [0, 1].
        outlier_px: outlier displacement scale [px].
        image_size: (width, height) [px].
    """
    check_shape("P", P, (None, 3, 4), "one 3x4 projection matrix per image")
    F = jnp.shape(P)[0]
    if jnp.ndim(points) not in (2, 3) or jnp.shape(points)[0] != F or jnp.shape(points)[-1] != 3:
        raise ValueError(
            f"points: expected shape ({F}, 3) or ({F}, M, 3) (one row per image of P), "
            f"got {tuple(jnp.shape(points))}"
        )
    det = _detector(noise_px, drop_rate, outlier_rate, outlier_px)
    return _observe(key, P, points, det, tuple(int(n) for n in image_size))


def _detector(noise_px, drop_rate, outlier_rate, outlier_px) -> dict:
    """Validated detector parameters as arrays (traced under jit: no recompiles)."""
    for name, rate in (("drop_rate", drop_rate), ("outlier_rate", outlier_rate)):
        if isinstance(rate, (int, float)) and not 0.0 <= rate <= 1.0:
            raise ValueError(f"{name}: expected a probability in [0, 1], got {rate}")
    if isinstance(noise_px, (int, float)) and noise_px < 0:
        raise ValueError(f"noise_px: expected a standard deviation >= 0, got {noise_px}")
    return dict(
        noise_px=_num(noise_px),
        drop_rate=_num(drop_rate),
        outlier_rate=_num(outlier_rate),
        outlier_px=_num(outlier_px),
    )


@eqx.filter_jit
def _observe(key, P, points, det, image_size):
    P = jnp.asarray(P)
    dtype = jnp.result_type(P.dtype, jnp.float32)
    P = P.astype(dtype)
    single = jnp.ndim(points) == 2
    X = jnp.asarray(points, dtype)
    X = X[:, None, :] if single else X
    shape = X.shape[:2]

    h = jnp.einsum("fij,fmj->fmi", P[:, :, :3], X) + P[:, None, :, 3]
    depth = h[..., 2] * jnp.sign(det3(P[:, :, :3]))[:, None]
    in_front = depth > 0
    z = jnp.where(in_front, h[..., 2], 1.0)  # double-where: finite gradients behind
    uv_true = h[..., :2] / z[..., None]

    # One uniform draw (cheap to compile): drop, outlier, jump size and direction, and a
    # Box-Muller pair for the Gaussian pixel noise.
    u = jax.random.uniform(key, (6, *shape), dtype)
    radius = jnp.sqrt(-2.0 * jnp.log1p(-u[4]))
    gauss = radius[..., None] * jnp.stack(
        [jnp.cos(2 * jnp.pi * u[5]), jnp.sin(2 * jnp.pi * u[5])], -1
    )
    noise = det["noise_px"] * gauss
    is_outlier = u[1] < det["outlier_rate"]
    mag = det["outlier_px"] * (0.5 + 0.5 * u[2])
    ang = 2 * jnp.pi * u[3]
    jump = mag[..., None] * jnp.stack([jnp.cos(ang), jnp.sin(ang)], axis=-1)
    uv = uv_true + jnp.where(is_outlier[..., None], jump, noise)

    w, hgt = image_size
    inside = (
        (uv[..., 0] >= -0.5)
        & (uv[..., 0] <= w - 0.5)
        & (uv[..., 1] >= -0.5)
        & (uv[..., 1] <= hgt - 0.5)
    )
    kept = in_front & inside & ~(u[0] < det["drop_rate"])
    uv = jnp.where(kept[..., None], uv, jnp.nan)
    obs = Observation(uv=uv, weights=kept.astype(dtype), outliers=is_outlier & kept)
    if single:
        obs = jax.tree.map(lambda a: a[:, 0], obs)
    return obs


def _num(x):
    """Python numbers as weakly typed arrays, so that jit traces them (no recompiles)."""
    return None if x is None else jnp.asarray(x)


def _direction(key, dtype, elevation=_ELEVATION):
    az = jax.random.uniform(key, (), dtype, 0.0, 2 * jnp.pi)
    e = jnp.asarray(elevation, dtype)
    return jnp.stack([jnp.cos(e) * jnp.cos(az), jnp.cos(e) * jnp.sin(az), jnp.sin(e)])


def _camera_path(camera, key, points, times, geo, options) -> CameraPath:
    """Camera poses of the given kind around the (F, 3) ``points``."""
    opts = dict(options or {})
    dtype = points.dtype
    standoff = geo["standoff"].astype(dtype)
    if camera == "static":
        position = jnp.mean(points, axis=0) + standoff[1] * _direction(key, dtype)
        return static_camera(position, jnp.mean(points, axis=0), points.shape[0])
    if camera == "following":
        offset = opts.pop("offset", 0.5 * (standoff[0] + standoff[1]) * _direction(key, dtype))
        return following_camera(points, offset, **opts)
    if camera == "random":
        return random_discontinuous_camera(key, points, standoff=standoff, **opts)
    if camera == "orbit":
        r = 0.5 * (standoff[0] + standoff[1])
        opts.setdefault("radius", r * jnp.cos(_ELEVATION))
        opts.setdefault("height", r * jnp.sin(_ELEVATION))
        opts.setdefault("angular_speed", jnp.pi / (times[-1] - times[0]))  # half a turn
        return orbit_camera(points, times=times, **opts)
    if camera == "smooth":
        return smooth_random_camera(
            key, points, times, speed=geo["camera_speed"], standoff=standoff, **opts
        )
    raise ValueError(f"camera: expected one of {CAMERA_KINDS}, got {camera!r}")


def _scene_times(key, times, n_frames, duration, irregular):
    if times is None:
        return sample_times(key, n_frames, duration, irregular=irregular)
    check_shape("times", times, (None,), "(F,) image times")
    t = jnp.asarray(times)
    return t.astype(jnp.result_type(t.dtype, jnp.float32))


class Scene(eqx.Module):
    """One point on a moving workpiece seen by a moving camera (all arrays per image).

    Attributes:
        times: (F,) image times [s].
        points: (F, 3) true point positions [m].
        K: (3, 3) camera matrix.
        R_c_w, t_c_w: (F, 3, 3), (F, 3) camera poses.
        P: (F, 3, 4) projection matrices.
        camera_centres: (F, 3) [m].
        uv: (F, 2) detected pixels, NaN where missing [px].
        weights: (F,) 1 for a detection, 0 for a missing one.
        outliers: (F,) bool, detections that are outliers.
    """

    times: Float[Array, " F"]
    points: Float[Array, "F 3"]
    K: Float[Array, "3 3"]
    R_c_w: Float[Array, "F 3 3"]
    t_c_w: Float[Array, "F 3"]
    P: Float[Array, "F 3 4"]
    camera_centres: Float[Array, "F 3"]
    uv: Float[Array, "F 2"]
    weights: Float[Array, " F"]
    outliers: Bool[Array, " F"]

    def basis(self, k: int) -> Float[Array, "F k"]:
        """The (F, k) orthonormal DCT basis at the image times."""
        return dct_basis(self.times, k)


def make_scene(
    key: PRNGKeyArray,
    *,
    camera: str = "random",
    n_frames: int = 150,
    duration: float = 10.0,
    noise_px: float = 0.3,
    irregular: bool = True,
    drop_rate: float = 0.0,
    outlier_rate: float = 0.0,
    outlier_px: float = 20.0,
    extent: float = 0.3,
    centre: Float[ArrayLike, " 3"] = (0.0, 0.0, 0.0),
    standoff: tuple[float, float] = (0.5, 1.5),
    camera_speed: float = 0.3,
    K: Float[ArrayLike, "3 3"] | None = None,
    times: Float[ArrayLike, " F"] | None = None,
    points: Float[ArrayLike, "F 3"] | None = None,
    camera_options: dict | None = None,
) -> Scene:
    """A simulated single-point scene.

    The point follows :func:`smooth_random_curve` (or the given ``points``); the camera
    is one of :data:`CAMERA_KINDS`:

    * ``"static"``: fixed at ``standoff[1]`` from the mean point, 0.6 rad elevation;
    * ``"following"``: ``point + offset``, ``|offset|`` the mid stand-off (degenerate);
    * ``"random"``: :func:`random_discontinuous_camera` with ``standoff`` (the paper's);
    * ``"orbit"``: half a turn over the duration at the mid stand-off, 0.6 rad elevation;
    * ``"smooth"``: :func:`smooth_random_camera` at ``camera_speed`` m/s.

    ``camera_options`` are passed to the camera function (e.g. ``cone_angle``,
    ``max_aim`` for "random"; ``radius``, ``angular_speed`` for "orbit").

    Args:
        key: a ``jax.random`` key (split for times, curve, camera and detector).
        n_frames, duration: image count and time span [s] when ``times`` is not given.
        irregular: jittered image times (see :func:`sample_times`).
        noise_px, drop_rate, outlier_rate, outlier_px: detector model, see :func:`observe`.
        extent, centre: size and bounding-box centre of the random curve [m].
        standoff: (low, high) camera distance [m].
        K: (3, 3) camera matrix; default :func:`default_intrinsics`.
        times, points: (F,), (F, 3) a given trajectory (e.g. :func:`bvh_curve`); ``points``
            needs ``times``.
    """
    if camera not in CAMERA_KINDS:
        raise ValueError(f"camera: expected one of {CAMERA_KINDS}, got {camera!r}")
    if points is not None and times is None:
        raise ValueError("times: required when points are given (one time per row of points)")
    if times is not None:
        check_shape("times", times, (None,), "(F,) image times")
    if points is not None:
        F = jnp.shape(times)[0]
        check_shape("points", points, (F, 3), "one point per image time")
    _check_scene_args(n_frames, K, standoff, centre, extent)
    det = _detector(noise_px, drop_rate, outlier_rate, outlier_px)
    geo = dict(duration=_num(duration), extent=_num(extent), centre=jnp.asarray(centre))
    geo.update(standoff=jnp.asarray(standoff), camera_speed=_num(camera_speed))
    static = (camera, n_frames, irregular, camera_options)
    return _make_scene(key, static, geo, det, K, times, points)


def _check_scene_args(n_frames, K, standoff, centre, extent) -> None:
    if not isinstance(n_frames, int) or isinstance(n_frames, bool) or n_frames < 2:
        raise ValueError(f"n_frames: expected an int >= 2, got {n_frames!r}")
    if K is not None:
        check_shape("K", K, (3, 3), "camera matrix")
    check_shape("standoff", standoff, (2,), "(low, high) camera distance [m]")
    if isinstance(standoff, (tuple, list)) and not 0 < standoff[0] <= standoff[1]:
        raise ValueError(f"standoff: expected (low, high) with 0 < low <= high, got {standoff}")
    check_shape("centre", centre, (3,), "a 3D point [m]")
    if isinstance(extent, (int, float)) and not extent > 0:
        raise ValueError(f"extent: expected a positive length in metres, got {extent}")


@eqx.filter_jit
def _make_scene(key, static, geo, det, K, times, points):
    camera, n_frames, irregular, camera_options = static
    k_t, k_p, k_c, k_o = jax.random.split(key, 4)
    times = _scene_times(k_t, times, n_frames, geo["duration"], irregular)
    dtype = times.dtype
    if points is None:
        points = smooth_random_curve(k_p, times, centre=geo["centre"], extent=geo["extent"])
    else:
        points = jnp.asarray(points, dtype)
    K = default_intrinsics(dtype=dtype) if K is None else jnp.asarray(K, dtype)
    path = _camera_path(camera, k_c, points, times, geo, camera_options)
    P = path.projection_matrices(K)
    obs = _observe(k_o, P, points, det, IMAGE_SIZE)
    fields = (path.R_c_w, path.t_c_w, P, path.centres, obs.uv, obs.weights, obs.outliers)
    return Scene(times, points, K, *fields)


def paper_experiment(key: PRNGKeyArray, n_frames: int = 150) -> Scene:
    """The paper's section-5 experiment: an arbitrary smooth curve (0.3 m), ``n_frames``
    images at irregular times over 10 s, a random discontinuous camera at 0.5-1.5 m
    stand-off, a 640x480 camera (f = 700 px) and 0.3 px pixel noise."""
    return make_scene(key, n_frames=n_frames, duration=10.0, noise_px=0.3, standoff=(0.5, 1.5))


class RigidScene(eqx.Module):
    """Several markers on a rigid, moving workpiece seen by a moving camera.

    Attributes as :class:`Scene`, with per-marker ``points`` (F, M, 3), ``uv`` (F, M, 2),
    ``weights`` and ``outliers`` (F, M), plus ``model_points`` (M, 3) in the object frame
    and the true pose ``R_w_o`` (F, 3, 3), ``p_w_o`` (F, 3).
    """

    times: Float[Array, " F"]
    model_points: Float[Array, "M 3"]
    R_w_o: Float[Array, "F 3 3"]
    p_w_o: Float[Array, "F 3"]
    points: Float[Array, "F M 3"]
    K: Float[Array, "3 3"]
    R_c_w: Float[Array, "F 3 3"]
    t_c_w: Float[Array, "F 3"]
    P: Float[Array, "F 3 4"]
    camera_centres: Float[Array, "F 3"]
    uv: Float[Array, "F M 2"]
    weights: Float[Array, "F M"]
    outliers: Bool[Array, "F M"]

    def basis(self, k: int) -> Float[Array, "F k"]:
        """The (F, k) orthonormal DCT basis at the image times."""
        return dct_basis(self.times, k)


def make_rigid_scene(
    key: PRNGKeyArray,
    model_points: Float[ArrayLike, "M 3"] | None = None,
    *,
    camera: str = "random",
    n_frames: int = 150,
    duration: float = 10.0,
    noise_px: float = 0.3,
    irregular: bool = True,
    drop_rate: float = 0.0,
    outlier_rate: float = 0.0,
    outlier_px: float = 20.0,
    extent: float = 0.3,
    centre: Float[ArrayLike, " 3"] = (0.0, 0.0, 0.0),
    max_angle: float = 0.3,
    standoff: tuple[float, float] = (0.7, 1.5),
    camera_speed: float = 0.3,
    K: Float[ArrayLike, "3 3"] | None = None,
    camera_options: dict | None = None,
) -> RigidScene:
    """A simulated rigid workpiece with markers, for 6-DoF pose reconstruction.

    The object pose follows :func:`rigid_motion`; the camera (as in :func:`make_scene`)
    is placed relative to the object origin ``p_w_o`` and looks at it.

    Args:
        key: a ``jax.random`` key.
        model_points: (M, 3) marker positions in the object frame [m]; default
            :data:`DEFAULT_MARKERS` (five non-coplanar markers within 0.11 m of the origin).
        max_angle: largest rotation of the object from the identity [rad].
        Other arguments as :func:`make_scene`.
    """
    if camera not in CAMERA_KINDS:
        raise ValueError(f"camera: expected one of {CAMERA_KINDS}, got {camera!r}")
    if model_points is None:
        model_points = DEFAULT_MARKERS
    check_shape("model_points", model_points, (None, 3), "(M, 3) markers in the object frame")
    _check_scene_args(n_frames, K, standoff, centre, extent)
    det = _detector(noise_px, drop_rate, outlier_rate, outlier_px)
    if isinstance(max_angle, (int, float)) and max_angle < 0:
        raise ValueError(f"max_angle: expected an angle >= 0 in radians, got {max_angle}")
    geo = dict(duration=_num(duration), extent=_num(extent), centre=jnp.asarray(centre))
    geo.update(standoff=jnp.asarray(standoff), camera_speed=_num(camera_speed))
    geo.update(max_angle=_num(max_angle))
    static = (camera, n_frames, irregular, camera_options)
    return _make_rigid_scene(key, jnp.asarray(model_points), static, geo, det, K)


@eqx.filter_jit
def _make_rigid_scene(key, model_points, static, geo, det, K):
    camera, n_frames, irregular, camera_options = static
    k_t, k_p, k_c, k_o = jax.random.split(key, 4)
    times = sample_times(k_t, n_frames, geo["duration"], irregular=irregular)
    dtype = times.dtype
    model = model_points.astype(dtype)
    R_w_o, p_w_o = rigid_motion(
        k_p, times, centre=geo["centre"], extent=geo["extent"], max_angle=geo["max_angle"]
    )
    points = transform_points(R_w_o, p_w_o, model)
    K = default_intrinsics(dtype=dtype) if K is None else jnp.asarray(K, dtype)
    path = _camera_path(camera, k_c, p_w_o, times, geo, camera_options)
    P = path.projection_matrices(K)
    obs = _observe(k_o, P, points, det, IMAGE_SIZE)
    fields = (path.R_c_w, path.t_c_w, P, path.centres, obs.uv, obs.weights, obs.outliers)
    return RigidScene(times, model, R_w_o, p_w_o, points, K, *fields)

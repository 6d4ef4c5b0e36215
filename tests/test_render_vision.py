"""Rendered marker/chessboard/ChArUco images against ground truth: rendering exactness,
marker detection, chessboard corners, intrinsic calibration."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from jaxtraj.io.records import CameraCalibration
from jaxtraj.sim.render import (
    PlanarTexture,
    charuco_texture,
    chessboard_texture,
    marker_board,
    render,
    undistorted_rays,
)
from jaxtraj.vision.calibration import (
    CalibrationTarget,
    calibrate_camera,
    check_image_size,
    find_chessboard,
)
from jaxtraj.vision.markers import detect_markers, diagonal_centres

SIZE = (640, 480)
K = np.array([[700.0, 0.0, 322.5], [0.0, 703.0, 236.0], [0.0, 0.0, 1.0]])
DIST = np.array([-0.1, 0.05, 0.001, -0.0005, 0.0])
IDS = [3, 7, 11, 20, 5, 9]
BOARD_UP = np.diag([1.0, -1.0, -1.0])  # camera above the board, looking down (x_c = x_o)


def _pose(rvec, t):
    """Camera-from-object pose: a tilt ``rvec`` applied to the looking-down camera."""
    return cv2.Rodrigues(np.asarray(rvec, float))[0] @ BOARD_UP, np.asarray(t, float)


def _project(points, R, t, K=K, dist=DIST):
    uv, _ = cv2.projectPoints(np.asarray(points, float), cv2.Rodrigues(R)[0], t, K, dist)
    return uv.reshape(-1, 2)


MARKER_POSES = [
    _pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.5]),
    _pose([0.3, -0.2, 0.1], [0.05, 0.02, 0.6]),
    _pose([-0.5, 0.3, 0.4], [-0.05, 0.03, 0.8]),
    _pose([0.2, 0.6, -0.3], [0.1, -0.05, 1.0]),
    _pose([0.1, 0.1, 2.0], [0.0, 0.0, 0.55]),
]


def test_undistorted_rays_invert_opencv_projection():
    s = 2
    rays = undistorted_rays(K, DIST, SIZE, supersample=s).reshape(-1, 2).astype(np.float64)
    pts = np.concatenate([rays, np.ones((len(rays), 1))], 1)
    uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, DIST)
    u = (np.arange(SIZE[0] * s) + 0.5) / s - 0.5
    v = (np.arange(SIZE[1] * s) + 0.5) / s - 0.5
    want = np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)
    assert np.abs(uv.reshape(-1, 2) - want).max() < 1e-3  # float32 storage: ~2e-5 px
    assert undistorted_rays(K, DIST, SIZE, supersample=s) is undistorted_rays(
        K, DIST, SIZE, supersample=s
    )  # cached


def test_render_samples_texture_at_exact_geometry():
    # A texture whose grey level is its column (or row) index: bilinear sampling of a
    # linear ramp is exact, so each rendered pixel must equal the texture coordinate of
    # the point its centre ray hits, computed here independently.
    ramp = np.tile(np.arange(200, dtype=np.uint8), (150, 1))
    R, t = _pose([0.25, -0.3, 0.2], [0.01, -0.02, 0.45])
    for image, axis in ((ramp, 0), (np.ascontiguousarray(ramp.T[:, :150]), 1)):
        H, W = image.shape
        tex = PlanarTexture(image, (0.2 * W / 200, 0.2 * H / 200), BOARD_UP, [-0.1, 0.075, 0])
        img = render(tex, R, t, K, DIST, SIZE, supersample=1, blur_px=0, noise_std=0)
        uu, vv = np.meshgrid(np.arange(SIZE[0], dtype=float), np.arange(SIZE[1], dtype=float))
        xy = cv2.undistortPointsIter(
            np.stack([uu, vv], -1).reshape(-1, 1, 2), K, DIST, None, None,
            (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12),
        ).reshape(-1, 2)  # fmt: skip
        ray_o = np.concatenate([xy, np.ones((len(xy), 1))], 1) @ R  # object-frame directions
        c_o = -R.T @ t
        lam = -c_o[2] / ray_o[:, 2]
        p_o = c_o + lam[:, None] * ray_o
        ij = np.stack(
            [
                (p_o[:, 0] + 0.1) * W / tex.size[0] - 0.5,
                (0.075 - p_o[:, 1]) * H / tex.size[1] - 0.5,
            ],
            -1,
        )
        inside = np.all((ij > 0.5) & (ij < np.array([W, H]) - 1.5), axis=1)
        assert inside.sum() > 20000
        err = img.reshape(-1).astype(float)[inside] - ij[inside, axis]
        assert np.abs(err).max() <= 0.6  # uint8 rounding + remap's 1/32 texel weights
        assert abs(err.mean()) < 0.02  # no systematic shift (a 0.02-texel bias would show)
        # Outside the plate: the background.
        far = np.all((ij < -3) | (ij > np.array([W, H]) + 3), axis=1)
        assert np.all(img.reshape(-1)[far] == 90)


def test_marker_board_layout():
    tex, centres, corners = marker_board(IDS, grid=(3, 2), marker_size=0.06, spacing=0.03)
    assert tex.size == pytest.approx((0.3, 0.21))
    np.testing.assert_allclose(centres[:, 2], 0.0)
    np.testing.assert_allclose(centres.mean(0), 0.0, atol=1e-12)  # centred on the origin
    # First marker top-left as printed (x_o < 0, y_o > 0); ArUco corner order.
    np.testing.assert_allclose(centres[0], [-0.09, 0.045, 0.0], atol=1e-12)
    np.testing.assert_allclose(corners[:, 1] - corners[:, 0], [[0.06, 0, 0]] * 6, atol=1e-12)
    np.testing.assert_allclose(corners[:, 3] - corners[:, 0], [[0, -0.06, 0]] * 6, atol=1e-12)
    np.testing.assert_allclose(diagonal_centres(corners[:, :, :2]), centres[:, :2], atol=1e-12)
    with pytest.raises(ValueError, match="ids"):
        marker_board([1, 1])
    with pytest.raises(ValueError, match="dictionary"):
        marker_board([1], dictionary="DICT_NOPE")


def test_detect_markers_matches_projection_with_distortion():
    tex, centres, corners = marker_board(IDS, grid=(3, 2))
    order = np.argsort(IDS)
    err_c, err_k = [], []
    for k, (R, t) in enumerate(MARKER_POSES):
        img = render(tex, R, t, K, DIST, SIZE, rng=k)
        det = detect_markers(img)
        assert det.ids.tolist() == sorted(IDS)
        assert det.duplicates.size == 0
        err_c.append(np.linalg.norm(det.centres - _project(centres, R, t)[order], axis=1))
        true_k = _project(corners.reshape(-1, 3), R, t).reshape(-1, 4, 2)[order]
        err_k.append(np.linalg.norm(det.corners - true_k, axis=2).ravel())
    err_c, err_k = np.concatenate(err_c), np.concatenate(err_k)
    # Measured: centres RMS 0.05 px, max 0.10 px; corners RMS 0.19 px, max 0.28 px.
    assert np.sqrt(np.mean(err_c**2)) < 0.1
    assert err_c.max() < 0.2
    assert np.sqrt(np.mean(err_k**2)) < 0.35
    # BGR input gives the same detections.
    bgr = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    np.testing.assert_allclose(detect_markers(bgr).centres, det.centres)


def test_back_side_and_blank_images_give_no_detections():
    tex, _, _ = marker_board(IDS, grid=(3, 2))
    R, t = _pose([np.pi, 0.0, 0.0], [0.0, 0.0, 0.5])  # camera below the plate, looking up
    img = render(tex, R, t, K, DIST, SIZE, noise_std=0, rng=0)
    assert np.all(img == 90)  # the plain back of the plate
    assert len(detect_markers(img)) == 0
    blank = np.zeros((480, 640), np.uint8)
    det = detect_markers(blank)
    assert det.ids.shape == (0,) and det.corners.shape == (0, 4, 2) and det.centres.shape == (0, 2)


def test_duplicate_ids_are_reported_and_dropped():
    tex_a, _, _ = marker_board([5, 8], grid=(2, 1))
    tex_b, _, _ = marker_board([5, 12], grid=(2, 1))
    tex_b = PlanarTexture(tex_b.image, tex_b.size, tex_b.R_o_p, tex_b.t_o_p - [0.0, 0.14, 0.0])
    tex_a = PlanarTexture(tex_a.image, tex_a.size, tex_a.R_o_p, tex_a.t_o_p - [0.0, -0.02, 0.0])
    R, t = _pose([0.0, 0.0, 0.0], [0.0, -0.05, 0.55])
    det = detect_markers(render([tex_a, tex_b], R, t, K, DIST, SIZE, rng=1))
    assert det.ids.tolist() == [8, 12]
    assert det.duplicates.tolist() == [5]


def test_nearer_plane_hides_farther_one():
    tex, _, _ = marker_board(IDS, grid=(3, 2))
    white = np.full((10, 10), 235, np.uint8)
    # A white card 5 cm above the board, covering its left third.
    card = PlanarTexture(white, (0.1, 0.3), BOARD_UP, [-0.16, 0.15, 0.05])
    R, t = _pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.5])
    for planes in ([tex, card], [card, tex]):  # order of the list does not matter
        det = detect_markers(render(planes, R, t, K, DIST, SIZE, rng=2))
        assert det.ids.tolist() == [5, 7, 9, 11]  # 3 and 20 (left column) are hidden


def test_detect_markers_rejects_bad_input():
    with pytest.raises(ValueError, match="uint8"):
        detect_markers(np.zeros((10, 10), np.float32))
    with pytest.raises(ValueError, match="image"):
        detect_markers(np.zeros((10, 10, 2), np.uint8))
    with pytest.raises(ValueError, match="DICT_4X4_50"):
        detect_markers(np.zeros((10, 10), np.uint8), dictionary="4x4")
    with pytest.raises(ValueError, match="refine"):
        detect_markers(np.zeros((10, 10), np.uint8), refine="magic")


def _board_views(
    points, n, seed, dist_range=(0.38, 0.55), margin=15.0, inside=1.0, shift=0.08, tilt=(0.1, 0.6)
):
    """n seeded random poses that keep a fraction ``inside`` of ``points`` in the image."""
    rng = np.random.default_rng(seed)
    poses = []
    while len(poses) < n:
        axis = rng.normal(size=2)
        rvec = rng.uniform(*tilt) * np.append(axis / np.linalg.norm(axis), 0.0)
        R = cv2.Rodrigues(np.array([0, 0, rng.uniform(-0.5, 0.5)]) + rvec)[0] @ BOARD_UP
        t = np.array([*rng.uniform(-shift, shift, 2), rng.uniform(*dist_range)])
        uv = _project(points, R, t)
        if np.mean(np.all((uv > margin) & (uv < np.array(SIZE) - margin), axis=1)) >= inside:
            poses.append((R, t))
    return poses


def test_chessboard_corners_in_documented_order():
    cols, rows, square = 7, 6, 0.025
    tex, corners = chessboard_texture(cols, rows, square)
    target = CalibrationTarget("chessboard", cols, rows, square)
    np.testing.assert_allclose(corners, target.object_points(), atol=1e-12)
    np.testing.assert_allclose(corners[0], [-0.075, 0.0625, 0.0])  # top-left inner corner
    poses = _board_views(corners, 4, seed=3)
    poses.append(_pose([0.1, 0.0, np.pi - 0.2], [0.0, 0.0, 0.45]))  # board upside down
    err = []
    for k, (R, t) in enumerate(poses):
        uv = find_chessboard(render(tex, R, t, K, DIST, SIZE, rng=k), (cols, rows))
        assert uv is not None
        err.append(np.linalg.norm(uv - _project(corners, R, t), axis=1))
    err = np.concatenate(err)
    assert np.sqrt(np.mean(err**2)) < 0.1  # measured ~0.04 px
    assert err.max() < 0.2
    assert find_chessboard(np.full((480, 640), 128, np.uint8), (cols, rows)) is None


def _check_calibration(result, n_views, poses, points, max_px=0.1):
    cal = result.calibration
    assert cal.image_size == SIZE
    assert len(result.used) == n_views
    np.testing.assert_allclose(cal.K[[0, 1], [0, 1]], K[[0, 1], [0, 1]], rtol=5e-3)
    np.testing.assert_allclose(cal.K[[0, 1], [2, 2]], K[[0, 1], [2, 2]], atol=1.0)
    assert cal.rms_px < 0.1
    assert result.per_view_rms.shape == (n_views,) and result.per_view_rms.max() < 0.15
    # The true target points, reprojected with the estimated camera and poses.
    err = []
    for (R, t), R_est, t_est in zip(poses, result.R_c_t, result.t_c_t, strict=True):
        true = _project(points, R, t)
        seen = np.all((true > 0) & (true < np.array(SIZE)), axis=1)
        est = _project(points[seen], R_est, t_est, cal.K, cal.dist)
        err.append(np.linalg.norm(est - true[seen], axis=1))
    err = np.concatenate(err)
    assert np.sqrt(np.mean(err**2)) < 0.05 and err.max() < max_px
    # Rays of the true camera through a pixel grid over the whole image, reprojected by
    # the estimated camera (up to the small rotation of the camera frame the poses absorb).
    uu, vv = np.meshgrid(np.linspace(0, SIZE[0] - 1, 33), np.linspace(0, SIZE[1] - 1, 25))
    uv = np.stack([uu, vv], -1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    rays = [
        np.c_[cv2.undistortPointsIter(uv, k, d, None, None, crit).reshape(-1, 2), np.ones(len(uv))]
        for k, d in ((K, DIST), (cal.K, cal.dist))
    ]
    U, _, Vt = np.linalg.svd(rays[1].T @ rays[0])
    R_align = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    back = _project(rays[0], R_align, np.zeros(3), cal.K, cal.dist)
    grid_err = np.linalg.norm(back - uv.reshape(-1, 2), axis=1)
    return grid_err


def test_calibrate_camera_chessboard():
    cols, rows, square = 7, 6, 0.025
    tex, corners = chessboard_texture(cols, rows, square)
    poses = _board_views(corners, 12, seed=11)
    images = [render(tex, R, t, K, DIST, SIZE, rng=100 + k) for k, (R, t) in enumerate(poses)]
    images.insert(4, np.full((480, 640), 90, np.uint8))  # a view without the target
    names = [f"img{k:02d}.png" for k in range(len(images))]
    target = CalibrationTarget.from_dict(
        {"kind": "chessboard", "cols": 7, "rows": 6, "square": 0.025}
    )
    result = calibrate_camera(images, target, image_names=names)
    assert result.skipped == [("img04.png", "chessboard not found")]
    assert result.used == [k for k in range(13) if k != 4]
    grid_err = _check_calibration(result, 12, poses, corners)
    # Measured: corners RMS 0.010 px, max 0.05 px; grid RMS 0.06 px, max 0.24 px (corners).
    assert np.sqrt(np.mean(grid_err**2)) < 0.1 and grid_err.max() < 0.4
    # Per-view target poses: the rendered ones.
    for (R, t), R_est, t_est in zip(poses, result.R_c_t, result.t_c_t, strict=True):
        assert np.linalg.norm(t_est - t) < 2e-3
        assert np.degrees(np.linalg.norm(cv2.Rodrigues(R_est @ R.T)[0])) < 0.2


def test_calibrate_camera_charuco():
    board = charuco_texture(8, 6, 0.03, 0.022, px_per_square=60)
    target = CalibrationTarget("charuco", 8, 6, 0.03, marker=0.022, dictionary="DICT_4X4_50")
    np.testing.assert_allclose(board.corners, target.object_points(), atol=1e-12)
    # Partial views (80 % of the corners in the image), as ChArUco allows.
    poses = _board_views(
        board.corners, 12, seed=5, dist_range=(0.4, 0.6), inside=0.8, shift=0.12, tilt=(0.3, 0.7)
    )
    images = [render(board.texture, R, t, K, DIST, SIZE, rng=k) for k, (R, t) in enumerate(poses)]
    images.append(np.zeros((480, 640, 3), np.uint8))
    result = calibrate_camera(images, target)
    assert result.skipped == [(12, "0 ChArUco corners found, need 6")]
    # Measured: corners RMS 0.026 px, max 0.12 px (a corner at the image edge).
    grid_err = _check_calibration(result, 12, poses, board.corners, max_px=0.15)
    # Over the whole image (extrapolating beyond the partial views, k3 poorly fixed):
    # measured RMS 0.19 px, max 1.6 px in the image corners.
    assert np.sqrt(np.mean(grid_err**2)) < 0.3


def test_calibrate_camera_errors():
    cols, rows, square = 7, 6, 0.025
    tex, corners = chessboard_texture(cols, rows, square)
    target = CalibrationTarget("chessboard", cols, rows, square)
    images = [
        render(tex, R, t, K, DIST, SIZE, rng=k)
        for k, (R, t) in enumerate(_board_views(corners, 2, seed=2))
    ]
    images.append(np.zeros((480, 640), np.uint8))
    with pytest.raises(ValueError, match=r"found in 2 image.*blank\.png \(chessboard not found\)"):
        calibrate_camera(images, target, image_names=["a.png", "b.png", "blank.png"])
    images.append(np.zeros((240, 320), np.uint8))
    with pytest.raises(ValueError, match=r"images\[3\] \(3\).*\(320, 240\)"):
        calibrate_camera(images, target)


def test_calibration_target_dict_round_trip_and_validation():
    t = CalibrationTarget("charuco", 6, 5, 0.04, marker=0.03)
    assert t.dictionary == "DICT_4X4_50"
    assert CalibrationTarget.from_dict(t.to_dict()) == t
    c = CalibrationTarget("chessboard", 7, 6, 0.025)
    assert c.to_dict() == {"kind": "chessboard", "cols": 7, "rows": 6, "square": 0.025}
    with pytest.raises(ValueError, match="colour"):
        CalibrationTarget.from_dict({**c.to_dict(), "colour": "red"})
    with pytest.raises(ValueError, match="square"):
        CalibrationTarget.from_dict({"kind": "chessboard", "cols": 7, "rows": 6})
    with pytest.raises(ValueError, match="kind"):
        CalibrationTarget("circles", 7, 6, 0.025)
    with pytest.raises(ValueError, match="cols"):
        CalibrationTarget("chessboard", 1, 6, 0.025)
    with pytest.raises(ValueError, match="marker"):
        CalibrationTarget("charuco", 6, 5, 0.04, marker=0.05)
    with pytest.raises(ValueError, match="dictionary"):
        CalibrationTarget("charuco", 6, 5, 0.04, marker=0.03, dictionary="DICT_X")


def test_check_image_size():
    cal = CameraCalibration(K=K, dist=DIST, image_size=SIZE)
    check_image_size(cal, (640, 480))
    with pytest.raises(ValueError, match=r"cam0/0001\.png.*\(1280, 720\).*\(640, 480\)"):
        check_image_size(cal, (1280, 720), source="cam0/0001.png")

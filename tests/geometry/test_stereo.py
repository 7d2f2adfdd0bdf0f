import cv2
import numpy as np
import pytest

from lunarnav_ml.errors import InputError
from lunarnav_ml.geometry.stereo import (
    SGBMStereo,
    compute_disparity,
    disparity_to_depth,
    disparity_to_points,
    match_strips,
)


def _texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 1.2)


def _warp(img: np.ndarray, disparity: np.ndarray) -> np.ndarray:
    """Right image of a left image whose pixel u appears at u - d in the right one."""
    h, w = img.shape
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    # right(u) = left(u + d(u)) to first order for slowly varying d
    out = cv2.remap(img, uu + disparity.astype(np.float32), vv, cv2.INTER_CUBIC)
    return np.clip(out, 0, 255).astype(np.uint8)


def test_disparity_to_depth_on_a_synthetic_plane():
    f, b, cx, cy = 512.0, 0.3, 320.0, 240.0
    n, c = np.array([0.0, np.cos(0.2), np.sin(0.2)]), 1.5  # a ground plane n . X = c
    v, u = np.mgrid[0:480, 0:640].astype(np.float64)
    q = np.stack([(u - cx) / f, (v - cy) / f, np.ones_like(u)], -1)
    disp = f * b * (q @ n) / c
    disp[disp <= 0] = np.nan  # above the horizon
    pts = disparity_to_points(disp, f, b, cx, cy)
    ok = np.isfinite(disp)
    assert ok.sum() > 1000
    np.testing.assert_allclose(pts[ok] @ n, c, rtol=1e-5)
    depth = disparity_to_depth(disp, f, b)
    np.testing.assert_allclose(depth[ok], pts[ok][:, 2], rtol=1e-6)
    assert np.isnan(depth[~ok]).all() and np.isnan(pts[~ok]).all()


def test_sgbm_recovers_a_slanted_plane_without_bias():
    left = _texture(300, 480)
    v = np.arange(300, dtype=np.float32)[:, None]
    truth = np.broadcast_to(3.0 + 0.12 * v, left.shape)
    right = _warp(left, truth)
    res = compute_disparity(left.astype(np.uint8), right, num_disparities=64)
    err = (res.disparity - truth)[:, 80:-20]
    assert np.isfinite(err).mean() > 0.9
    assert abs(np.nanmedian(err)) < 0.05  # 8-path SGBM: no bias on slanted surfaces
    assert np.nanpercentile(np.abs(err), 90) < 0.35
    assert res.disparity.dtype == np.float32 and res.valid.shape == left.shape
    np.testing.assert_array_equal(np.isfinite(res.disparity), res.valid)


def test_strip_matcher_reads_each_side_of_a_horizontal_depth_edge():
    """One-row windows right below a depth edge read the near side's disparity; SGBM's square
    windows and smoothness terms mix the far side in there."""
    left = _texture(120, 400, seed=3)
    truth = np.where(np.arange(120)[:, None] < 60, 8.0, 14.3) * np.ones((1, 400))
    right = _warp(left, truth)
    cols = np.repeat(np.arange(60, 340, 20), 4)
    rows = np.tile([60, 61, 62, 63], len(cols) // 4)  # the first rows of the near side
    prior = np.full(len(cols), 12.0)  # 2.3 px off: the search finds the peak
    got = match_strips(left.astype(np.uint8), right, cols, rows, prior, half_width=7)
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, 14.3, atol=0.15)
    far = match_strips(left.astype(np.uint8), right, cols, rows - 5, np.full(len(cols), 9.0))
    np.testing.assert_allclose(far, 8.0, atol=0.2)
    # a prior too far off puts the peak at the end of the search: NaN, not a wrong disparity
    assert np.isnan(match_strips(left.astype(np.uint8), right, cols[:3], rows[:3],
                                 np.full(3, 4.0), search_px=3)).all()
    # windows outside the image, NaN priors and flat windows give NaN
    flat = np.full((40, 100), 90, np.uint8)
    assert np.isnan(match_strips(flat, flat, np.array([50]), np.array([20]), np.array([5.0])))[0]
    assert np.isnan(match_strips(left, right, np.array([3, 50]), np.array([10, 10]),
                                 np.array([8.0, np.nan]))).all()
    with pytest.raises(InputError, match="two gray images of one shape"):
        match_strips(left, right[:-1], cols, rows, prior)
    with pytest.raises(InputError, match="cols, rows, d0: expected one length"):
        match_strips(left, right, cols, rows[:-1], prior)


def test_penalties_reach_the_matcher():
    """A smaller P1 lets the disparity follow a slanted plane in smaller steps: a different map,
    still unbiased."""
    left = _texture(200, 320, seed=2)
    v = np.arange(200, dtype=np.float32)[:, None]
    truth = np.broadcast_to(3.0 + 0.12 * v, left.shape)
    right = _warp(left, truth)
    default = SGBMStereo(num_disparities=48)(left.astype(np.uint8), right).disparity
    soft = SGBMStereo(num_disparities=48, penalties=(2.0, 32.0))(left.astype(np.uint8), right)
    assert not np.array_equal(np.nan_to_num(default), np.nan_to_num(soft.disparity))
    assert abs(np.nanmedian((soft.disparity - truth)[:, 60:-20])) < 0.05
    rows = SGBMStereo(num_disparities=48, penalties=(2.0, 32.0))(left.astype(np.uint8), right,
                                                                 rows=(80, 120))
    np.testing.assert_array_equal(rows.disparity[90:110], soft.disparity[90:110])


def test_left_right_check_flags_occlusions():
    left = _texture(200, 320, seed=1)
    truth = np.full(left.shape, 8.0, np.float32)
    truth[60:140, 140:200] = 24.0  # a near box: occludes a strip to its left in the right view
    right = np.clip(_texture(200, 320, seed=2), 0, 255).astype(np.uint8)
    base = _warp(left, np.full(left.shape, 8.0, np.float32))
    box = _warp(left, truth)
    right[:] = base
    # paint the near box at its shifted place (u - 24) in the right image
    right[60:140, 116:176] = np.clip(left[60:140, 140:200], 0, 255).astype(np.uint8)
    del box
    res = compute_disparity(np.clip(left, 0, 255).astype(np.uint8), right, num_disparities=48)
    occluded = (slice(70, 130), slice(126, 138))  # left pixels hidden behind the box in the right view
    assert res.valid[occluded].mean() < 0.3
    assert res.valid[70:130, 150:190].mean() > 0.8
    np.testing.assert_allclose(np.nanmedian(res.disparity[70:130, 150:190]), 24.0, atol=0.1)
    no_check = compute_disparity(np.clip(left, 0, 255).astype(np.uint8), right, num_disparities=48,
                                 lr_max_diff_px=0)
    assert no_check.valid.sum() > res.valid.sum()


def test_rendered_scene_disparity_matches_truth(crater_scene):
    sc = crater_scene
    res = SGBMStereo(num_disparities=96)(sc.left, sc.right)
    truth = sc.rig.focal_px * sc.rig.baseline_m / sc.depth
    ground = (slice(300, 400), slice(40, 600))  # terrain in front of the crater
    err = res.disparity[ground] - truth[ground]
    assert np.isfinite(err).mean() > 0.8
    assert abs(np.nanmedian(err)) < 0.1
    assert np.isnan(res.disparity[:100]).mean() > 0.9  # black sky has no valid disparity


def test_stereo_bad_inputs():
    img = np.zeros((50, 60), np.uint8)
    with pytest.raises(InputError, match="right"):
        compute_disparity(img, np.zeros((50, 61), np.uint8))
    with pytest.raises(InputError, match="block_size"):
        compute_disparity(img, img, block_size=4)
    with pytest.raises(InputError, match="mode"):
        compute_disparity(img, img, mode="fast")
    with pytest.raises(InputError, match="penalties"):
        compute_disparity(img, img, penalties=(32.0, 8.0))
    with pytest.raises(InputError, match="penalties"):
        compute_disparity(img, img, penalties=(8.0,))
    with pytest.raises(InputError, match="left"):
        compute_disparity(np.full((50, 60), np.nan), img)
    with pytest.raises(InputError, match="left"):
        compute_disparity(np.zeros((2, 50, 60)), img)
    with pytest.raises(InputError, match="disparity"):
        disparity_to_points(np.zeros(5), 500.0, 0.3, 1, 1)
    with pytest.raises(InputError, match="focal_px"):
        disparity_to_depth(np.ones((2, 2)), 0.0, 0.3)


def test_textureless_images_give_all_invalid_disparity():
    img = np.full((60, 80), 128, np.uint8)
    res = compute_disparity(img, img, num_disparities=16)
    assert res.disparity.shape == img.shape
    assert not res.valid.any() and np.isnan(res.disparity).all()


def test_sgbm_sized_to_the_frame():
    from lunarnav_ml.geometry.stereo import SGBMStereo

    assert SGBMStereo.for_width(1024).num_disparities == 128
    assert SGBMStereo.for_width(640).num_disparities == 80
    assert SGBMStereo.for_width(100).num_disparities == 32
    assert all(SGBMStereo.for_width(w).num_disparities % 16 == 0 for w in (100, 333, 777, 2048))

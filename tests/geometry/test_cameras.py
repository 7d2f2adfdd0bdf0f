import numpy as np
import pytest

from lunarnav_ml.errors import InputError
from lunarnav_ml.geometry.cameras import (
    CAHVModel,
    PinholeCamera,
    cahv_backproject,
    cahv_project,
    cahv_to_pinhole,
    change_pcam_pair,
    parse_cahv,
    pinhole_backproject,
    pinhole_from_fov,
    pinhole_project,
    pinhole_to_cahv,
    rectify_cahv_pair,
    rectify_images,
)


@pytest.fixture(scope="module")
def points() -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.uniform([-4, -2, 4], [4, 2, 40], (200, 3))


@pytest.fixture(scope="module")
def pcam_rect():
    return rectify_cahv_pair(*change_pcam_pair(3))


def test_parse_cahv_reads_the_paper_table():
    left, right = change_pcam_pair(4)
    assert (left.width, left.height) == (2352, 1728)
    np.testing.assert_allclose(right.c, [0.269990, -0.001864, -0.001342])
    np.testing.assert_allclose(right.h, [6729.968393, 5.565861, 1401.340421])
    assert np.linalg.norm(right.c - left.c) == pytest.approx(0.27, abs=1e-3)


@pytest.mark.parametrize("mission", [3, 4])
@pytest.mark.parametrize("side", [0, 1])
def test_cahv_round_trip_within_1e_6_px(points, mission, side):
    model = change_pcam_pair(mission)[side]
    rng = np.random.default_rng(1)
    uv = rng.uniform([0, 0], [model.width, model.height], (500, 2))
    rays = cahv_backproject(model, uv)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    assert np.all(rays @ model.a > 0)
    again = cahv_project(model, model.c + 13.7 * rays)
    assert np.abs(again - uv).max() < 1e-6
    uv_pts = cahv_project(model, points)
    back = cahv_backproject(model, uv_pts)
    expected = (points - model.c) / np.linalg.norm(points - model.c, axis=1, keepdims=True)
    np.testing.assert_allclose(back, expected, atol=1e-12)


def test_cahv_known_answer_left_pcam():
    left, _ = change_pcam_pair(3)
    # left model is an ideal camera at the origin: u = 6773.068749 x / z + 1175.5
    uv = cahv_project(left, [[1.0, -0.5, 10.0]])
    np.testing.assert_allclose(uv, [[677.3068749 + 1175.5, -339.5797455 + 863.5]], atol=1e-6)


@pytest.mark.parametrize("side", [0, 1])
def test_cahv_to_pinhole_is_exact_and_invertible(points, side):
    model = change_pcam_pair(3)[side]
    cam = cahv_to_pinhole(model)
    np.testing.assert_allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(cam.R) == pytest.approx(1.0)
    assert cam.K[2, 2] == 1.0 and cam.K[1, 0] == 0.0 and np.all(np.diag(cam.K) > 0)
    np.testing.assert_allclose(cam.center, model.c, atol=1e-12)
    np.testing.assert_allclose(pinhole_project(cam, points), cahv_project(model, points), atol=1e-8)
    back = pinhole_to_cahv(cam)
    np.testing.assert_allclose(back.project(points), model.project(points), atol=1e-8)
    uv = model.project(points)
    np.testing.assert_allclose(pinhole_backproject(cam, uv), cahv_backproject(model, uv), atol=1e-10)


def test_left_pcam_intrinsics():
    cam = cahv_to_pinhole(change_pcam_pair(3)[0])
    np.testing.assert_allclose(cam.K, [[6773.068749, 0, 1175.5], [0, 6791.59491, 863.5], [0, 0, 1]])
    np.testing.assert_allclose(cam.R, np.eye(3), atol=1e-12)


def test_pinhole_from_fov_paper_camera():
    cam = pinhole_from_fov(1024, 1024, 90.0)
    assert cam.K[0, 0] == pytest.approx(512.0)
    np.testing.assert_allclose(cam.project([[0.0, 0.0, 5.0]]), [[511.5, 511.5]])
    assert np.isnan(cam.project([[0.0, 0.0, -1.0]])).all()


def test_rectified_pair_has_row_epipolars_and_known_disparity(points, pcam_rect):
    rect = pcam_rect
    assert rect.baseline_m == pytest.approx(0.27, abs=1e-3)
    ul, ur = rect.left.project(points), rect.right.project(points)
    np.testing.assert_allclose(ul[:, 1], ur[:, 1], atol=1e-8)
    z = (points - rect.left.c) @ rect.rotation[2]
    np.testing.assert_allclose(ul[:, 0] - ur[:, 0], rect.focal_px * rect.baseline_m / z, atol=1e-8)


def test_rectification_maps_point_back_to_original_pixels(points, pcam_rect):
    left, right = change_pcam_pair(3)
    rect = pcam_rect
    for orig, model, maps in ((left, rect.left, rect.maps_left), (right, rect.right, rect.maps_right)):
        uv_rect = model.project(points)
        inside = (uv_rect[:, 0] >= 0) & (uv_rect[:, 0] < orig.width - 1) & (uv_rect[:, 1] >= 0) & (
            uv_rect[:, 1] < orig.height - 1)
        iu, iv = np.rint(uv_rect[inside]).astype(int).T
        expected = orig.project(model.c + model.backproject(np.column_stack([iu, iv])))
        got = np.column_stack([maps[0][iv, iu], maps[1][iv, iu]])
        assert inside.sum() > 20
        np.testing.assert_allclose(got, expected, atol=2e-3)  # float32 maps


def test_rectify_images_shapes_and_size_check(pcam_rect):
    img = np.zeros((1728, 2352), np.uint8)
    a, b = rectify_images(pcam_rect, img, img)
    assert a.shape == b.shape == img.shape
    with pytest.raises(InputError, match="left"):
        rectify_images(pcam_rect, np.zeros((10, 10), np.uint8), img)


def test_bad_inputs_raise_input_error():
    left, _right = change_pcam_pair(3)
    with pytest.raises(InputError, match="points"):
        cahv_project(left, np.zeros((4, 2)))
    with pytest.raises(InputError, match="uv"):
        cahv_backproject(left, [[np.nan, 1.0]])
    with pytest.raises(InputError, match="unit"):
        CAHVModel(np.zeros(3), [0, 0, 2.0], left.h, left.v, 10, 10)
    with pytest.raises(InputError, match="missing"):
        parse_cahv("C = 0 0 0\nA = 0 0 1", 10, 10)
    with pytest.raises(InputError, match="3 numbers"):
        parse_cahv("C = 0 0\nA = 0 0 1\nH = 1 0 0\nV = 0 1 0", 10, 10)
    with pytest.raises(InputError, match="coincide"):
        rectify_cahv_pair(left, left)
    with pytest.raises(InputError, match="mission"):
        change_pcam_pair(5)


def test_pinhole_camera_methods_match_functions(points):
    cam = PinholeCamera(np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), np.eye(3),
                        np.array([0.1, 0.0, 0.0]), 640, 480)
    np.testing.assert_allclose(cam.project(points), pinhole_project(cam, points))
    uv = cam.project(points)
    rays = cam.backproject(uv)
    np.testing.assert_allclose(cam.project(cam.center + 5 * rays), uv, atol=1e-9)

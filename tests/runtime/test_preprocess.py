"""Letterbox, input checks and normalization of the runtime."""

import numpy as np
import pytest

from lunarnav_ml.errors import InputError
from lunarnav_ml.runtime.preprocess import check_images, letterbox, prepare_batch, to_input


def test_letterbox_known_answer():
    image = np.zeros((100, 200, 3), np.uint8)
    image[:, :100] = 255  # left half white
    canvas, lb = letterbox(image, (64, 64))
    assert canvas.shape == (64, 64, 3) and lb.scale == pytest.approx(0.32)
    assert (lb.pad_x, lb.pad_y) == (0, 16)
    assert (canvas[:16] == 114).all() and (canvas[48:] == 114).all()
    assert (canvas[20:44, 2:30] == 255).all() and (canvas[20:44, 34:62] == 0).all()


def test_boxes_round_trip_to_image_pixels():
    _, lb = letterbox(np.zeros((300, 150, 3), np.uint8), (128, 128))
    boxes = np.array([[10.0, 20.0, 110.0, 290.0], [-5.0, 0.0, 160.0, 400.0]])
    net = boxes * lb.scale + [lb.pad_x, lb.pad_y, lb.pad_x, lb.pad_y]
    back = lb.boxes_to_image(net)
    np.testing.assert_allclose(back[0], boxes[0], atol=1e-4)
    np.testing.assert_allclose(back[1], [0, 0, 150, 300], atol=1e-4)  # clipped to the image


@pytest.mark.parametrize("shape", [(100, 200), (256, 256), (512, 300), (50, 60)])
def test_same_canvas_as_the_training_letterbox(shape):
    from lunarnav_ml.data.letterbox import letterbox as train_letterbox

    image = np.random.default_rng(0).integers(0, 255, (*shape, 3), dtype=np.uint8)
    ours, lb = letterbox(image, (128, 128))
    theirs, info = train_letterbox(image, 128)
    np.testing.assert_array_equal(ours, theirs)
    assert (lb.scale, lb.pad_x, lb.pad_y) == (info.scale, info.pad_x, info.pad_y)


def test_to_input_layout_and_normalization():
    canvas = np.zeros((4, 6, 3), np.uint8)
    canvas[..., 0], canvas[..., 2] = 255, 51
    x = to_input([canvas, canvas])
    assert x.shape == (2, 3, 4, 6) and x.dtype == np.float32 and x.flags.c_contiguous
    np.testing.assert_allclose(x[0, :, 0, 0], [1.0, 0.0, 0.2], atol=1e-6)
    y = to_input([canvas], mean=(0.5, 0.5, 0.5), std=(0.5, 0.5, 0.5))
    np.testing.assert_allclose(y[0, :, 0, 0], [1.0, -1.0, -0.6], atol=1e-6)


@pytest.mark.parametrize(("image", "match"), [
    (np.zeros((8, 8, 3), np.float32), "dtype uint8"),
    (np.zeros((8, 8), np.uint8), r"shape \(H, W, 3\)"),
    (np.zeros((8, 8, 4), np.uint8), "3 channels"),
    (np.zeros((0, 8, 3), np.uint8), "empty"),
    ([[1, 2, 3]], "numpy array"),
])
def test_bad_images_raise_input_error_with_index(image, match):
    good = np.zeros((8, 8, 3), np.uint8)
    with pytest.raises(InputError, match=match) as err:
        check_images([good, image])
    assert "images[1]" in str(err.value)


def test_a_bare_array_is_not_a_list_of_images():
    with pytest.raises(InputError, match="list"):
        prepare_batch(np.zeros((8, 8, 3), np.uint8), (32, 32))

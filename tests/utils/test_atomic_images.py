"""Atomic writers check their destination before any work; the disparity reader rejects a map
with no finite value."""

import numpy as np
import pytest

from lunarnav_ml.errors import InputError
from lunarnav_ml.utils import atomic
from lunarnav_ml.utils.images import read_disparity


def test_atomic_dir_onto_an_existing_file_fails_before_the_work(tmp_path):
    (tmp_path / "afile").write_text("x")
    with (pytest.raises(InputError, match="afile: output folder is an existing file"),
          atomic.atomic_dir(tmp_path / "afile")):
        raise AssertionError("the work ran")
    with (pytest.raises(InputError, match="which is a file"),
          atomic.atomic_dir(tmp_path / "afile" / "sub")):
        raise AssertionError("the work ran")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_atomic_path_onto_an_existing_folder_names_the_destination(tmp_path):
    (tmp_path / "adir").mkdir()
    with pytest.raises(InputError, match="adir: output file is an existing folder") as err:
        atomic.write_text(tmp_path / "adir", "x")
    assert "\n" not in str(err.value) and ".adir." not in str(err.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir"]


def test_an_existing_folder_is_replaced_and_a_file_overwritten(tmp_path):
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "old").write_text("x")
    with atomic.atomic_dir(tmp_path / "d") as work:
        (work / "new").write_text("y")
    assert [p.name for p in (tmp_path / "d").iterdir()] == ["new"]
    atomic.write_text(tmp_path / "f.txt", "a")
    assert atomic.write_text(tmp_path / "f.txt", "b").read_text() == "b"


@pytest.mark.parametrize("name, message", [
    ("g.txt", "suffix '.txt'"),
    ("noext", r"suffix '\(none\)'"),
])
def test_write_image_with_a_suffix_opencv_cannot_write_is_an_input_error(tmp_path, name, message):
    with pytest.raises(InputError, match=message) as err:
        atomic.write_image(tmp_path / name, np.zeros((4, 4), np.uint8))
    assert name in str(err.value) and "\n" not in str(err.value)
    assert list(tmp_path.iterdir()) == []


def test_write_image_turns_an_opencv_exception_into_an_input_error(tmp_path):
    # a 5-channel image: OpenCV's PNG encoder raises cv2.error rather than returning False
    with pytest.raises(InputError, match="g.png: OpenCV could not write the image") as err:
        atomic.write_image(tmp_path / "g.png", np.zeros((4, 4, 5), np.uint8))
    assert "\n" not in str(err.value)
    assert list(tmp_path.iterdir()) == []


def test_disparity_with_no_finite_value_is_rejected(tmp_path):
    np.save(tmp_path / "nan.npy", np.full((4, 5), np.nan, np.float32))
    with pytest.raises(InputError, match="nan.npy: disparity has no finite value"):
        read_disparity(tmp_path, {"id": 1, "disparity_file": "nan.npy"})


def test_disparity_with_some_invalid_pixels_is_kept_as_it_is(tmp_path):
    disp = np.zeros((4, 5), np.float32)
    disp[0] = np.nan  # invalid pixels are legitimate
    disp[1, 1] = 3.5
    np.save(tmp_path / "part.npy", disp)
    out = read_disparity(tmp_path, {"id": 1, "disparity_file": "part.npy"})
    assert out.dtype == np.float64 and np.isnan(out[0]).all() and out[1, 1] == 3.5

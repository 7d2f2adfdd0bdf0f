import cv2
import numpy as np
import pytest

from lunarnav_ml.data.coco import load_coco
from lunarnav_ml.data.yolo_txt import import_yolo_txt
from lunarnav_ml.errors import InputError


def _layout(tmp_path, lines):
    (tmp_path / "images").mkdir()
    (tmp_path / "labels").mkdir()
    cv2.imwrite(str(tmp_path / "images" / "a.jpg"), np.zeros((50, 100, 3), np.uint8))
    cv2.imwrite(str(tmp_path / "images" / "b.png"), np.zeros((40, 40), np.uint8))
    (tmp_path / "labels" / "a.txt").write_text("\n".join(lines))
    return tmp_path / "annotations.json"


def test_import_known_answer(tmp_path):
    out = _layout(tmp_path, ["0 0.5 0.5 0.2 0.4", "2 0.1 0.1 0.2 0.2", ""])
    import_yolo_txt(tmp_path / "images", tmp_path / "labels", out)
    records = load_coco(out)  # the result passes the COCO validation
    assert [r.path.name for r in records] == ["a.jpg", "b.png"]
    np.testing.assert_allclose(records[0].boxes, [[40, 15, 60, 35], [0, 0, 20, 10]])
    assert records[0].labels.tolist() == [1, 3] and len(records[1].boxes) == 0


@pytest.mark.parametrize("line, match", [
    ("5 0.5 0.5 0.1 0.1", "a.txt:1: unknown class 5"),
    ("0 0.5 0.5 0.1", "expected 'class cx cy w h'"),
    ("0 0.5 1.5 0.1 0.1", r"outside \[0, 1\]"),
    ("0 0.5 0.5 0 0.1", "zero size"),
])
def test_bad_label_lines(tmp_path, line, match):
    out = _layout(tmp_path, [line])
    with pytest.raises(InputError, match=match):
        import_yolo_txt(tmp_path / "images", tmp_path / "labels", out)


def test_no_images(tmp_path):
    with pytest.raises(InputError, match="no images found"):
        import_yolo_txt(tmp_path, tmp_path, tmp_path / "a.json")

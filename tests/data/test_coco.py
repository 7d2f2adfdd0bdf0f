import json
import shutil

import numpy as np
import pytest

from lunarnav_ml.data.coco import load_coco, read_image
from lunarnav_ml.data.dataset import CocoDetection, collate
from lunarnav_ml.data.letterbox import letterbox
from lunarnav_ml.errors import InputError


def _copy(tiny_coco, tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(tiny_coco["val"].parent, root)
    path = root / "annotations.json"
    return path, json.loads(path.read_text())


def test_load_records(tiny_coco):
    records = load_coco(tiny_coco["train"])
    assert len(records) == 16
    rec = records[3]
    assert rec.boxes.shape == (3, 4) and rec.labels.dtype == np.int64
    assert rec.ignore.tolist() == [False, False, True]  # image 4 carries an ignore region
    assert read_image(rec).shape == (96, 96, 3)  # grayscale PNG read as RGB


@pytest.mark.parametrize("edit, match", [
    (lambda d: d["annotations"][0].update(bbox=[90.0, 10.0, 20.0, 5.0]), "lies outside image"),
    (lambda d: d["annotations"][0].update(category_id=7), "unknown category_id 7"),
    (lambda d: d["annotations"][0].update(bbox=[10.0, 10.0, -3.0, 5.0]), "non-positive width"),
    (lambda d: d["annotations"][0].update(bbox=[10.0, "x", 3.0, 5.0]), "4 finite numbers"),
    (lambda d: d["annotations"][0].update(image_id=999), "unknown image_id 999"),
    (lambda d: d.update(images=[], annotations=[]), "has no images"),
    (lambda d: d.pop("categories"), "missing the 'categories' list"),
])
def test_bad_annotations_name_file_and_item(tiny_coco, tmp_path, edit, match):
    path, data = _copy(tiny_coco, tmp_path)
    edit(data)
    path.write_text(json.dumps(data))
    with pytest.raises(InputError, match=match) as err:
        load_coco(path)
    assert str(path) in str(err.value)


def test_missing_and_corrupt_images(tiny_coco, tmp_path):
    path, data = _copy(tiny_coco, tmp_path)
    first = path.parent / data["images"][0]["file_name"]
    first.write_bytes(b"not a png")
    records = load_coco(path)
    with pytest.raises(InputError, match=r"0000.png: corrupt or unreadable image \(image id 1\)"):
        read_image(records[0])
    first.unlink()
    with pytest.raises(InputError, match="image id 1: file .*0000.png not found"):
        load_coco(path)


def test_missing_or_invalid_json(tmp_path):
    with pytest.raises(InputError, match="annotation file not found"):
        load_coco(tmp_path / "nope.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    with pytest.raises(InputError, match="bad.json: annotation is not valid JSON"):
        load_coco(bad)


def test_letterbox_round_trip():
    image = np.zeros((50, 100, 3), np.uint8)
    square, info = letterbox(image, 64)
    assert square.shape == (64, 64, 3) and info.scale == pytest.approx(0.64)
    box = np.array([[10.0, 5.0, 40.0, 45.0]])
    inside = box * info.scale + [info.pad_x, info.pad_y, info.pad_x, info.pad_y]
    np.testing.assert_allclose(info.to_original(inside, 100, 50), box, atol=1e-4)
    # a (height, width) rectangle: the largest scale that fits, the rest padded
    rect, info = letterbox(np.full((50, 100, 3), 9, np.uint8), (32, 96))
    assert rect.shape == (32, 96, 3) and info.scale == pytest.approx(0.64)
    assert (info.pad_x, info.pad_y) == (16.0, 0.0) and rect[:, 16:80].max() == 9
    assert (rect[:, :16] == 114).all() and (rect[:, 80:] == 114).all()


@pytest.mark.parametrize("augment, mosaic", [(False, 0.0), (True, 0.0), (True, 1.0)])
def test_dataset_items(tiny_coco, augment, mosaic):
    import torch

    torch.manual_seed(0)  # each item's augmentation seed comes from torch's generator
    ds = CocoDetection(tiny_coco["train"], img_size=64, augment=augment, mosaic_prob=mosaic)
    images, targets, metas = collate([ds[i] for i in range(4)])
    assert images.shape == (4, 3, 64, 64) and images.dtype.is_floating_point is False
    assert sum(len(t["boxes"]) for t in targets) > 0
    for t in targets:
        b = t["boxes"]  # may be empty: a mosaic or crop can leave every box out of the square
        assert b.shape[1] == 4 and len(t["labels"]) == len(b) == len(t["ignore"])
        assert (b[:, 2:] > b[:, :2]).all() and (len(b) == 0 or (b.min() >= 0 and b.max() <= 64))
        assert set(t["labels"].tolist()) <= {1, 2, 3}
    assert {"image_id", "scale", "pad", "size"} <= set(metas[0])


def test_dataset_is_deterministic_under_torch_seed(tiny_coco):
    import torch

    ds = CocoDetection(tiny_coco["train"], img_size=64, augment=True, mosaic_prob=0.5)
    torch.manual_seed(3)
    a = [ds[i] for i in range(3)]
    torch.manual_seed(3)
    b = [ds[i] for i in range(3)]
    for (ia, ta, _), (ib, tb, _) in zip(a, b):
        assert torch.equal(ia, ib) and torch.equal(ta["boxes"], tb["boxes"])


@pytest.mark.parametrize("size", [100, 0, -32])
def test_img_size_must_be_positive_multiple_of_32(tiny_coco, size):
    with pytest.raises(InputError, match=f"positive multiple of 32, got {size}"):
        CocoDetection(tiny_coco["train"], img_size=size)

import dataclasses

import cv2
import numpy as np
import pytest
import torch

from lunarnav_ml.data.augment import Boxes, apply_augment, build_augment, mosaic
from lunarnav_ml.data.datamodule import DetectionDataModule, mixing_weights
from lunarnav_ml.data.dataset import CocoDetection, crop_around_box
from lunarnav_ml.errors import ConfigError, InputError


def test_mixing_weights_known_answer():
    w = mixing_weights([2, 6], [0.5, 0.5])
    assert w.shape == (8,)
    torch.testing.assert_close(w[:2].sum(), w[2:].sum().to(w))  # each source half the draws
    with pytest.raises(ConfigError, match="2 sampling weights for 3 training sources"):
        mixing_weights([1, 2, 3], [1.0, 1.0])
    with pytest.raises(ConfigError, match="positive sum"):
        mixing_weights([1, 2], [0.0, 0.0])


def test_two_sources_are_drawn_by_weight(tiny_coco):
    dm = DetectionDataModule([str(tiny_coco["train"]), str(tiny_coco["val"])],
                             str(tiny_coco["val"]), weights=[0.0, 1.0], img_size=64,
                             batch_size=4, augment=False)
    dm.setup("fit")
    torch.manual_seed(0)
    loader = dm.train_dataloader()
    val_ids = {r.image_id for r in dm.val_set.records}
    ids = [m["image_id"] for _, _, metas in loader for m in metas]
    assert len(ids) == 24 and set(ids) <= val_ids  # weight 0: the first source never drawn
    anchors = dm.kmeans_anchors(levels=3)
    assert anchors.shape == (3, 3, 2)


def test_horizontal_flip_moves_boxes():
    aug = build_augment(flip_lr=1.0, exposure=0.0, noise=0.0, blur=0.0, affine=0.0)
    image = np.zeros((32, 64, 3), np.uint8)
    boxes = Boxes(np.array([[4.0, 2.0, 14.0, 12.0]], np.float32), np.array([1]),
                  np.array([False]))
    out_img, out = apply_augment(aug, image, boxes, seed=0)
    assert out_img.shape == image.shape
    np.testing.assert_allclose(out.boxes, [[50.0, 2.0, 60.0, 12.0]], atol=1e-3)
    assert out.labels.tolist() == [1] and out.ignore.tolist() == [False]


def test_mosaic_keeps_boxes_inside_and_labels():
    rng = np.random.default_rng(0)
    parts = [Boxes(np.array([[10.0, 10.0, 30.0, 30.0]], np.float32), np.array([k]),
                   np.array([k == 3])) for k in (1, 2, 3, 1)]
    images = [np.full((64, 48, 3), 40 * k, np.uint8) for k in range(4)]
    out, boxes = mosaic(images, parts, 64, rng)
    assert out.shape == (64, 64, 3)
    assert (boxes.boxes >= 0).all() and (boxes.boxes <= 64).all()
    assert set(boxes.labels.tolist()) <= {1, 2, 3} and len(boxes.labels) == len(boxes.ignore)


def _gradient_image(h: int, w: int) -> np.ndarray:
    vv, uu = np.mgrid[0:h, 0:w]
    return np.stack([uu % 256, vv % 256, (uu // 256 + 4 * (vv // 256)) * 16], -1).astype(np.uint8)


def test_crop_around_box_holds_a_box_centre_and_ignores_cut_boxes():
    image = _gradient_image(300, 1000)
    boxes = Boxes(np.array([[700.0, 150.0, 760.0, 170.0],   # the only live box
                            [0.0, 0.0, 1000.0, 40.0],       # wider than any crop: cut
                            [100.0, 100.0, 120.0, 110.0]], np.float32),
                  np.array([1, 1, 2]), np.array([False, False, True]))
    boxes.ignore[1] = True  # only box 0 can centre a crop
    rng = np.random.default_rng(3)
    for _ in range(20):
        crop, out, (x0, y0) = crop_around_box(image, boxes, 128, rng, p_box=1.0)
        assert crop.shape == (128, 128, 3)
        assert x0 <= 730 < x0 + 128 and y0 <= 160 < y0 + 128  # the box centre is inside
        np.testing.assert_array_equal(crop, image[y0:y0 + 128, x0:x0 + 128])  # pixels line up
        live = out.boxes[~out.ignore]
        assert (out.boxes >= 0).all() and (out.boxes <= 128).all()
        for b in live:  # a live box is (nearly) whole: 90 % of it inside the crop
            assert (b[2] - b[0]) * (b[3] - b[1]) >= 0.9 * 60 * 20 - 1e-3
    # the same generator state gives the same crop
    a = crop_around_box(image, boxes, 128, np.random.default_rng(7))
    b = crop_around_box(image, boxes, 128, np.random.default_rng(7))
    assert a[2] == b[2] and np.array_equal(a[1].boxes, b[1].boxes)


def test_crop_cuts_a_live_box_into_an_ignore_region():
    image = _gradient_image(256, 256)
    boxes = Boxes(np.array([[10.0, 10.0, 200.0, 30.0]], np.float32), np.array([1]),
                  np.array([False]))
    _, out, _ = crop_around_box(image, boxes, 64, np.random.default_rng(0), p_box=1.0)
    assert len(out.boxes) == 1 and out.ignore.tolist() == [True]  # 190 px wide in 64 px


def test_read_size_crops_training_frames(tiny_coco):
    ds = CocoDetection(tiny_coco["train"], img_size=64, augment=True, read_size=96)
    torch.manual_seed(0)
    image, target, meta = ds[0]
    assert image.shape == (3, 64, 64)
    assert meta["scale"] == 1.0 and meta["pad"][0] <= 0 and meta["pad"][1] <= 0
    assert (target["boxes"] >= 0).all() and (target["boxes"] <= 64).all()
    assert CocoDetection(tiny_coco["val"], img_size=64, augment=False, read_size=96
                         ).read_size == 64  # validation sees whole frames
    with pytest.raises(InputError, match="read_size"):
        CocoDetection(tiny_coco["val"], img_size=64, read_size=32)
    with pytest.raises(ConfigError, match="read_sizes: 1 entries for 2"):
        DetectionDataModule([str(tiny_coco["train"]), str(tiny_coco["val"])],
                            str(tiny_coco["val"]), read_sizes=[96]).setup("fit")


def test_preload_fills_the_cache_the_workers_share(tiny_coco):
    lazy = CocoDetection(tiny_coco["train"], img_size=64)
    dm = DetectionDataModule(str(tiny_coco["train"]), str(tiny_coco["val"]), img_size=64,
                             batch_size=4, num_workers=1, augment=False)
    dm.setup("fit")
    ds = dm.train_sets[0]
    assert len(ds._cache) == len(ds) and len(dm.val_set._cache) == len(dm.val_set)
    for i in (0, len(ds) - 1):
        np.testing.assert_array_equal(ds[i][0].numpy(), lazy[i][0].numpy())
    threads = cv2.getNumThreads()
    try:
        ids = [m["image_id"] for _, _, metas in dm.train_dataloader() for m in metas]
        assert cv2.getNumThreads() == 1  # set before the workers fork, not inside them
    finally:
        cv2.setNumThreads(threads)
    assert sorted(ids) == sorted(r.image_id for r in ds.records)


def test_preload_names_a_corrupt_image(tiny_coco, tmp_path):
    ds = CocoDetection(tiny_coco["val"], img_size=64)
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not a png")
    ds.records[3] = dataclasses.replace(ds.records[3], path=bad)
    with pytest.raises(InputError, match="bad.png: corrupt"):
        ds.preload(threads=2)


@pytest.mark.parametrize("field, value, message", [
    ("img_size", 0, "data.img_size: must be a positive multiple of 32, got 0"),
    ("img_size", -32, "data.img_size: must be a positive multiple of 32, got -32"),
    ("img_size", 100, "data.img_size: must be a positive multiple of 32, got 100"),
    ("batch_size", 0, "data.batch_size: must be an integer >= 1, got 0"),
    ("num_workers", -1, "data.num_workers: must be an integer >= 0, got -1"),
])
def test_impossible_loader_settings_are_config_errors(field, value, message):
    """Caught when the DataModule is built, not as a DataLoader ValueError at fit."""
    with pytest.raises(ConfigError, match=message):
        DetectionDataModule("train.json", "val.json", **{field: value})

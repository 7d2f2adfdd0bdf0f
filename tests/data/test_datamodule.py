import numpy as np
import pytest
import torch

from lunarnav_ml.data.augment import Boxes, apply_augment, build_augment, mosaic
from lunarnav_ml.data.datamodule import DetectionDataModule, mixing_weights
from lunarnav_ml.errors import ConfigError


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

"""numpy NMS and post-processing against known answers and torchvision."""

import numpy as np
import torch

from lunarnav_ml.models.decode import postprocess as torch_postprocess
from lunarnav_ml.runtime.nms import batched_nms, cxcywh_to_xyxy, nms, postprocess, split_graph_nms


def test_nms_known_answer():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [20, 20, 30, 30], [0, 0, 10, 9]], float)
    scores = np.array([0.9, 0.8, 0.7, 0.95])
    # box 3 (0.95) suppresses 0 (IoU 0.9) and 1 (IoU ~0.61 > 0.5); box 2 is apart
    np.testing.assert_array_equal(nms(boxes, scores, 0.5), [3, 2])
    np.testing.assert_array_equal(nms(boxes, scores, 0.95), [3, 0, 1, 2])


def test_classes_never_suppress_each_other():
    boxes = np.array([[0, 0, 10, 10], [0, 0, 10, 10]], float)
    keep = batched_nms(boxes, np.array([0.9, 0.8]), np.array([0, 1]), 0.5)
    np.testing.assert_array_equal(keep, [0, 1])
    assert batched_nms(np.zeros((0, 4)), np.zeros(0), np.zeros(0, int), 0.5).shape == (0,)


def test_matches_torchvision_batched_nms():
    from torchvision.ops import batched_nms as tv_batched_nms

    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 200, (400, 2))
    boxes = np.concatenate([xy, xy + rng.uniform(5, 60, (400, 2))], axis=1).astype(np.float32)
    scores = rng.random(400).astype(np.float32)
    labels = rng.integers(0, 3, 400)
    ref = tv_batched_nms(torch.from_numpy(boxes), torch.from_numpy(scores),
                         torch.from_numpy(labels), 0.45).numpy()
    np.testing.assert_array_equal(batched_nms(boxes, scores, labels, 0.45), ref)


def test_postprocess_matches_the_torch_postprocess():
    rng = np.random.default_rng(1)
    decoded = np.concatenate([rng.uniform(10, 300, (2, 500, 2)), rng.uniform(4, 80, (2, 500, 2)),
                              rng.random((2, 500, 4))], axis=2).astype(np.float32)
    ours = postprocess(decoded, conf_thres=0.05, iou_thres=0.5, max_det=100)
    ref = torch_postprocess(torch.from_numpy(decoded), 0.05, 0.5, 100)
    for o, r in zip(ours, ref):
        np.testing.assert_allclose(o["boxes"], r["boxes"].numpy(), atol=1e-5)
        np.testing.assert_allclose(o["scores"], r["scores"].numpy())
        np.testing.assert_array_equal(o["labels"], r["labels"].numpy())
        assert len(o["boxes"]) <= 100 and set(o["labels"]) <= {1, 2, 3}


def test_cxcywh_to_xyxy():
    np.testing.assert_allclose(cxcywh_to_xyxy(np.array([[10.0, 20.0, 4.0, 6.0]])),
                               [[8.0, 17.0, 12.0, 23.0]])


def test_split_graph_nms_per_image_by_score():
    indices = np.array([[0, 0, 5], [1, 2, 3], [0, 1, 7]])
    boxes = np.arange(12, dtype=np.float32).reshape(3, 4)
    out = split_graph_nms(indices, boxes, np.array([0.2, 0.9, 0.6], np.float32), batch=3,
                          max_det=5)
    np.testing.assert_array_equal(out[0]["labels"], [2, 1])
    np.testing.assert_array_equal(out[0]["boxes"], boxes[[2, 0]])
    np.testing.assert_array_equal(out[1]["labels"], [3])
    assert len(out[2]["boxes"]) == 0

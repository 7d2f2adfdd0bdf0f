import numpy as np
import pytest

from lunarnav_ml.data.anchors import anchors_for_levels, kmeans_anchors, mean_best_iou
from lunarnav_ml.errors import InputError


def test_kmeans_recovers_known_clusters():
    rng = np.random.default_rng(0)
    truth = np.array([[8.0, 10.0], [30.0, 20.0], [90.0, 110.0]])
    wh = np.concatenate([c * rng.uniform(0.95, 1.05, (200, 2)) for c in truth])
    anchors = kmeans_anchors(wh, 3, seed=1)
    np.testing.assert_allclose(anchors, truth, rtol=0.05)
    assert mean_best_iou(wh, anchors) > 0.9


def test_anchors_split_by_level_and_sorted():
    wh = np.random.default_rng(1).uniform(4, 120, (500, 2))
    anchors = anchors_for_levels(wh, levels=3)
    areas = anchors.prod(axis=2).ravel()
    assert anchors.shape == (3, 3, 2) and np.all(np.diff(areas) >= 0)
    np.testing.assert_array_equal(anchors, anchors_for_levels(wh, levels=3))  # deterministic


def test_too_few_boxes():
    with pytest.raises(InputError, match="need at least 9 labelled boxes, found 2"):
        kmeans_anchors(np.ones((2, 2)), 9)

"""Transfer metrics on hand-made cases with known answers; the written report and gallery."""

import cv2
import numpy as np
import pytest

from lunarnav_ml.errors import InputError
from lunarnav_ml.eval.coco_metrics import coco_from_dict
from lunarnav_ml.realdata.transfer import (
    recall_at_budgets,
    transfer_metrics,
    write_transfer_report,
)

CATEGORIES = [{"id": 1, "name": "crater"}, {"id": 2, "name": "rock"}, {"id": 3, "name": "artifact"}]


def _ann(k, image_id, cat, bbox, ignore=False):
    return {"id": k, "image_id": image_id, "category_id": cat, "bbox": bbox,
            "area": bbox[2] * bbox[3], "ignore": ignore, "iscrowd": int(ignore)}


def _det(image_id, cat, bbox, score):
    return {"image_id": image_id, "category_id": cat, "bbox": bbox, "score": score}


@pytest.fixture
def case():
    """Image 1 (pcam_pan): craters A, B and an ignored C; image 2 (ce4): rock R."""
    gt = {"images": [{"id": 1, "file_name": "a.png", "width": 64, "height": 64,
                      "camera_name": "pcam_pan"},
                     {"id": 2, "file_name": "b.png", "width": 64, "height": 64,
                      "camera_name": "ce4"}],
          "annotations": [_ann(1, 1, 1, [0, 0, 10, 10]), _ann(2, 1, 1, [20, 20, 10, 10]),
                          _ann(3, 1, 1, [40, 40, 10, 10], ignore=True),
                          _ann(4, 2, 2, [5, 5, 10, 10])],
          "categories": CATEGORIES}
    results = [_det(1, 1, [0, 0, 10, 10], 0.9),  # finds A
               _det(1, 1, [50, 0, 10, 10], 0.8),  # nothing there
               _det(1, 1, [20, 20, 10, 10], 0.7),  # finds B
               _det(1, 1, [40, 40, 10, 10], 0.5),  # on the ignored crater: neither
               _det(2, 2, [5, 5, 10, 10], 0.6),  # finds R
               _det(2, 1, [0, 0, 5, 5], 0.99)]  # a crater where image 2 has none
    return gt, results


def test_recall_at_budgets_known_answer(case):
    gt, results = case
    recall = recall_at_budgets(coco_from_dict(gt), results)
    assert recall["crater"] == {"n_gt": 2, "recall@1": 0.5, "recall@3": 1.0, "recall@5": 1.0,
                                "recall@10": 1.0}
    assert recall["rock"]["n_gt"] == 1 and recall["rock"]["recall@1"] == 1.0
    assert recall["artifact"] == {"n_gt": 0, "recall@1": None, "recall@3": None,
                                  "recall@5": None, "recall@10": None}


@pytest.mark.parametrize("shift, found", [(4, 0.0), (2, 1.0)])  # IoU 0.43 misses, 0.67 hits
def test_recall_needs_iou_half(shift, found):
    gt = {"images": [{"id": 1, "file_name": "a.png", "width": 64, "height": 64}],
          "annotations": [_ann(1, 1, 1, [0, 0, 10, 10])], "categories": CATEGORIES}
    recall = recall_at_budgets(coco_from_dict(gt), [_det(1, 1, [shift, 0, 10, 10], 0.9)],
                               budgets=(1,))
    assert recall["crater"]["recall@1"] == found


def test_metrics_per_camera_and_ap50(case):
    gt, results = case
    m = transfer_metrics(gt, results)
    crater = m["all"]["per_class"]["crater"]
    # crater ranking: FP .99, TP .9, FP .8, TP .7 (the .5 one is ignored): precision 0.5 at
    # every recall level, so AP50 = 0.5.
    assert crater["AP50"] == pytest.approx(0.5) and crater["recall@1"] == 0.5
    assert m["all"]["per_class"]["rock"]["AP50"] == pytest.approx(1.0)
    assert set(m["per_camera"]) == {"ce4", "pcam_pan"}
    pan, ce4 = m["per_camera"]["pcam_pan"], m["per_camera"]["ce4"]
    assert pan["n_images"] == 1 and pan["per_class"]["crater"]["recall@1"] == 0.5
    # image 1 alone: TP .9, FP .8, TP .7 -> interpolated precision 1 up to recall 0.5 (51 of
    # COCO's 101 recall points), 2/3 above it (50 points).
    assert pan["per_class"]["crater"]["AP50"] == pytest.approx((51 + 50 * 2 / 3) / 101)
    assert pan["per_class"]["rock"]["n_gt"] == 0 and pan["per_class"]["rock"]["AP50"] is None
    assert ce4["per_class"]["rock"]["recall@10"] == 1.0 and ce4["per_class"]["crater"]["n_gt"] == 0
    assert "lower bound" in m["note"]


def test_no_detections_and_bad_detections(case):
    gt, _ = case
    m = transfer_metrics(gt, [])
    assert m["all"]["per_class"]["crater"]["recall@10"] == 0.0
    assert m["all"]["per_class"]["crater"]["AP50"] == 0.0
    with pytest.raises(InputError, match="image_id 7"):
        transfer_metrics(gt, [_det(7, 1, [0, 0, 1, 1], 0.5)])


def test_report_and_gallery(case, tmp_path):
    gt, results = case
    for img in gt["images"]:
        cv2.imwrite(str(tmp_path / img["file_name"]), np.full((64, 64, 3), 90, np.uint8))
    out = tmp_path / "report"
    write_transfer_report(gt, results, tmp_path, out, gallery_images=3, top_k=2)
    text = (out / "transfer_report.md").read_text()
    assert "## camera ce4 (1 images)" in text and "lower bound" in text
    assert "| crater | 2 | 0.500 | 1.000 | 1.000 | 1.000 | 0.500 |" in text
    gallery = cv2.imread(str(out / "gallery.png"))
    assert gallery.shape == (320, 4 * 320, 3)  # 2 images, padded to one row of 4 tiles
    assert (out / "transfer_metrics.json").is_file()

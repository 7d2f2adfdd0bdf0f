"""Known-answer tests for COCO AP and the paper's Pd / false-alarm metrics."""

import math

import numpy as np
import pytest

from lunarnav_ml.errors import InputError
from lunarnav_ml.eval.coco_metrics import coco_ap
from lunarnav_ml.eval.pd import box_precision, match_craters, pd_by, pick_operating_threshold
from lunarnav_ml.eval.report import detection_metrics, render_markdown

CATS = [{"id": 1, "name": "crater"}, {"id": 2, "name": "rock"}, {"id": 3, "name": "artifact"}]


def _gt():
    images = [{"id": i, "width": 100, "height": 100, "file_name": f"{i}.png",
               "sun_zenith_deg": 20.0 * i, "sun_azimuth_deg": 300.0} for i in (1, 2)]
    anns = [
        {"id": 1, "image_id": 1, "category_id": 1, "bbox": [10, 10, 20, 20],
         "near_rim_range_m": 8.0, "diameter_m": 6.0},
        {"id": 2, "image_id": 1, "category_id": 1, "bbox": [60, 60, 20, 10],
         "near_rim_range_m": 16.0, "diameter_m": 12.0},
        {"id": 3, "image_id": 2, "category_id": 1, "bbox": [5, 5, 30, 30], "ignore": True,
         "near_rim_range_m": 40.0, "diameter_m": 6.0},
        {"id": 4, "image_id": 2, "category_id": 2, "bbox": [50, 50, 10, 10]},
    ]
    for a in anns:
        a["area"] = a["bbox"][2] * a["bbox"][3]
    return {"images": images, "annotations": anns, "categories": CATS}


def _det(img, cat, bbox, score):
    return {"image_id": img, "category_id": cat, "bbox": bbox, "score": score}


def test_perfect_detections_give_ap_one():
    gt = _gt()
    results = [_det(a["image_id"], a["category_id"], a["bbox"], 0.9)
               for a in gt["annotations"] if not a.get("ignore")]
    m = coco_ap(gt, results)
    assert m["per_class"]["crater"]["AP50"] == pytest.approx(1.0)
    assert m["per_class"]["rock"]["AP"] == pytest.approx(1.0)
    assert m["per_class"]["artifact"]["AP"] is None  # no ground truth
    assert m["per_class"]["crater"]["n_gt"] == 2


def test_detection_on_ignored_box_is_not_a_false_alarm():
    gt = _gt()
    results = [_det(1, 1, [10, 10, 20, 20], 0.9), _det(2, 1, [5, 5, 30, 30], 0.8),
               _det(2, 1, [70, 0, 20, 20], 0.7)]
    match = match_craters(gt, results, threshold=0.5)
    assert match.hit.tolist() == [True, False]
    assert match.false_alarms == 1  # only the box on empty ground
    assert match.fa_per_image == 0.5
    # ignored boxes also do not count in pycocotools AP: one of two craters found at top score
    assert coco_ap(gt, results)["per_class"]["crater"]["AP50"] == pytest.approx(0.5, abs=0.02)


def test_box_inside_an_ignored_crater_is_not_a_false_alarm():
    # a 10 x 10 box on part of the ignored 30 x 30 crater: IoU 0.11, but all of it lies on the
    # crater (pycocotools' crowd overlap 1.0), as the AP counts it; half on, half off is the edge
    gt = _gt()
    inside = [_det(2, 1, [10, 10, 10, 10], 0.9)]
    assert match_craters(gt, inside, threshold=0.5).false_alarms == 0
    straddling = [_det(2, 1, [30, 10, 10, 10], 0.9)]  # 5 of its 10 px width on the crater
    assert match_craters(gt, straddling, threshold=0.5).false_alarms == 0
    mostly_off = [_det(2, 1, [32, 10, 10, 10], 0.9)]  # 3 of 10 px on it
    assert match_craters(gt, mostly_off, threshold=0.5).false_alarms == 1


def test_box_precision_of_the_matched_boxes():
    gt = _gt()
    # crater 1 (20 x 20 at 10, 10): left edge +2 px, right edge -2 px (width ratio 0.8);
    # crater 2 (20 x 10 at 60, 60): found exactly; a false alarm does not count
    results = [_det(1, 1, [12, 10, 16, 20], 0.9), _det(1, 1, [60, 60, 20, 10], 0.8),
               _det(2, 1, [80, 0, 10, 10], 0.7)]
    match = match_craters(gt, results, threshold=0.5)
    np.testing.assert_array_equal(match.box[0], [12, 10, 16, 20])
    b = box_precision(match)
    assert b["n"] == 2
    assert b["width_ratio_median"] == pytest.approx(-0.1)  # median of 0.8 and 1.0, minus 1
    assert b["height_ratio_median"] == pytest.approx(0.0)
    # per edge, two offsets (0.1 and 0): MAD 0.05, so sigma 1.4826 x 0.05
    assert b["edge_sigma"]["left"] == pytest.approx(1.4826 * 0.05)
    assert b["edge_sigma"]["top"] == 0.0
    missed = match_craters(gt, [_det(1, 1, [0, 80, 10, 10], 0.9)], threshold=0.5)
    assert np.isnan(missed.box).all() and box_precision(missed) == {"n": 0}
    md = render_markdown(detection_metrics(gt, results, 0.5), "t")
    assert "## Box precision of the detected craters" in md and "| all craters | 2 |" in md


def test_threshold_and_low_iou():
    gt = _gt()
    results = [_det(1, 1, [10, 10, 20, 20], 0.3), _det(1, 1, [60, 60, 40, 40], 0.9)]
    assert match_craters(gt, results, threshold=0.5).hit.tolist() == [False, False]
    assert match_craters(gt, results, threshold=0.2).hit.tolist() == [True, False]


def test_operating_threshold_respects_false_alarm_budget():
    gt = _gt()
    results = [_det(1, 1, [10, 10, 20, 20], 0.9), _det(1, 1, [60, 60, 20, 10], 0.6),
               _det(1, 1, [0, 80, 10, 10], 0.7), _det(2, 1, [80, 0, 10, 10], 0.4)]
    thr = pick_operating_threshold(gt, results, max_fa_per_image=0.5)
    assert thr == pytest.approx(0.6)  # admits the 0.7 false alarm (0.5 per image) but not the 0.4
    assert match_craters(gt, results, thr).fa_per_image <= 0.5
    assert pick_operating_threshold(gt, results, max_fa_per_image=0.0) == pytest.approx(0.9)
    assert pick_operating_threshold(gt, [], 0.2) == 1.0


def test_pd_bins_and_report():
    gt = _gt()
    results = [_det(1, 1, [10, 10, 20, 20], 0.9)]
    match = match_craters(gt, results, 0.5)
    rows = pd_by(match, "near_rim_range_m", [5, 10, 20])
    assert [(r["n"], r["pd"]) for r in rows] == [(1, 1.0), (1, 0.0)]
    metrics = detection_metrics(gt, results, 0.5)
    assert metrics["crater_pd_D5_within20m"] == pytest.approx(0.5)
    low, high = metrics["crater_pd_D5_within20m_ci95"]  # 1 of 2: Wilson's closed form
    z = 1.959963984540054
    centre, half = (1 + z * z / 2) / (2 + z * z), z * math.sqrt(0.25 * 2 + z * z / 4) / (2 + z * z)
    assert (low, high) == pytest.approx((centre - half, centre + half))
    assert "; 95 % interval 0.095-0.905, Wilson" in render_markdown(metrics, "t")
    from lunarnav_ml.eval.report import pd_interval

    assert pd_interval(0, 0) is None
    low, high = pd_interval(292, 324)  # session 77's key craters on the mono quarter
    assert low < 292 / 324 < high and high - low == pytest.approx(0.065, abs=0.005)
    assert metrics["pd_vs_sun_azimuth"][2]["n"] == 2  # 300 deg folds to 60 deg
    text = render_markdown(metrics, "t")
    assert "| crater |" in text and "Pd vs near-rim range" in text


def test_report_notes_synthetic_labels_from_before_the_overprint_rule():
    results = [_det(1, 1, [10, 10, 20, 20], 0.9)]
    gt = _gt()
    assert "labels_predate_overprint_rule" not in detection_metrics(gt, results, 0.5)  # real
    for a in gt["annotations"][:3]:
        a["visible_rim_fraction"] = 1.0
    metrics = detection_metrics(gt, results, 0.5)
    assert metrics["labels_predate_overprint_rule"] is True
    assert "predate the `overprinted` rule" in render_markdown(metrics, "t")
    for a in gt["annotations"][:3]:
        a["surviving_bowl_fraction"] = 1.0
    assert "labels_predate_overprint_rule" not in detection_metrics(gt, results, 0.5)


def test_bad_detections_raise_naming_the_item():
    gt = _gt()
    with pytest.raises(InputError, match="detection 0: unknown category_id 7"):
        coco_ap(gt, [_det(1, 7, [0, 0, 1, 1], 0.5)])
    with pytest.raises(InputError, match="detection 0: image_id 99"):
        coco_ap(gt, [_det(99, 1, [0, 0, 1, 1], 0.5)])
    with pytest.raises(InputError, match="finite"):
        coco_ap(gt, [_det(1, 1, [0, np.nan, 1, 1], 0.5)])


def test_report_notes_countable_craters_seen_edge_on():
    results = [_det(1, 1, [10, 10, 20, 20], 0.9)]
    gt = _gt()
    for a in gt["annotations"][:3]:
        a["visible_rim_fraction"], a["surviving_bowl_fraction"] = 1.0, 1.0
        a["ellipse"] = [20.0, 20.0, 10.0, 10.0, 0.0]
    assert "countable_edge_on_craters" not in detection_metrics(gt, results, 0.5)
    gt["annotations"][0]["ellipse"] = [20.0, 20.0, 2.9, 20.0, 70.0]  # 5.8 px across, tilted
    metrics = detection_metrics(gt, results, 0.5)
    assert metrics["countable_edge_on_craters"] == 1
    assert "1 countable crater labels here are seen edge-on" in render_markdown(metrics, "t")
    gt["annotations"][0]["ignore"] = True  # ignored (as the rule marks it): nothing to note
    assert "countable_edge_on_craters" not in detection_metrics(gt, results, 0.5)

import json

import numpy as np

from tests.bench_scripts import load_script
from tests.eval.coco_fixtures import CATEGORIES
from tests.eval.coco_fixtures import ann as _ann

share = load_script("overlay_share")


def _gt() -> dict:
    return {"images": [{"id": i, "file_name": f"{i}.png", "width": 432, "height": 432}
                       for i in (1, 2)],
            "categories": CATEGORIES,
            "annotations": [
                _ann(1, 1, [10, 10, 100, 20]),            # found at 0.6 (and 0.05 elsewhere)
                _ann(2, 1, [200, 200, 40, 20]),           # only a box at IoU < 0.5
                _ann(3, 2, [50, 50, 60, 30]),             # found at 0.15
                _ann(4, 2, [0, 0, 10, 10], ignore=True),  # not counted
                _ann(5, 2, [80, 80, 10, 10], category=2),  # a rock: not counted
            ]}


def _dets() -> list[dict]:
    return [{"image_id": 1, "category_id": 1, "bbox": [12, 10, 100, 20], "score": 0.6},
            {"image_id": 1, "category_id": 1, "bbox": [10, 11, 98, 20], "score": 0.05},
            {"image_id": 1, "category_id": 1, "bbox": [220, 200, 40, 20], "score": 0.9},
            {"image_id": 2, "category_id": 1, "bbox": [50, 52, 60, 30], "score": 0.15},
            {"image_id": 2, "category_id": 2, "bbox": [0, 0, 10, 10], "score": 0.99}]


def test_best_scores_take_the_best_match_at_iou_half():
    best = share.best_scores(_gt(), _dets())
    np.testing.assert_allclose(best, [0.6, 0.0, 0.15])


def test_main_prints_shares_and_boxes_per_frame(tmp_path, capsys):
    gt, dets = tmp_path / "gt.json", tmp_path / "dets.json"
    gt.write_text(json.dumps(_gt()))
    dets.write_text(json.dumps(_dets()))
    assert share.main(["--gt", str(gt), "--detections", str(dets), "--conf", "0.25", "0.1"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines == ["conf 0.25: 0.33 of 3 craters kept, 1.0 crater boxes per frame",
                     "conf 0.1: 0.67 of 3 craters kept, 1.5 crater boxes per frame"]


def test_main_names_a_missing_file(tmp_path, capsys):
    assert share.main(["--gt", str(tmp_path / "none.json"), "--detections", "x"]) == 2
    assert "none.json" in capsys.readouterr().err


def test_main_names_a_malformed_detection_in_one_line(tmp_path, capsys):
    gt, dets = tmp_path / "gt.json", tmp_path / "dets.json"
    gt.write_text(json.dumps(_gt()))
    dets.write_text(json.dumps([{**_dets()[0], "bbox": [1, 2]}]))
    assert share.main(["--gt", str(gt), "--detections", str(dets)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "dets.json[0]" in err[0] and "bbox" in err[0]

"""COCO results files are checked entry by entry before pycocotools reads them."""

import pytest

from lunarnav_ml.errors import InputError
from lunarnav_ml.eval.predict import check_coco_results

GOOD = {"image_id": 3, "category_id": 1, "bbox": [1.0, 2.0, 30.0, 4.5], "score": 0.7}


def test_good_results_pass_unchanged():
    results = [GOOD, {**GOOD, "score": 0}, {k: v for k, v in GOOD.items() if k != "score"}]
    assert check_coco_results(results, "r.json") is results


@pytest.mark.parametrize("bad, message", [
    ({"a": 1}, "expected a list of COCO results, got dict"),
    ([3], r"r.json\[0\]: expected an object"),
    ([{**GOOD, "bbox": [1, 2]}], r"r.json\[0\]: bbox must be 4 finite numbers"),
    ([GOOD, {**GOOD, "bbox": [1, 2, float("nan"), 3]}], r"r.json\[1\]: bbox must be 4 finite"),
    ([{**GOOD, "bbox": [1, 2, -3, 4]}], "negative width or height"),
    ([{**GOOD, "image_id": "3"}], "image_id must be an integer"),
    ([{**GOOD, "category_id": None}], "category_id must be an integer"),
    ([{**GOOD, "score": float("inf")}], "score must be a finite number"),
])
def test_malformed_results_name_the_entry_and_field(bad, message):
    with pytest.raises(InputError, match=message):
        check_coco_results(bad, "r.json")


def test_eval_cli_reports_a_malformed_results_file_in_one_line(tiny_coco, tmp_path, capsys):
    from lunarnav_ml.cli import main

    bad = tmp_path / "short.json"
    bad.write_text('[{"image_id": 1, "category_id": 1, "bbox": [1, 2], "score": 0.5}]')
    code = main(["eval", "--task", "detection", "--gt", str(tiny_coco["val"]), "--threshold",
                 "0.5", "--test-results", str(bad), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "short.json: detections[0]: bbox" in err[0]
    assert not (tmp_path / "out").exists()

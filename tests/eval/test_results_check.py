"""COCO results files are checked entry by entry before pycocotools reads them."""

import json

import pytest

from lunarnav_ml.errors import InputError
from lunarnav_ml.eval.predict import check_coco_results
from tests.detector_fixtures import make_coco

GOOD = {"image_id": 3, "category_id": 1, "bbox": [1.0, 2.0, 30.0, 4.5], "score": 0.7}


def test_good_results_pass_and_a_missing_score_is_filled_in_as_one():
    results = [GOOD, {**GOOD, "score": 0}, {k: v for k, v in GOOD.items() if k != "score"}]
    assert check_coco_results(results, "r.json") is results
    assert [r["score"] for r in results] == [0.7, 0, 1.0]
    assert results[0] == GOOD


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


def _eval(gt, results, out, *extra):
    from lunarnav_ml.cli import main

    return main(["eval", "--task", "detection", "--gt", str(gt), "--threshold", "0.5",
                 "--test-results", str(results), "--out", str(out), "--no-progress", *extra])


def _results_without_score(gt, path):
    anns = json.loads(gt.read_text())["annotations"]
    path.write_text(json.dumps([{k: a[k] for k in ("image_id", "category_id", "bbox")}
                                for a in anns]))
    return path


def test_eval_cli_takes_results_without_score_as_score_one(tiny_coco, tmp_path):
    res = _results_without_score(tiny_coco["val"], tmp_path / "noscore.json")
    assert _eval(tiny_coco["val"], res, tmp_path / "out", "--overlays", "1") == 0
    written = json.loads((tmp_path / "out" / "detections.json").read_text())
    assert {d["score"] for d in written} == {1.0}
    assert len(list((tmp_path / "out" / "overlays").iterdir())) == 1


def test_eval_cli_unreadable_image_for_overlays_is_one_line(tmp_path, capsys):
    gt = make_coco(tmp_path / "set", n_images=2, size=64)
    res = _results_without_score(gt, tmp_path / "res.json")
    bad = tmp_path / "set" / json.loads(gt.read_text())["images"][0]["file_name"]
    bad.write_text("not an image")
    assert _eval(gt, res, tmp_path / "out") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and bad.name in err[0] and "not a readable image" in err[0]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("option, value", [
    ("--threshold", "nan"), ("--threshold", "-1"), ("--threshold", "2"),
    ("--max-fa", "-1"), ("--max-fa", "nan"), ("--max-fa", "inf"), ("--overlays", "-1"),
])
def test_eval_cli_rejects_impossible_settings_before_any_work(tiny_coco, tmp_path, capsys,
                                                             monkeypatch, option, value):
    from lunarnav_ml.eval import cli

    def fail(*args, **kwargs):
        raise AssertionError("results read before the settings were checked")

    monkeypatch.setattr(cli, "read_coco_results", fail)
    res = _results_without_score(tiny_coco["val"], tmp_path / "res.json")
    from lunarnav_ml.cli import main

    code = main(["eval", "--task", "detection", "--gt", str(tiny_coco["val"]), "--test-results",
                 str(res), "--out", str(tmp_path / "out"), "--threshold", "0.5",
                 option, value])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and option in err[0] and value in err[0]
    assert not (tmp_path / "out").exists()


def test_eval_cli_out_that_is_a_file_is_found_before_any_work(tiny_coco, tmp_path, capsys,
                                                             monkeypatch):
    from lunarnav_ml.eval import cli

    def fail(*args, **kwargs):
        raise AssertionError("results read before --out was checked")

    monkeypatch.setattr(cli, "read_coco_results", fail)
    (tmp_path / "afile").write_text("x")
    assert _eval(tiny_coco["val"], tmp_path / "res.json", tmp_path / "afile") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "afile: output folder is an existing file" in err[0]

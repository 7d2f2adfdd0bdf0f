"""``lunarnav eval --task detection``: a split given as both validation and test runs once."""

import json

from lunarnav_ml.cli import main
from lunarnav_ml.eval import predict
from tests.detector_fixtures import make_coco


def test_same_split_for_threshold_and_report_is_detected_once(tmp_path, onnx_path,
                                                               monkeypatch):
    gt = make_coco(tmp_path / "set", n_images=3, size=96)
    calls = []
    real = predict.predict_coco

    def counting(*args, **kwargs):
        calls.append(kwargs.get("desc"))
        return real(*args, **kwargs)

    monkeypatch.setattr(predict, "predict_coco", counting)
    common = ["eval", "--task", "detection", "--model", str(onnx_path), "--no-progress",
              "--overlays", "0"]
    assert main([*common, "--val-gt", str(gt), "--test-gt", str(gt),
                 "--out", str(tmp_path / "a")]) == 0
    assert calls == ["val"]
    other = make_coco(tmp_path / "other", n_images=2, size=96, seed=1)
    assert main([*common, "--val-gt", str(gt), "--test-gt", str(other),
                 "--out", str(tmp_path / "b")]) == 0
    assert calls == ["val", "val", "test"]
    report = json.loads((tmp_path / "a" / "metrics.json").read_text())
    assert report["n_images"] == 3


def test_crater_boxes_refined_by_default_and_said_in_the_report(tmp_path, onnx_path):
    gt = make_coco(tmp_path / "set", n_images=2, size=96)
    common = ["eval", "--task", "detection", "--model", str(onnx_path), "--no-progress",
              "--overlays", "0", "--gt", str(gt), "--threshold", "0.3"]
    runs = {}
    for name, extra in (("on", []), ("off", ["--no-box-refiner"])):
        assert main([*common, *extra, "--out", str(tmp_path / name)]) == 0
        runs[name] = json.loads((tmp_path / name / "detections.json").read_text())
    title = (tmp_path / "on" / "report.md").read_text().splitlines()[0]
    assert title.endswith("(crater boxes refined and rescored by the shipped box refiner)")
    from lunarnav_ml.training.cli import DEFAULT_WEIGHTS

    assert main([*common[:4], str(DEFAULT_WEIGHTS), *common[5:], "--box-rescorer", "--out",
                 str(tmp_path / "rescored")]) == 0
    title = (tmp_path / "rescored" / "report.md").read_text().splitlines()[0]
    assert title.endswith("shipped box refiner; scored by the shipped box rescorer)")
    assert (tmp_path / "off" / "report.md").read_text().splitlines()[0].endswith("annotations.json")
    craters = [r for r in runs["on"] if r["category_id"] == 1]
    assert craters and all(r.get("box_refined") for r in craters)
    assert not any("box_refined" in r for r in runs["off"])
    # a results file is scored as it is: its boxes are not refined again
    assert main(["eval", "--task", "detection", "--gt", str(gt), "--threshold", "0.3",
                 "--test-results", str(tmp_path / "off" / "detections.json"), "--overlays", "0",
                 "--out", str(tmp_path / "file")]) == 0
    assert json.loads((tmp_path / "file" / "detections.json").read_text()) == runs["off"]

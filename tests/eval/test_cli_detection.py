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

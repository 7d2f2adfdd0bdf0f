"""benchmarks/mirrored_read.py: a read of the mirrored frames, its boxes mapped back."""

import json

import numpy as np

from tests.bench_scripts import load_script
from tests.detector_fixtures import make_coco

mir = load_script("mirrored_read")


class _LeftHalfDark:
    """Finds one box around the frame's left 10 columns; records what it was given."""

    img_size = 64

    def __init__(self):
        self.seen = []

    def predict(self, images, conf_thres=0.001, iou_thres=0.6, max_det=300):
        self.seen += [im.copy() for im in images]
        return [{"boxes": np.array([[0, 5, 10, 9]], np.float32),
                 "scores": np.array([0.9], np.float32), "labels": np.array([1])}
                for _ in images]


def test_boxes_of_the_mirrored_frame_come_back_mirrored():
    inner = _LeftHalfDark()
    read = mir.MirroredRead(inner)
    image = np.arange(2 * 3 * 40, dtype=np.uint8).reshape(2 * 3, 40)
    (pred,) = read.predict([image])
    np.testing.assert_array_equal(inner.seen[0], image[:, ::-1])
    np.testing.assert_allclose(pred["boxes"], [[30, 5, 40, 9]])
    assert read.img_size == 64  # other attributes are the wrapped predictor's


def test_the_script_writes_a_read_and_names_bad_input(tmp_path, onnx_path, capsys):
    gt = make_coco(tmp_path / "set", n_images=2, size=96)
    out = tmp_path / "m.json"
    assert mir.main(["--gt", str(gt), "--model", str(onnx_path), "--out", str(out),
                     "--threads", "1", "--no-progress"]) == 0
    results = json.loads(out.read_text())
    assert results and all(r["bbox"][0] >= -1e-3 and r["bbox"][0] + r["bbox"][2] <= 96 + 1e-3
                           for r in results)
    assert mir.main(["--gt", str(tmp_path / "nope.json"), "--model", str(onnx_path),
                     "--out", str(tmp_path / "x.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert "nope.json" in err and "\n" not in err and not (tmp_path / "x.json").exists()

"""benchmarks/squeezed_read.py: the band is read squeezed across, and its boxes come back to
the frame's pixels."""

import json

import numpy as np
import pytest

from tests.bench_scripts import load_script
from tests.detector_fixtures import make_coco

squeezed = load_script("squeezed_read")


class _Fake:
    """Returns two boxes in its input's pixels: one 8 px high, one 40 px high."""
    strides = (8, 16, 32)

    def __init__(self):
        self.img_size, self.seen = 384, []

    def set_img_size(self, size):
        self.img_size = size

    def predict(self, images, conf_thres=0.001, iou_thres=0.6, max_det=300):
        self.seen.append((images[0].shape, self.img_size))
        return [{"boxes": np.array([[10, 20, 50, 28], [0, 0, 60, 40]], np.float32),
                 "scores": np.array([0.9, 0.8], np.float32), "labels": np.array([1, 2])}]


def test_the_band_is_squeezed_and_boxes_map_back():
    fake = _Fake()
    read = squeezed.SqueezedBandRead(fake, 640, (0.15, 0.6), 0.5, 15.0)
    (pred,) = read.predict([np.zeros((1024, 1024, 3), np.uint8)])
    (shape, size), = fake.seen
    assert shape[:2] == (289, 320) and size == (320, 320)  # rows 153-614 at 0.625, across 0.3125
    assert fake.img_size == 384  # the model's own side again
    # the 40 px box is 25 px high at 384 of the frame's 1024: dropped; the other maps back
    np.testing.assert_allclose(pred["boxes"], [[32, 153 + 20 * 462 / 289, 160,
                                                153 + 28 * 462 / 289]], rtol=1e-5)
    assert pred["labels"].tolist() == [1] and pred["scores"].tolist() == [pytest.approx(0.9)]


@pytest.mark.parametrize("kw, says", [({"band": (0.6, 0.2)}, "--band"),
                                      ({"squeeze": float("nan")}, "--squeeze"),
                                      ({"below_px": 0.0}, "--below")])
def test_bad_settings_are_refused(kw, says):
    args = {"side": 640, "band": (0.15, 0.6), "squeeze": 0.5, "below_px": 15.0, **kw}
    with pytest.raises(squeezed.ConfigError, match=says):
        squeezed.SqueezedBandRead(_Fake(), **args)


def test_the_command_writes_results_and_bad_input_is_one_line(tmp_path, onnx_path, capsys):
    gt = make_coco(tmp_path / "set", n_images=2, size=96)
    out = tmp_path / "s.json"
    assert squeezed.main(["--gt", str(gt), "--out", str(out), "--model", str(onnx_path),
                          "--side", "128", "--below", "1000", "--no-progress"]) == 0
    results = json.loads(out.read_text())
    ids = {im["id"] for im in json.loads(gt.read_text())["images"]}
    assert results and {r["image_id"] for r in results} <= ids
    assert squeezed.main(["--gt", str(tmp_path / "none.json"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "none.json" in err[0]

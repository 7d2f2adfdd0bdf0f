"""Test-time augmentation: the sides, mirroring back, fusion scores, and real models."""

import json
import math

import cv2
import numpy as np
import pytest

from lunarnav_ml.errors import ConfigError
from lunarnav_ml.eval.cli import load_predictor
from lunarnav_ml.eval.tta import TTAConfig, TTAPredictor, tta_sides
from lunarnav_ml.training import cli as train_cli
from lunarnav_ml.training.cli import DEFAULT_WEIGHTS
from tests.detector_fixtures import FakeSidedDetector


def test_sides_round_to_the_stride_without_repeats():
    assert tta_sides(224, (0.8, 1.0, 1.2), 32) == [192, 224, 256]
    assert tta_sides(160, (0.8, 1.0, 1.2), 32) == [128, 160, 192]
    assert tta_sides(160, (1.0, 1.05, 0.1), 32) == [160, 32]


@pytest.mark.parametrize("kwargs, field", [({"scales": ()}, "scales"),
                                           ({"scales": (1.0, 0.0)}, "scales"),
                                           ({"scales": (math.nan,)}, "scales"),
                                           ({"fuse_iou": 1.0}, "fuse_iou")])
def test_config_rejects_bad_values(kwargs, field):
    with pytest.raises(ConfigError, match=field):
        TTAConfig(**kwargs)


class BrightSquare(FakeSidedDetector):
    """Finds the bright square of an image exactly; at its own side, on unmirrored images
    only (the square sits right of centre), it also reports a spurious box of class 2."""

    def detect(self, images):
        out = []
        for image in images:
            ys, xs = np.nonzero(image[..., 0] > 200)
            boxes = [[xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]]
            scores, labels = [0.9], [1]
            if self.img_size == 96 and xs.mean() > image.shape[1] / 2:
                boxes.append([0, 0, 8, 8])
                scores.append(0.6)
                labels.append(2)
            out.append({"boxes": np.array(boxes, np.float32), "scores": np.array(scores,
                        np.float32), "labels": np.array(labels, np.int64)})
        return out


def _image():
    image = np.zeros((60, 100, 3), np.uint8)
    image[10:30, 60:90] = 255  # off centre, so a wrong mirroring moves it
    return image


def test_mirrored_passes_map_back_and_agreement_sets_the_score():
    fake = BrightSquare()
    tta = TTAPredictor(fake, TTAConfig(scales=(0.67, 1.0, 1.33)))
    assert tta.sides == [64, 96, 128] and tta.passes == 6
    (pred,) = tta.predict([_image()])
    assert sorted(fake.sides_run[-6:]) == [64, 64, 96, 96, 128, 128]
    assert fake.img_size == 96  # the wrapped model is back at its own side
    np.testing.assert_allclose(pred["boxes"][0], [60, 10, 90, 30], atol=1e-3)
    assert pred["labels"].tolist() == [1, 2]
    # found by all six passes keeps its score; by one pass, 1/6 of it
    np.testing.assert_allclose(pred["scores"], [0.9, 0.6 / 6], rtol=1e-5)


def test_the_side_is_restored_when_a_pass_fails():
    fake = BrightSquare(fail_at=128)
    tta = TTAPredictor(fake, TTAConfig(scales=(1.0, 1.33)))
    with pytest.raises(RuntimeError, match="boom"):
        tta.predict([_image()])
    assert fake.img_size == 96


@pytest.fixture(scope="module")
def frame():
    rng = np.random.default_rng(0)
    image = np.clip(rng.normal(120, 10, (150, 200, 3)), 0, 255).astype(np.uint8)
    cv2.ellipse(image, (100, 80), (30, 18), 0, 0, 360, (50, 50, 50), -1)
    cv2.ellipse(image, (100, 80), (30, 18), 0, 180, 360, (230, 230, 230), 4)
    return image


def _check(pred, shape):
    boxes, scores = pred["boxes"], pred["scores"]
    assert boxes.dtype == np.float32 and boxes.shape == (len(scores), 4) and len(scores) > 0
    assert np.all(np.diff(scores) <= 0) and np.all(boxes[:, 2:] >= boxes[:, :2])
    assert boxes[:, [0, 2]].max() <= shape[1] + 1e-3 and boxes.min() >= 0


def test_shipped_model_with_tta(frame):
    predictor = load_predictor(DEFAULT_WEIGHTS, 1, 160, TTAConfig())
    assert predictor.sides == [128, 160, 192] and predictor.predictor.img_size == 160
    (pred,) = predictor.predict([frame])
    _check(pred, frame.shape)
    assert predictor.predictor.img_size == 160
    assert predictor.class_names == ["crater", "rock", "artifact"]


def test_onnx_model_with_tta_and_a_fixed_input_refused(onnx_path, onnx_static_path, frame):
    (pred,) = load_predictor(onnx_path, 1, None, TTAConfig()).predict([frame])
    _check(pred, frame.shape)
    with pytest.raises(ConfigError, match="fixed input"):
        load_predictor(onnx_static_path, 1, None, TTAConfig())


def test_detect_cli_with_tta(tmp_path, frame):
    cv2.imwrite(str(tmp_path / "a.png"), frame)
    parser = __import__("argparse").ArgumentParser()
    train_cli.register(parser.add_subparsers(dest="command"))
    out = {}
    for name, flags in (("plain", []), ("tta", ["--tta", "--tta-scales", "0.8", "1"])):
        args = parser.parse_args(["detect", str(tmp_path / "a.png"), "--out",
                                  str(tmp_path / name), "--quiet", "--gallery", "0",
                                  "--img-size", "160", *flags])
        assert args.func(args) == 0
        out[name] = json.loads((tmp_path / name / "results.json").read_text())
    assert out["tta"] and out["tta"] != out["plain"]


def test_detection_report_names_tta(tmp_path, onnx_path):
    from lunarnav_ml.cli import main
    from tests.detector_fixtures import make_coco

    gt = make_coco(tmp_path / "set", n_images=3, size=96)
    assert TTAConfig().describe() == ("test-time augmentation: 0.8 / 1 / 1.2 x the input side, "
                                      "each mirrored, fused")
    for name, flags in (("plain", []), ("tta", ["--tta"])):
        assert main(["eval", "--task", "detection", "--test-gt", str(gt), "--model",
                     str(onnx_path), "--threshold", "0.5", "--out", str(tmp_path / name),
                     "--no-progress", "--overlays", "0", *flags]) == 0
    assert "test-time augmentation" not in (tmp_path / "plain" / "report.md").read_text()
    assert TTAConfig().describe() in (tmp_path / "tta" / "report.md").read_text()


def test_no_detections_in_any_pass_fuse_to_empty_arrays():
    from lunarnav_ml.eval.tta import fuse_passes

    empty = {"boxes": np.zeros((0, 4), np.float32), "scores": np.zeros(0, np.float32),
             "labels": np.zeros(0, np.int64)}
    out = fuse_passes([empty, empty], (60, 100, 3))
    assert out["boxes"].shape == (0, 4) and out["boxes"].dtype == np.float32
    assert out["scores"].shape == (0,) and out["labels"].dtype == np.int64

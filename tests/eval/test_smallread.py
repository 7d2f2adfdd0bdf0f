"""The second, larger read of the small boxes: what it keeps, the side it restores, bad options
and real models."""

import math

import cv2
import numpy as np
import pytest

from lunarnav_ml.errors import ConfigError
from lunarnav_ml.eval.cli import load_predictor
from lunarnav_ml.eval.smallread import SmallBoxReadConfig, SmallBoxReadPredictor
from lunarnav_ml.eval.tta import TTAConfig
from lunarnav_ml.training.cli import DEFAULT_WEIGHTS
from tests.detector_fixtures import FakeSidedDetector


def _pred(rows):
    rows = np.array(rows, np.float64).reshape(-1, 6)
    return {"boxes": rows[:, :4].astype(np.float32), "scores": rows[:, 4].astype(np.float32),
            "labels": rows[:, 5].astype(np.int64)}


class TwoSides(FakeSidedDetector):
    """At its own side (96) a big crater box and a faint small one; at 192 the small one again,
    stronger and a pixel taller, a second small one, and a big box too."""

    def detect(self, images):
        if self.img_size == 96:
            rows = [[0, 0, 50, 50, 0.8, 1], [10, 10, 14, 14, 0.3, 1]]
        else:
            rows = [[0, 0, 60, 55, 0.95, 1], [10, 10, 14, 15, 0.7, 1], [70, 40, 74, 44, 0.5, 2]]
        return [_pred(rows) for _ in images]


def test_the_larger_read_adds_only_its_small_boxes_and_repeats_are_suppressed():
    fake = TwoSides()
    reader = SmallBoxReadPredictor(fake, SmallBoxReadConfig(side=192))
    image = np.zeros((60, 100, 3), np.uint8)  # 0.96 of the frame at the model's own side
    (pred,) = reader.predict([image])
    assert fake.sides_run[-2:] == [96, 192] and fake.img_size == 96
    # the 55 px box is 52.8 px high at 96: the first read's own big box stays instead
    np.testing.assert_allclose(pred["boxes"], [[0, 0, 50, 50], [10, 10, 14, 15],
                                               [70, 40, 74, 44]])
    np.testing.assert_allclose(pred["scores"], [0.8, 0.7, 0.5], rtol=1e-6)
    assert pred["labels"].tolist() == [1, 1, 2]
    assert pred["boxes"].dtype == np.float32 and pred["labels"].dtype == np.int64
    (capped,) = reader.predict([image], max_det=2)
    assert len(capped["scores"]) == 2
    # a lower cut keeps none of the second read's boxes: the first read as it was
    strict = SmallBoxReadPredictor(TwoSides(), SmallBoxReadConfig(side=192, below_px=3))
    (own,) = strict.predict([image])
    np.testing.assert_allclose(own["scores"], [0.8, 0.3], rtol=1e-6)
    assert reader.class_names == ("crater", "rock", "artifact")
    assert reader.predict([]) == []


def test_the_side_is_restored_when_the_second_read_fails():
    fake = TwoSides(fail_at=192)
    reader = SmallBoxReadPredictor(fake, SmallBoxReadConfig(side=192))
    with pytest.raises(RuntimeError, match="boom"):
        reader.predict([np.zeros((60, 100, 3), np.uint8)])
    assert fake.img_size == 96


class BrightSquareInCrop(FakeSidedDetector):
    """Finds the bright square of whatever it is given, in that image's pixels."""

    def detect(self, images):
        out = []
        for image in images:
            ys, xs = np.nonzero(image[..., 0] > 200)
            out.append(_pred([[xs.min(), ys.min(), xs.max() + 1, ys.max() + 1, 0.9, 1]]))
        return out


def test_a_band_of_rows_is_read_at_the_whole_frames_scale_and_mapped_back():
    fake = BrightSquareInCrop()
    config = SmallBoxReadConfig(side=192, below_px=30, band=(0.1, 0.6))
    assert config.describe() == "boxes under 30 px high read again at 192 px (rows 0.1-0.6)"
    reader = SmallBoxReadPredictor(fake, config)
    image = np.zeros((60, 100, 3), np.uint8)
    image[10:30, 60:90] = 255
    (pred,) = reader.predict([image])
    # rows 6-36 at 1.92 px a pixel: 57.6 -> 64 rows, 192 columns; then back at its own side
    assert fake.sides_run == [96, (64, 192)] and fake.img_size == 96
    np.testing.assert_allclose(pred["boxes"], [[60, 10, 90, 30]])  # one box: NMS took the repeat
    fake.fail_at = (64, 192)
    with pytest.raises(RuntimeError, match="boom"):
        reader.predict([image])
    assert fake.img_size == 96


@pytest.mark.parametrize("kwargs, field", [({"side": 0}, "--small-read"),
                                           ({"side": 640.0}, "--small-read"),
                                           ({"side": True}, "--small-read"),
                                           ({"side": 640, "below_px": 0.0}, "--small-read-below"),
                                           ({"side": 640, "below_px": math.nan},
                                            "--small-read-below"),
                                           ({"side": 640, "band": (0.5, 0.5)},
                                            "--small-read-band"),
                                           ({"side": 640, "band": (-0.1, 0.5)},
                                            "--small-read-band"),
                                           ({"side": 640, "band": (0.2, 1.5)},
                                            "--small-read-band"),
                                           ({"side": 640, "band": (math.nan, 0.5)},
                                            "--small-read-band"),
                                           ({"side": 640, "band": (0.1,)},
                                            "--small-read-band"),
                                           ({"side": 640, "horizon": (5.0, -5.0)},
                                            "--small-read-horizon"),
                                           ({"side": 640, "horizon": (90.0, 5.0)},
                                            "--small-read-horizon"),
                                           ({"side": 640, "horizon": (math.nan, 5.0)},
                                            "--small-read-horizon"),
                                           ({"side": 640, "band": (0.1, 0.5),
                                             "horizon": (5.0, 5.0)}, "choose one")])
def test_config_rejects_bad_values(kwargs, field):
    with pytest.raises(ConfigError, match=field):
        SmallBoxReadConfig(**kwargs)


PAPER_CAMERA = {"pitch_deg": 20.0, "fy": 512.0, "cy": 512.0}  # 1024 px, 90 deg


def test_a_band_over_the_horizon_is_read_as_rows_of_the_camera():
    config = SmallBoxReadConfig(640, horizon=(15.0, 31.3))
    assert config.describe().endswith("(15 deg over to 31.3 under the horizon)")
    rows = config.at_camera(PAPER_CAMERA, 1024)
    assert rows.horizon is None and rows.band == pytest.approx((0.15, 0.60), abs=2e-3)
    assert rows.record() == config.record() == {"side": 640, "below_px": 15.0}
    # the horizon row, 186 px over the centre: a band of 1 deg each side straddles it
    top, bottom = SmallBoxReadConfig(640, horizon=(1.0, 1.0)).at_camera(PAPER_CAMERA, 1024).band
    assert top < (512 - 512 * math.tan(math.radians(20))) / 1024 < bottom
    assert bottom - top == pytest.approx(2 * 512 / math.cos(math.radians(20)) ** 2
                                         * math.radians(1) / 1024, rel=0.01)
    # level camera, a band past the frame's edge is clipped to it
    level = {"pitch_deg": 0.0, "fy": 512.0, "cy": 512.0}
    assert SmallBoxReadConfig(640, horizon=(60.0, 80.0)).at_camera(level, 1024).band == (0, 1)
    assert SmallBoxReadConfig(640, band=(0.2, 0.3)).at_camera(level, 1024).band == (0.2, 0.3)
    with pytest.raises(ConfigError, match="no row of the frame lies in the band"):
        SmallBoxReadConfig(640, horizon=(80.0, -60.0)).at_camera(PAPER_CAMERA, 1024)


def test_a_band_over_the_horizon_is_read_at_the_readers_camera():
    fake = BrightSquareInCrop()
    reader = SmallBoxReadPredictor(fake, SmallBoxReadConfig(192, below_px=30,
                                                            horizon=(10.0, 20.0)))
    image = np.zeros((60, 100, 3), np.uint8)
    image[25:40, 60:90] = 255
    with pytest.raises(ConfigError, match="--small-read-horizon needs the camera's pitch"):
        reader.predict([image])
    assert fake.sides_run == []  # refused before any read
    reader.camera = {"pitch_deg": 0.0, "fy": 50.0, "cy": 30.0}
    top, bottom = reader.band_for(60)  # rows 30 - 50 tan 10 deg to 30 + 50 tan 20 deg
    assert (top, bottom) == pytest.approx(((30 - 50 * math.tan(math.radians(10))) / 60,
                                           (30 + 50 * math.tan(math.radians(20))) / 60))
    (pred,) = reader.predict([image])
    # rows 21-49 at 1.92 px a pixel: 53.8 -> 64 rows; the square read in both, kept once
    assert fake.sides_run == [96, (64, 192)]
    np.testing.assert_allclose(pred["boxes"], [[60, 25, 90, 40]])
    reader.camera = {"pitch_deg": 60.0, "fy": 50.0, "cy": 30.0}  # the band over the frame
    with pytest.raises(ConfigError, match="no row of the frame lies in the band"):
        reader.predict([image])


class CameraLog(SmallBoxReadPredictor):
    """Notes the camera and the number of frames of each call."""

    def predict(self, images, *args, **kwargs):
        self.calls.append((self.camera["pitch_deg"], len(images)))
        return super().predict(images, *args, **kwargs)


class Outer:
    """A wrapper around a predictor, as the box refiner's is."""

    def __init__(self, predictor):
        self.predictor = predictor

    def predict(self, images, *args, **kwargs):
        return self.predictor.predict(images, *args, **kwargs)


def _with_cameras(gt, pitches):
    import json

    data = json.loads(gt.read_text())
    for record, pitch in zip(data["images"], pitches, strict=True):
        record["camera"] = {"height_m": 1.5, "pitch_deg": pitch, "roll_deg": 0.0,
                            "fov_deg": 90.0, "baseline_m": 0.3, "fx": 48.0, "fy": 48.0,
                            "cx": 47.5, "cy": 47.5}
    gt.write_text(json.dumps(data))
    return data


def test_coco_images_are_read_in_groups_of_one_camera_each(tmp_path):
    from lunarnav_ml.errors import InputError
    from lunarnav_ml.eval.predict import predict_coco
    from lunarnav_ml.eval.smallread import small_reader
    from tests.detector_fixtures import make_coco

    gt = make_coco(tmp_path / "set", n_images=5, size=96)
    data = _with_cameras(gt, [0.0, 10.0, 0.0, 10.0, 0.0])
    for record in data["images"]:  # one bright square on each frame, to find in both reads
        image = np.full((96, 96), 120, np.uint8)
        image[50:60, 20:50] = 255
        cv2.imwrite(str(gt.parent / record["file_name"]), image)
    reader = CameraLog(BrightSquareInCrop(), SmallBoxReadConfig(192, horizon=(5.0, 40.0)))
    reader.calls = []
    assert small_reader(Outer(reader)) is reader and small_reader(BrightSquareInCrop()) is None
    results = predict_coco(Outer(reader), data, gt.parent, progress=False)
    assert reader.calls == [(0.0, 3), (10.0, 2)]
    assert [r["image_id"] for r in results] == [1, 2, 3, 4, 5]  # the dataset's order
    assert all(r["bbox"] == pytest.approx([20, 50, 30, 10]) for r in results)
    del data["images"][1]["camera"]
    with pytest.raises(InputError, match=r"set/annotations.json: image 2 \(images/left/0001.png\) has no "
                                         r"camera record"):
        predict_coco(reader, data, gt.parent, origin=str(gt), progress=False)
    data["images"][1]["camera"] = {"pitch_deg": "down"}
    with pytest.raises(InputError, match="annotations.json: image 2 .*camera: missing key"):
        predict_coco(reader, data, gt.parent, origin=str(gt), progress=False)


def test_a_side_not_larger_than_the_models_own_and_tta_together_are_refused():
    with pytest.raises(ConfigError, match="not larger than the model's own side, 96 px"):
        SmallBoxReadPredictor(TwoSides(), SmallBoxReadConfig(side=96))
    with pytest.raises(ConfigError, match="choose one"):
        load_predictor(DEFAULT_WEIGHTS, 1, 160, TTAConfig(), SmallBoxReadConfig(side=320))


@pytest.fixture(scope="module")
def frame():
    rng = np.random.default_rng(0)
    image = np.clip(rng.normal(120, 10, (300, 400, 3)), 0, 255).astype(np.uint8)
    for cx, cy, a in ((200, 160, 60), (320, 240, 9), (80, 250, 7)):  # one big, two small
        cv2.ellipse(image, (cx, cy), (a, a // 2 + 1), 0, 0, 360, (50, 50, 50), -1)
        cv2.ellipse(image, (cx, cy), (a, a // 2 + 1), 0, 180, 360, (230, 230, 230), 2)
    return image


def test_real_models_with_a_second_read(frame, onnx_path, onnx_static_path):
    predictor = load_predictor(DEFAULT_WEIGHTS, 1, 160, small_read=SmallBoxReadConfig(320))
    (pred,) = predictor.predict([frame])
    assert predictor.predictor.img_size == 160
    (own,) = predictor.predictor.predict([frame])
    assert len(pred["scores"]) > 0 and np.all(np.diff(pred["scores"]) <= 0)
    assert not np.array_equal(pred["boxes"], own["boxes"])  # the second read added boxes
    band = SmallBoxReadConfig(320, band=(0.5, 1.0))  # the two small craters' rows
    (banded,) = load_predictor(DEFAULT_WEIGHTS, 1, 160, small_read=band).predict([frame])
    assert len(banded["scores"]) > 0 and banded["boxes"][:, 3].max() <= frame.shape[0]
    (pred,) = load_predictor(onnx_path, 1, None, small_read=SmallBoxReadConfig(192)).predict(
        [frame])
    assert pred["boxes"].shape == (len(pred["scores"]), 4)
    (pred,) = load_predictor(onnx_path, 1, None, small_read=SmallBoxReadConfig(
        192, band=(0.25, 0.75))).predict([frame])  # a rectangular input through onnxruntime
    assert pred["boxes"].shape == (len(pred["scores"]), 4)
    with pytest.raises(ConfigError, match="fixed input"):
        load_predictor(onnx_static_path, 1, None, small_read=SmallBoxReadConfig(192))


def test_detection_report_names_the_second_read(tmp_path, onnx_path):
    from lunarnav_ml.cli import main
    from tests.detector_fixtures import make_coco

    gt = make_coco(tmp_path / "set", n_images=3, size=96)
    for name, flags in (("plain", []), ("read", ["--small-read", "192"])):
        assert main(["eval", "--task", "detection", "--test-gt", str(gt), "--model",
                     str(onnx_path), "--threshold", "0.5", "--out", str(tmp_path / name),
                     "--no-progress", "--overlays", "0", *flags]) == 0
    line = SmallBoxReadConfig(192).describe()
    assert line == "boxes under 15 px high read again at 192 px"
    assert line not in (tmp_path / "plain" / "report.md").read_text()
    assert line in (tmp_path / "read" / "report.md").read_text()

def test_a_band_without_the_second_read_is_refused(tmp_path, capsys):
    from lunarnav_ml.cli import main

    assert main(["eval", "--task", "detection", "--test-gt", str(tmp_path / "none.json"),
                 "--threshold", "0.5", "--out", str(tmp_path / "out"), "--small-read-band",
                 "0.2", "0.6"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--small-read-band chooses the rows of the second read: give --small-read" in err
    assert "Traceback" not in err and not (tmp_path / "out").exists()
    from argparse import Namespace

    from lunarnav_ml.eval.smallread import small_read_config

    with pytest.raises(ConfigError, match="--small-read-horizon chooses the rows"):
        small_read_config(Namespace(small_read=None, small_read_band=None,
                                    small_read_horizon=[15.0, 31.0]))
    assert small_read_config(Namespace(small_read=None)) is None


def test_a_bad_second_read_is_one_line_naming_the_option(tmp_path, onnx_path, capsys):
    from lunarnav_ml.cli import main
    from tests.detector_fixtures import make_coco

    gt = make_coco(tmp_path / "set", n_images=1, size=96)
    assert main(["eval", "--task", "detection", "--test-gt", str(gt), "--model", str(onnx_path),
                 "--threshold", "0.5", "--out", str(tmp_path / "bad"), "--small-read",
                 "32"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--small-read: 32 px is not larger" in err and "Traceback" not in err
    assert not (tmp_path / "bad").exists()


def _rows(pitch, above=5.0, below=30.0):  # _with_cameras' 96 px frames: fy 48, cy 47.5
    return ((47.5 - 48.0 * math.tan(math.radians(above + pitch))) / 96,
            (47.5 + 48.0 * math.tan(math.radians(below - pitch))) / 96)


def test_eval_reads_the_band_over_each_images_camera(tmp_path, onnx_path, capsys):
    import json

    from lunarnav_ml.cli import main
    from lunarnav_ml.eval.predict import to_coco_results
    from lunarnav_ml.utils.images import read_rgb
    from tests.detector_fixtures import make_coco

    gt = make_coco(tmp_path / "set", n_images=4, size=96)
    flags = ["--test-gt", str(gt), "--model", str(onnx_path), "--threshold", "0.5",
             "--no-progress", "--overlays", "0", "--no-box-refiner", "--threads", "1",
             "--small-read", "192", "--small-read-horizon", "5", "30"]
    assert main(["eval", *flags, "--out", str(tmp_path / "none")]) == 2  # no camera records
    err = capsys.readouterr().err.strip()
    assert "annotations.json: image 1 (images/left/0000.png) has no camera record" in err
    assert "\n" not in err and not (tmp_path / "none").exists()
    data = _with_cameras(gt, [0.0, 20.0, 0.0, 20.0])
    assert main(["eval", *flags, "--out", str(tmp_path / "read")]) == 0
    got = json.loads((tmp_path / "read" / "detections.json").read_text())
    assert "(5 deg over to 30 under the horizon)" in (tmp_path / "read" / "report.md").read_text()
    def read(pitches):  # each frame read with the band of the pitch given for it
        out = []
        for record, pitch in zip(data["images"], pitches, strict=True):
            reader = load_predictor(onnx_path, 1, None, small_read=SmallBoxReadConfig(
                192, band=_rows(pitch)))
            (pred,) = reader.predict([read_rgb(gt.parent / record["file_name"])])
            out += to_coco_results(pred, record["id"])
        return [(r["image_id"], r["category_id"], *np.round(r["bbox"], 3)) for r in out]

    got = [(r["image_id"], r["category_id"], *np.round(r["bbox"], 3)) for r in got]
    assert got == read((0.0, 20.0, 0.0, 20.0))
    assert got != read((0.0, 0.0, 0.0, 0.0))  # one camera's band for all: other boxes


def test_detect_reads_the_band_over_its_cameras_horizon(tmp_path, onnx_path, capsys):
    import json

    from lunarnav_ml.cli import main
    from tests.detector_fixtures import make_coco

    gt = make_coco(tmp_path / "set", n_images=2, size=96)
    camera = _with_cameras(gt, [20.0, 20.0])["images"][0]["camera"]
    (tmp_path / "camera.json").write_text(json.dumps({"camera": camera}))
    frames = str(gt.parent / "images" / "left")
    flags = [frames, "--weights", str(onnx_path), "--quiet", "--gallery", "0", "--threads", "1",
             "--no-box-refiner", "--small-read", "192"]
    assert main(["detect", *flags, "--small-read-horizon", "5", "30", "--camera",
                 str(tmp_path / "camera.json"), "--out", str(tmp_path / "horizon")]) == 0
    assert main(["detect", *flags, "--small-read-band", *map(str, _rows(20.0)),
                 "--out", str(tmp_path / "band")]) == 0
    got, want = (json.loads((tmp_path / name / "results.json").read_text())
                 for name in ("horizon", "band"))
    assert got and got == want
    capsys.readouterr()
    for extra, says in ((["--small-read-horizon", "5", "30"], "needs --camera FILE"),
                        (["--camera", str(tmp_path / "camera.json")],
                         "--camera is read for --small-read-horizon only"),
                        (["--small-read-horizon", "5", "30", "--camera", str(tmp_path / "no.json")],
                         "no.json")):
        assert main(["detect", *flags, *extra, "--out", str(tmp_path / "bad")]) == 2
        err = capsys.readouterr().err.strip()
        assert says in err and "Traceback" not in err and not (tmp_path / "bad").exists()

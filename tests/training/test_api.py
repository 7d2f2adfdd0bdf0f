import json

import numpy as np
import pytest
import torch

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.training.api import load_detector
from lunarnav_ml.training.checkpoint import save_slim


def test_fit_detector_writes_best_checkpoint_and_logs(trained):
    best, out = trained
    assert best.is_file() and best.suffix == ".ckpt"
    assert (out / "checkpoints" / "last.ckpt").is_file()
    metrics = (next((out / "csv").rglob("metrics.csv"))).read_text()
    assert "val/AP50" in metrics and "train/box" in metrics
    assert list((out / "tensorboard").rglob("events.out.tfevents*"))
    ckpt = torch.load(best, map_location="cpu", weights_only=False)
    anchors = np.array(ckpt["hyper_parameters"]["anchors"])
    assert anchors.shape == (3, 3, 2) and anchors.max() < 64  # k-means on 64 px boxes


def test_load_detector_and_predict(trained, tiny_coco):
    det = load_detector(trained[0])
    assert det.img_size == 64 and det.strides == (8, 16, 32)
    assert det.class_names == ["crater", "rock", "artifact"]
    images = [np.zeros((50, 80, 3), np.uint8), np.full((96, 96, 3), 120, np.uint8)]
    preds = det.predict(images, conf_thres=0.0, iou_thres=0.6)
    assert len(preds) == 2
    for pred, image in zip(preds, images):
        n = len(pred["scores"])
        assert n > 0 and pred["boxes"].shape == (n, 4) and pred["labels"].shape == (n,)
        assert pred["boxes"][:, 2].max() <= image.shape[1] and pred["boxes"].min() >= 0
        assert set(pred["labels"].tolist()) <= {1, 2, 3}
    det.set_img_size((32, 96))  # a rectangular input: boxes still in the image's pixels
    (wide,) = det.predict([np.full((40, 120, 3), 120, np.uint8)], conf_thres=0.0)
    assert len(wide["scores"]) and wide["boxes"][:, 2].max() <= 120 and wide["boxes"].min() >= 0
    for bad in ((32, 90), (0, 64), 65, (32, 64, 64), True):
        with pytest.raises(ConfigError, match="img_size"):
            det.set_img_size(bad)
    det.set_img_size(64)
    results = det.to_coco_results(preds, [5, 6])
    assert {r["image_id"] for r in results} == {5, 6}
    assert set(results[0]) == {"image_id", "category_id", "bbox", "score"}
    json.dumps(results)


def test_slim_file_round_trip(trained, tmp_path):
    det = load_detector(trained[0])
    slim = det.save(tmp_path / "nano.pt")
    again = load_detector(slim)
    image = [np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8)]
    a, b = det.predict(image, 0.01), again.predict(image, 0.01)
    np.testing.assert_allclose(a[0]["boxes"], b[0]["boxes"])
    torch.testing.assert_close(det.anchors, again.anchors)


def test_load_detector_bad_files(tmp_path):
    with pytest.raises(InputError, match="checkpoint not found"):
        load_detector(tmp_path / "missing.ckpt")
    junk = tmp_path / "junk.ckpt"
    junk.write_bytes(b"junk")
    with pytest.raises(InputError, match="junk.ckpt: not a readable checkpoint"):
        load_detector(junk)


def test_predict_rejects_bad_images(trained):
    det = load_detector(trained[0])
    with pytest.raises(InputError, match=r"images\[0\]: expected an HxWx3"):
        det.predict([np.zeros((10, 10), np.uint8)])


def test_half_precision_slim_file(trained, tmp_path):
    det = load_detector(trained[0])
    full, half = det.save(tmp_path / "full.pt"), det.save(tmp_path / "half.pt", half=True)
    assert half.stat().st_size < 0.6 * full.stat().st_size
    again = load_detector(half)
    assert all(p.dtype == torch.float32 for p in again.model.parameters())
    for key, value in det.model.state_dict().items():
        if value.is_floating_point():  # float16 keeps ~3 significant digits
            torch.testing.assert_close(again.model.state_dict()[key], value, rtol=1e-3,
                                       atol=1e-4)


def test_checkpoint_without_names_gets_the_training_defaults(trained, tmp_path):
    det = load_detector(trained[0])
    path = save_slim(tmp_path / "old.pt", {**det.config, "class_names": None}, det.model)
    assert load_detector(path).class_names == ["crater", "rock", "artifact"]


def _nano_slim(tmp_path, name="nano.pt", config=None, state=None):
    """A slim file of an untrained nano detector, with config entries or weights replaced."""
    from lunarnav_ml.models import build_model
    from lunarnav_ml.training.api import Detector

    model = build_model("nano", 3)
    det = Detector(model, 64, ["crater", "rock", "artifact"], "nano")
    path = save_slim(tmp_path / name, {**det.config, **(config or {})}, model)
    if state is not None:
        ckpt = torch.load(path, weights_only=False)
        ckpt["state_dict"] = state(ckpt["state_dict"])
        torch.save(ckpt, path)
    return path


def test_load_detector_names_a_bad_preset_in_one_line(tmp_path):
    path = _nano_slim(tmp_path, config={"preset": "huge"})
    with pytest.raises(InputError, match=r"nano.pt: preset: unknown model preset 'huge' \(known"):
        load_detector(path)


def test_load_detector_rejects_non_finite_weights(tmp_path):
    def poison(state):
        state["head.preds.1.weight"][0, 0, 0, 0] = float("nan")
        state["head.preds.2.bias"][0] = float("inf")
        return state

    assert load_detector(_nano_slim(tmp_path)).img_size == 64
    path = _nano_slim(tmp_path, "nan.pt", state=poison)
    with pytest.raises(InputError, match=r"nan.pt: weights hold NaN or infinite values "
                                         r"\(first in head.preds.1.weight\)"):
        load_detector(path)


def test_load_detector_rejects_class_names_that_miss_classes(tmp_path):
    path = _nano_slim(tmp_path, config={"class_names": ["crater"]})
    with pytest.raises(InputError, match=r"nano.pt: 1 class_names \['crater'\] for "
                                         "num_classes 3"):
        load_detector(path)


def test_load_detector_names_mismatched_weights_in_one_line(tmp_path):
    def reshape(state):
        state["backbone.stem.0.weight"] = torch.zeros(3, 3)
        del state["head.preds.0.bias"]
        state["extra.weight"] = torch.zeros(1)
        return state

    with pytest.raises(InputError) as err:
        load_detector(_nano_slim(tmp_path, state=reshape))
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{tmp_path / 'nano.pt'}: weights do not")
    assert "missing head.preds.0.bias; unexpected extra.weight; other shape: " \
           "backbone.stem.0.weight [3, 3] in the file, [" in message


def test_average_detectors_is_the_mean_of_weights_and_statistics(trained, tmp_path):
    from lunarnav_ml.training.api import average_detectors

    det = load_detector(trained[0])
    other = load_detector(trained[0])
    with torch.no_grad():
        for key, value in other.model.state_dict().items():
            if value.is_floating_point() and "anchors" not in key:
                value.mul_(3.0)  # weights, biases and BatchNorm running statistics
    second = other.save(tmp_path / "x3.pt")
    mean = average_detectors([trained[0], second])
    assert mean.preset == det.preset and mean.img_size == det.img_size
    a, m = det.model.state_dict(), mean.model.state_dict()
    for key, value in a.items():
        if value.is_floating_point() and "anchors" not in key:
            torch.testing.assert_close(m[key], 2.0 * value)
    torch.testing.assert_close(mean.anchors, det.anchors)
    # the average of one file with itself is that file
    same = average_detectors([trained[0], trained[0]])
    image = [np.random.default_rng(1).integers(0, 255, (64, 64, 3), dtype=np.uint8)]
    np.testing.assert_allclose(same.predict(image, 0.01)[0]["boxes"],
                               det.predict(image, 0.01)[0]["boxes"], rtol=1e-5, atol=1e-4)


def test_average_detectors_refuses_other_architectures(trained, tmp_path):
    from lunarnav_ml.errors import ConfigError
    from lunarnav_ml.training.api import average_detectors

    with pytest.raises(ConfigError, match="two or more"):
        average_detectors([trained[0]])
    det = load_detector(trained[0])
    det.model.anchors.mul_(2.0)
    moved = det.save(tmp_path / "moved.pt")
    with pytest.raises(InputError, match="moved.pt: its anchors differ"):
        average_detectors([trained[0], moved])
    with pytest.raises(InputError, match="missing.pt"):
        average_detectors([trained[0], tmp_path / "missing.pt"])

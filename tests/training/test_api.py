import json

import numpy as np
import pytest
import torch

from lunarnav_ml.errors import InputError
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

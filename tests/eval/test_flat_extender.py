"""benchmarks/flat_extender.py: fragments of flat labels, the extender's crop, a trained extender
that grows fragments towards the whole box, and its candidates in the replay."""

import json
from argparse import Namespace

import cv2
import numpy as np

from tests.bench_scripts import load_script

ext = load_script("flat_extender")
replay = load_script("replay_candidates")


def test_fragments_lie_along_their_label():
    rng = np.random.default_rng(0)
    labels = np.array([[100.0, 50.0, 300.0, 12.0], [10.0, 200.0, 160.0, 8.0]])
    frag, lab = ext.fragments(labels, 50, rng)
    assert frag.shape == lab.shape == (100, 4)
    np.testing.assert_array_equal(lab[:50], np.tile(labels[0], (50, 1)))
    frac = frag[:, 2] / lab[:, 2]
    assert frac.min() >= 0.35 - 1e-9 and frac.max() <= 1.0 + 1e-9
    assert np.isclose(frac, 1.0).sum() >= 10  # about a quarter whole
    assert (frag[:, 0] >= lab[:, 0] - 1e-9).all()
    assert (frag[:, 0] + frag[:, 2] <= lab[:, 0] + lab[:, 2] + 1e-9).all()
    assert (frag[:, 3] > 0).all()
    again, _ = ext.fragments(labels, 50, np.random.default_rng(0))
    np.testing.assert_array_equal(frag, again)


def test_extender_crop_holds_span_widths_around_the_box():
    f = ext.extender_frames(np.array([[100.0, 50.0, 40.0, 5.0]]))
    x0, y0, w, h = f[0]
    assert w == ext.SPAN * 40 and np.isclose(x0 + w / 2, 120) and np.isclose(y0 + h / 2, 52.5)
    assert np.isclose(h, 15 + 0.06 * w)


def _flat_set(root, n=48, seed=0):
    """Frames 384 x 128 with one or two dark edge-on rims (ellipses 10-16 times wider than
    high), each labelled by its box."""
    rng = np.random.default_rng(seed)
    (root / "images").mkdir(parents=True)
    images, anns = [], []
    for i in range(n):
        img = np.clip(rng.normal(150, 10, (128, 384)), 0, 255).astype(np.uint8)
        for j in range(1 + i % 2):
            h = float(rng.uniform(8, 12))
            w = h * float(rng.uniform(10, 16))
            cx, cy = float(rng.uniform(w / 2 + 5, 379 - w / 2)), 30.0 + 60 * j
            cv2.ellipse(img, (round(cx), round(cy)), (round(w / 2), round(h / 2)), 0, 0, 360,
                        40, -1)
            anns.append({"id": len(anns) + 1, "image_id": i + 1, "category_id": 1,
                         "bbox": [cx - w / 2, cy - h / 2, w, h], "area": w * h, "iscrowd": 0})
        name = f"images/{i:03d}.png"
        cv2.imwrite(str(root / name), img)
        images.append({"id": i + 1, "file_name": name, "width": 384, "height": 128})
    cats = [{"id": 1, "name": "crater"}]
    (root / "annotations.json").write_text(json.dumps({"images": images, "annotations": anns,
                                                       "categories": cats}))
    return root / "annotations.json"


def _iou(a, b):
    iw = max(0.0, min(a[0] + a[2], b[0] + b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[1] + a[3], b[1] + b[3]) - max(a[1], b[1]))
    return iw * ih / (a[2] * a[3] + b[2] * b[3] - iw * ih)


def test_a_trained_extender_grows_fragments_to_the_rim(tmp_path, capsys):
    gt = _flat_set(tmp_path / "train")
    out = tmp_path / "ext.pt"
    assert ext.main([str(gt), "--out", str(out), "--per-label", "16", "--epochs", "8",
                     "--batch", "64", "--lr", "3e-3", "--threads", "1"]) == 0
    assert "held-out mean |edge error|" in capsys.readouterr().out
    extender = ext.FlatExtender(out)
    coco = json.loads(_flat_set(tmp_path / "held", n=12, seed=1).read_text())
    before, after = [], []
    rng = np.random.default_rng(2)
    for im in coco["images"]:
        gray = cv2.imread(str(tmp_path / "held" / im["file_name"]), cv2.IMREAD_GRAYSCALE)
        labels = np.array([a["bbox"] for a in coco["annotations"]
                           if a["image_id"] == im["id"]])
        frag, lab = ext.fragments(labels, 4, rng)
        grown = extender(gray, frag)
        before += [_iou(f, t) for f, t in zip(frag, lab, strict=True)]
        after += [_iou(g, t) for g, t in zip(grown, lab, strict=True)]
    assert np.mean(after) > np.mean(before) + 0.1, (np.mean(before), np.mean(after))


def test_no_flat_label_is_a_one_line_error(tmp_path, capsys):
    (tmp_path / "images").mkdir()
    cv2.imwrite(str(tmp_path / "images" / "a.png"), np.zeros((64, 64), np.uint8))
    (tmp_path / "annotations.json").write_text(json.dumps({
        "images": [{"id": 1, "file_name": "images/a.png", "width": 64, "height": 64}],
        "annotations": [{"id": 1, "image_id": 1, "category_id": 1, "bbox": [5, 5, 20, 20],
                         "area": 400, "iscrowd": 0}],
        "categories": [{"id": 1, "name": "crater"}]}))
    out = tmp_path / "ext.pt"
    assert ext.main([str(tmp_path / "annotations.json"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]  # after the progress bar
    assert err.startswith("flat_extender: error:") and "wider than high" in err
    assert not out.exists()


def test_not_an_extender_file_is_named(tmp_path):
    import pytest
    import torch

    from lunarnav_ml.errors import InputError

    torch.save({"something": 1}, tmp_path / "x.pt")
    with pytest.raises(InputError, match="x.pt: not a flat extender"):
        ext.FlatExtender(tmp_path / "x.pt")


def test_replay_adds_each_flat_box_extended():
    pred = {"boxes": np.array([[100, 50, 160, 58], [10, 10, 30, 30], [200, 50, 260, 58]],
                              np.float64),
            "scores": np.array([0.9, 0.95, 0.5], np.float32), "labels": np.array([1, 1, 2])}
    args = Namespace(candidates="extend", flat=6.0, floor=0.05, top=30, factor=0.5)
    seen = []

    def extend(xywh):
        seen.append(xywh.copy())
        return xywh + np.array([-20.0, 0.0, 40.0, 1.0])

    out = replay.candidates(pred, (120, 240), args, extend)
    np.testing.assert_allclose(seen[0], [[100, 50, 60, 8]])  # the flat crater box only
    np.testing.assert_allclose(out["boxes"][3:], [[80, 50, 180, 59]])
    np.testing.assert_allclose(out["scores"][3:], [0.45])
    assert out["labels"][3:].tolist() == [1]

"""The crater-box refiner: crop geometry, the shipped file, errors, training, export and CLI."""

import json

import cv2
import numpy as np
import onnx
import pytest
import torch

from lunarnav_ml.cli import main
from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.geometry._checks import as_image
from lunarnav_ml.geometry.boxrefine import (
    CROP_H,
    CROP_W,
    DEFAULT_BOX_REFINER,
    BoxRefinedDetector,
    BoxRefiner,
    crop_frames,
    cut_crops,
    decode_edges,
    encode_edges,
    normalize_crops,
)
from lunarnav_ml.geometry.report import geometry_report
from lunarnav_ml.training.box_refiner import (
    BoxRefinerConfig,
    BoxRefinerNet,
    box_iou,
    build_crops,
    export_box_refiner,
    jitter_boxes,
    train_box_refiner,
)
from tests.geometry.test_report import _write_dataset


def test_crop_frame_encode_decode():
    rng = np.random.default_rng(0)
    boxes = np.column_stack([rng.uniform(0, 900, 20), rng.uniform(0, 900, 20),
                             rng.uniform(12, 400, 20), rng.uniform(6, 80, 20)])
    frames = crop_frames(boxes)
    edges = encode_edges(boxes, frames)
    np.testing.assert_allclose(edges[:, [0, 2]], np.tile([1 / 6, 5 / 6], (20, 1)), atol=1e-6)
    assert (edges[:, 1] > 0).all() and (edges[:, 3] < 1).all()  # vertical room around the box
    np.testing.assert_allclose(decode_edges(edges, frames), boxes, rtol=1e-5, atol=1e-3)


def test_cut_crops_put_the_box_in_the_middle():
    img = np.zeros((300, 400), np.uint8)
    img[100:130, 120:240] = 200  # a bright box 120 x 30 px
    crop = cut_crops(img, crop_frames(np.array([[120.0, 100.0, 120.0, 30.0]])))[0]
    assert crop.shape == (CROP_H, CROP_W)
    cols = np.flatnonzero(crop.max(axis=0) > 100)
    assert abs(cols[0] - CROP_W / 6) <= 1.5 and abs(cols[-1] + 1 - 5 * CROP_W / 6) <= 1.5
    x = normalize_crops(crop[None])
    assert x.shape == (1, 1, CROP_H, CROP_W) and abs(float(x.mean())) < 1e-4


@pytest.fixture(scope="module")
def shipped():
    return BoxRefiner()


@pytest.fixture(scope="module")
def renders(tmp_path_factory):
    """Two frames of the paper-stereo grid at 1024 px (left views only), seeds no training
    used."""
    from lunarnav_ml.synth.generate import generate_dataset

    root = tmp_path_factory.mktemp("boxref_renders")
    path = generate_dataset(root, seed=77000001, image_size=1024, protocol="paper-stereo",
                            items=[700, 1500], progress=False, stereo=False)
    return path


def test_shipped_refiner_moves_jittered_boxes_onto_the_craters(shipped, renders):
    """The shipped net on renders it never saw: boxes jittered by 15 % of their side come
    back nearer the labelled ones on average (a net that ignores the image, reads it mirrored
    or decodes the edges wrongly does not)."""
    import cv2

    coco = json.loads(renders.read_text())
    rng = np.random.default_rng(0)
    before, after = [], []
    for im in coco["images"]:
        labels = np.array([a["bbox"] for a in coco["annotations"]
                           if a["image_id"] == im["id"] and a["category_id"] == 1
                           and not a.get("ignore") and a["bbox"][2] >= 12 and a["bbox"][3] >= 6])
        truth = np.repeat(labels, 8, axis=0)
        jittered = jitter_boxes(truth, 0.15, rng)
        refined = shipped(cv2.imread(str(renders.parent / im["file_name"]), 0), jittered)
        assert refined.shape == truth.shape and np.isfinite(refined).all()
        before += list(np.diag(box_iou(jittered, truth)))
        after += list(np.diag(box_iou(refined, truth)))
    assert len(before) >= 40 and np.mean(after) > np.mean(before) + 0.02, (np.mean(before),
                                                                          np.mean(after))


def test_refiner_inputs_and_results(shipped):
    gray = np.zeros((64, 96), np.uint8)
    assert shipped(gray, np.zeros((0, 4))).shape == (0, 4)
    for bad in (np.array([[1.0, 2.0, np.nan, 4.0]]), np.array([[1.0, 2.0, -3.0, 4.0]]),
                np.ones((2, 3))):
        with pytest.raises(InputError, match="boxes: expected finite"):
            shipped(gray, bad)
    for image in (np.zeros((64, 96, 3), np.uint8), None):
        with pytest.raises(InputError, match="image: expected a uint8 gray image"):
            shipped(image, np.array([[10.0, 10.0, 40.0, 10.0]]))
    results = [{"image_id": 1, "category_id": 2, "bbox": [1, 2, 3, 4], "score": 0.9},
               {"image_id": 1, "category_id": 1, "bbox": [10.0, 10.0, 40.0, 10.0], "score": 0.8}]
    out = shipped.refine_results(gray, results)
    assert out[0] is results[0] and out[1]["score"] == 0.8 and len(out[1]["bbox"]) == 4
    assert results[1]["bbox"] == [10.0, 10.0, 40.0, 10.0]  # the input is not changed


class _FixedDetector:
    """Gives the same detections for every image (xyxy, highest score first)."""

    img_size = 384

    def __init__(self, boxes, scores, labels):
        self.out = {"boxes": np.asarray(boxes, np.float32),
                    "scores": np.asarray(scores, np.float32),
                    "labels": np.asarray(labels, np.int64)}
        self.calls = []

    def predict(self, images, conf_thres=0.001, iou_thres=0.6, max_det=300):
        self.calls.append((conf_thres, iou_thres, max_det))
        return [dict(self.out) for _ in images]


def test_refined_detector_moves_crater_boxes_and_suppresses_their_repeats(shipped, renders):
    """Crater boxes, and only those, are refined on the image they came from; two crater boxes
    that land on one rim count once (per-class NMS at the call's IoU), a rock box in the same
    place stays, and the results carry the mark that stops a second refinement."""
    import cv2

    from lunarnav_ml.eval.predict import to_coco_results

    coco = json.loads(renders.read_text())
    im = coco["images"][0]
    label = max((a["bbox"] for a in coco["annotations"] if a["image_id"] == im["id"]
                 and a["category_id"] == 1 and not a.get("ignore")), key=lambda b: b[2])
    gray = cv2.imread(str(renders.parent / im["file_name"]), 0)
    x, y, w, h = label
    near = [x + 0.08 * w, y - 0.1 * h, x + 1.02 * w, y + 0.95 * h]  # a detector's box, off
    rock = [5.0, 5.0, 40.0, 30.0]
    inner = _FixedDetector([near, near, rock], [0.9, 0.8, 0.7], [1, 1, 2])
    det = BoxRefinedDetector(inner, shipped)
    assert det.img_size == 384  # the wrapped detector's attributes
    rgb = np.repeat(gray[:, :, None], 3, axis=2)
    out = det.predict([rgb], conf_thres=0.01, iou_thres=0.5)[0]
    assert inner.calls == [(pytest.approx(0.01 ** 2), 0.5, 300)]  # rescored: conf squared
    # the shipped file estimates the box's IoU with its crater: the score is sqrt(score x that)
    assert shipped.has_quality
    quality = shipped.refine_scored(gray, np.array([[near[0], near[1], near[2] - near[0],
                                                     near[3] - near[1]]]))[1][0]
    assert 0.3 < quality <= 1.0
    assert out["labels"].tolist() == [1, 2]
    assert out["scores"].tolist() == pytest.approx([np.sqrt(0.9 * quality), 0.7], rel=1e-5)
    assert out["box_refined"].tolist() == [True, False]
    assert out["boxes"][1].tolist() == rock
    truth = np.array([[x, y, w, h]])

    def xywh(b):
        return np.array([[b[0], b[1], b[2] - b[0], b[3] - b[1]]])

    assert box_iou(xywh(out["boxes"][0]), truth)[0, 0] > box_iou(xywh(near), truth)[0, 0] + 0.05
    # the same as the refiner called on the gray image
    np.testing.assert_allclose(xywh(out["boxes"][0]), shipped(gray, xywh(near)), atol=1e-3)
    results = to_coco_results(out, 7)
    assert results[0]["box_refined"] is True and "box_refined" not in results[1]
    again = shipped.refine_results(gray, results)
    assert again[0] is results[0]  # marked: not refined a second time
    # no crater: the detections as they were, NMS not run again
    only_rock = BoxRefinedDetector(_FixedDetector([rock, rock], [0.9, 0.8], [2, 2]), shipped)
    out = only_rock.predict([rgb])[0]
    assert len(out["boxes"]) == 2 and not out["box_refined"].any()
    assert only_rock.predict([]) == []


def test_colour_frames_reach_the_refiner_as_its_training_read_them(tmp_path):
    """The refiners trained on cv2.imread(..., IMREAD_GRAYSCALE); an RGB frame (read_rgb) must
    reach them as the same gray (the luma), not the channels' mean, and a gray frame replicated
    to three channels as it was."""
    rng = np.random.default_rng(3)
    bgr = rng.integers(0, 256, (40, 50, 3), dtype=np.uint8)
    bgr[..., 0] //= 4  # unequal channels: the mean and the luma differ
    path = tmp_path / "frame.png"
    cv2.imwrite(str(path), bgr)
    from lunarnav_ml.utils.images import read_rgb

    gray = as_image("image", read_rgb(path)).astype(int)
    trained_on = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE).astype(int)
    assert np.abs(gray - trained_on).max() <= 1  # libpng's fixed-point rounding
    assert np.abs(bgr.mean(axis=2) - trained_on).mean() > 10
    plain = bgr[..., 1]
    assert np.array_equal(as_image("image", np.repeat(plain[..., None], 3, axis=2)), plain)
    floats = as_image("image", read_rgb(path) / 255.0)
    assert np.abs(floats.astype(int) - trained_on).max() <= 1


def test_refined_boxes_are_clipped_to_the_image():
    """A refiner that pushes a box past the frame's edges: the box ends at the edges, as the
    detector's boxes and the labels do."""

    class Outward:
        def refine_scored(self, gray, xywh):
            return xywh + np.array([-50.0, -50.0, 100.0, 100.0]), None

    det = BoxRefinedDetector(_FixedDetector([[10.0, 20.0, 60.0, 40.0]], [0.9], [1]), Outward())
    out = det.predict([np.zeros((80, 120, 3), np.uint8)])[0]
    assert out["boxes"].tolist() == [[0.0, 0.0, 110.0, 80.0]]


def test_quality_rescores_crater_boxes_and_orders_by_score():
    """A refiner with a quality output: each crater scores sqrt(score x quality) and the
    output is by score again; a rock keeps its score."""

    class Scoring:
        has_quality = True

        def refine_scored(self, gray, xywh):
            return xywh, np.array([0.1, 0.9], np.float32)

    boxes = [[10.0, 10.0, 50.0, 30.0], [100.0, 10.0, 150.0, 30.0], [10.0, 60.0, 40.0, 80.0],
             [199.0, 50.0, 199.0, 70.0]]  # the last one empty (clipped at the right edge)
    inner = _FixedDetector(boxes, [0.9, 0.5, 0.4, 0.2], [1, 1, 2, 1])
    det = BoxRefinedDetector(inner, Scoring())
    out = det.predict([np.zeros((100, 200, 3), np.uint8)])[0]
    assert out["scores"].tolist() == pytest.approx([np.sqrt(0.45), 0.4, np.sqrt(0.09), 0.2])
    assert out["labels"].tolist() == [1, 2, 1, 1]
    assert out["boxes"].tolist() == [boxes[1], boxes[2], boxes[0], boxes[3]]
    assert out["box_refined"].tolist() == [True, False, True, False]
    # a threshold holds for the final scores; the detector ran at its square
    out = det.predict([np.zeros((100, 200, 3), np.uint8)], conf_thres=0.5)[0]
    assert inner.calls[-1][0] == pytest.approx(0.25)
    assert out["scores"].tolist() == pytest.approx([np.sqrt(0.45)])
    assert out["labels"].tolist() == [1] and out["box_refined"].tolist() == [True]


def _export(tmp_path, name, quality=False, **props):
    torch.manual_seed(0)
    return export_box_refiner(BoxRefinerNet(quality=quality), tmp_path / name, props)


def test_refiner_file_errors(tmp_path):
    with pytest.raises(InputError, match="nope.onnx: box refiner not found"):
        BoxRefiner(tmp_path / "nope.onnx")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"\x08\x01garbage")
    with pytest.raises(InputError, match="bad.onnx: not a loadable ONNX model"):
        BoxRefiner(bad)
    path = _export(tmp_path, "foreign.onnx")
    model = onnx.load(str(path))
    del model.metadata_props[:]
    onnx.save(model, str(path))
    with pytest.raises(InputError, match="foreign.onnx: not a box refiner"):
        BoxRefiner(path)
    path = _export(tmp_path, "crop.onnx", **{"lunarnav.crop": "64,64"})
    with pytest.raises(InputError, match="crop.onnx: metadata lunarnav.crop"):
        BoxRefiner(path)
    with pytest.raises(InputError, match="not a box refiner"):
        BoxRefiner(DEFAULT_BOX_REFINER.with_name("disparity_refiner.onnx"))


def test_export_matches_torch(tmp_path):
    ref = BoxRefiner(_export(tmp_path, "b.onnx"))
    torch.manual_seed(0)
    net = BoxRefinerNet().eval()  # the same seed as _export: the same weights
    rng = np.random.default_rng(2)
    gray = rng.integers(0, 256, (200, 300)).astype(np.uint8)
    boxes = np.array([[50.0, 60.0, 120.0, 25.0], [10.0, 150.0, 40.0, 12.0]])
    frames = crop_frames(boxes)
    with torch.no_grad():
        edges = net(torch.from_numpy(normalize_crops(cut_crops(gray, frames)))).numpy()
    want = decode_edges(edges, frames)
    ok = (want[:, 2] >= 2) & (want[:, 3] >= 1)  # others are kept as given
    np.testing.assert_allclose(ref(gray, boxes)[ok], want[ok], rtol=1e-4, atol=1e-3)
    assert not ref.has_quality and ref.refine_scored(gray, boxes)[1] is None


def test_export_with_quality_matches_torch(tmp_path):
    ref = BoxRefiner(_export(tmp_path, "q.onnx", quality=True))
    assert ref.has_quality
    torch.manual_seed(0)
    net = BoxRefinerNet(quality=True).eval()
    rng = np.random.default_rng(3)
    gray = rng.integers(0, 256, (200, 300)).astype(np.uint8)
    boxes = np.array([[50.0, 60.0, 120.0, 25.0], [10.0, 150.0, 40.0, 12.0]])
    with torch.no_grad():
        out = net(torch.from_numpy(normalize_crops(cut_crops(gray, crop_frames(boxes))))).numpy()
    refined, quality = ref.refine_scored(gray, boxes)
    assert quality.shape == (2,) and quality.dtype == np.float32
    np.testing.assert_allclose(quality, 1 / (1 + np.exp(-out[:, 4])), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(ref(gray, boxes), refined)  # the lift reads the same edges


def test_edges_from_another_refiner(tmp_path):
    """One file: another refiner's edges, bit for bit (the lift moves boxes as with it), and the
    quality net's quality; a net without quality, or a file that is no refiner, is refused."""
    edges_file = _export(tmp_path, "edges.onnx")
    torch.manual_seed(1)
    qnet = BoxRefinerNet(quality=True)
    both = export_box_refiner(qnet, tmp_path / "both.onnx", edges_from=edges_file)
    alone = export_box_refiner(qnet, tmp_path / "alone.onnx")
    rng = np.random.default_rng(4)
    gray = rng.integers(0, 256, (200, 300)).astype(np.uint8)
    boxes = np.array([[50.0, 60.0, 120.0, 25.0], [10.0, 150.0, 40.0, 12.0], [200, 20, 60, 30]])
    crops = {"crops": normalize_crops(cut_crops(gray, crop_frames(boxes)))}

    def raw(path):  # the edges as the net gives them (untrained nets' boxes are kept as given)
        return BoxRefiner(path).session.run(None, crops)

    merged, base, own = raw(both), raw(edges_file), raw(alone)
    assert np.array_equal(merged[0], base[0]) and not np.array_equal(merged[0], own[0])
    np.testing.assert_array_equal(merged[1], own[1])
    assert BoxRefiner(both).has_quality
    meta = onnx.load(str(both)).metadata_props
    assert json.loads(next(p.value for p in meta if p.key == "lunarnav.edges_from"))[
        "file"] == "edges.onnx"
    with pytest.raises(InputError, match="no quality output"):
        export_box_refiner(BoxRefinerNet(), tmp_path / "x.onnx", edges_from=edges_file)
    with pytest.raises(InputError, match="not a box refiner"):
        export_box_refiner(qnet, tmp_path / "x.onnx",
                           edges_from=DEFAULT_BOX_REFINER.with_name("disparity_refiner.onnx"))
    assert not (tmp_path / "x.onnx").exists()


@pytest.fixture(scope="module")
def labelled_set(tmp_path_factory, crater_scene):
    root = tmp_path_factory.mktemp("boxref_ds")
    _write_dataset(root, crater_scene)
    x, y, w, h = (float(v) for v in crater_scene.box)
    dets = [{"image_id": 1, "category_id": 1, "bbox": [x + 0.1 * w, y, 0.8 * w, h], "score": 0.9},
            {"image_id": 1, "category_id": 1, "bbox": [0.0, 0.0, 20.0, 8.0], "score": 0.9},
            {"image_id": 1, "category_id": 1, "bbox": [x, y, w, h], "score": 0.01}]
    (root / "detections.json").write_text(json.dumps(dets))
    return root


SMALL = {"label_jitters": 24, "det_jitters": 24, "batch": 8, "epochs": 6, "lr": 3e-3,
         "val_fraction": 0.1}


def test_crops_from_labels_and_detections(labelled_set):
    cfg = BoxRefinerConfig(**SMALL)
    labels_only = build_crops([labelled_set], [None], cfg, progress=False)
    both = build_crops([labelled_set], [labelled_set / "detections.json"], cfg, progress=False)
    n_labels = len(labels_only) // cfg.label_jitters  # the 1 m crater is a label too
    # the detection overlapping the crater (its own box and its jitters) adds crops; the one
    # off the crater and the one under the score floor do not
    assert len(both) == len(labels_only) + 1 + cfg.det_jitters and n_labels == 2
    assert both.crops.shape[1:] == (CROP_H, CROP_W) and both.edges.shape == (len(both), 4)
    again = build_crops([labelled_set], [labelled_set / "detections.json"], cfg, progress=False)
    assert np.array_equal(both.crops, again.crops) and np.array_equal(both.edges, again.edges)
    # a set's weight in the mix: that many times its label crops and its detections' crops
    twice = build_crops([labelled_set], [labelled_set / "detections.json"], cfg, progress=False,
                        repeats=[2])
    assert len(twice) == 2 * len(both)
    for bad in ([0], [1, 1], [1.5]):
        with pytest.raises(ConfigError, match="repeats: one positive integer per set"):
            build_crops([labelled_set], [None], cfg, progress=False, repeats=bad)


def test_training_learns_and_is_seeded(labelled_set):
    cfg = BoxRefinerConfig(**SMALL)
    crops = build_crops([labelled_set], [labelled_set / "detections.json"], cfg, progress=False)
    net, report = train_box_refiner(crops, cfg, log=None)
    assert report.n_val >= 1 and report.steps > 0
    with torch.no_grad():
        fitted = net(torch.from_numpy(normalize_crops(crops.crops))).numpy()
    fit_err = np.abs(fitted - crops.edges)[:, [0, 2]].mean()
    input_err = np.abs(np.array([1 / 6, 5 / 6]) - crops.edges[:, [0, 2]]).mean()
    assert fit_err < 0.8 * input_err  # it learns where the edges lie (a broken target does not)
    net2, _ = train_box_refiner(crops, cfg, log=None)
    for a, b in zip(net.parameters(), net2.parameters(), strict=True):
        assert torch.equal(a, b)


def test_quality_crops_and_training(labelled_set):
    """With a quality weight the unmatched detection (off every label) adds a crop for the
    quality output only, every crop's target is its box's best IoU with a label, and the
    trained output ranks the crater's crops above the one off it."""
    cfg = BoxRefinerConfig(**SMALL, quality=1.0)
    dets = labelled_set / "detections.json"
    plain = build_crops([labelled_set], [dets], BoxRefinerConfig(**SMALL), progress=False)
    crops = build_crops([labelled_set], [dets], cfg, progress=False)
    assert len(crops) == len(plain) + 1 and crops.quality.shape == (len(crops),)
    off = ~np.isfinite(crops.edges[:, 0])
    assert off.sum() == 1 and crops.quality[off][0] < 0.3
    assert (crops.quality[~off] > 0.3).mean() > 0.9  # jittered labels and matched detections
    assert len(build_crops([labelled_set], [dets], cfg, progress=False, repeats=[3])) \
        == 3 * len(crops)
    net, report = train_box_refiner(crops, cfg, log=None)
    assert report.quality_corr is not None and np.isfinite(report.refined_l1)
    with torch.no_grad():
        q = torch.sigmoid(net(torch.from_numpy(normalize_crops(crops.crops)))[:, 4]).numpy()
    assert q[off][0] < np.median(q[~off])
    with pytest.raises(InputError, match="no quality targets"):
        train_box_refiner(plain, cfg, log=None)


def test_config_and_data_checks(labelled_set, tmp_path):
    for bad in ({"epochs": 0}, {"label_jitter": 0.7}, {"det_jitters": -1}, {"lr": 0.0},
                {"val_fraction": 0.6}, {"quality": -1.0}, {"quality": float("nan")}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            BoxRefinerConfig(**bad)
    with pytest.raises(ConfigError, match="one results file"):
        build_crops([labelled_set], [], progress=False)
    (tmp_path / "bad.json").write_text(json.dumps(
        [{"image_id": 1, "category_id": 1, "bbox": [1, 2, "x", 4], "score": 0.5}]))
    with pytest.raises(InputError, match="bad.json: result 0: bbox"):
        build_crops([labelled_set], [tmp_path / "bad.json"], progress=False)
    crops = build_crops([labelled_set], [None], BoxRefinerConfig(label_jitters=1),
                        progress=False)
    with pytest.raises(InputError, match="training crops: need at least"):
        train_box_refiner(crops, BoxRefinerConfig(), log=None)


def test_cli_train_then_eval_and_errors(labelled_set, tmp_path, capsys):
    out = tmp_path / "b.onnx"
    dets = labelled_set / "detections.json"
    assert main(["train-box-refiner", str(labelled_set), "--detections", str(dets),
                 "--out", str(out), "--epochs", "1", "--batch", "4", "--label-jitters", "8",
                 "--quiet", "--threads", "1"]) == 0
    assert "held-out mean |edge error|" in capsys.readouterr().out
    assert not BoxRefiner(out).has_quality
    assert main(["train-box-refiner", str(labelled_set), "--detections", str(dets),
                 "--out", str(tmp_path / "q.onnx"), "--epochs", "1", "--batch", "4",
                 "--label-jitters", "8", "--quality", "0.1", "--quiet", "--threads", "1"]) == 0
    assert "quality vs IoU r = " in capsys.readouterr().out
    assert BoxRefiner(tmp_path / "q.onnx").has_quality
    assert main(["train-box-refiner", str(labelled_set), "--detections", str(dets),
                 "--out", str(tmp_path / "qb.onnx"), "--epochs", "1", "--batch", "4",
                 "--label-jitters", "8", "--quality", "0.1", "--edges-from", str(out),
                 "--quiet", "--threads", "1"]) == 0
    gray = np.full((100, 200), 90, np.uint8)
    box = np.array([[40.0, 30.0, 60.0, 20.0]])
    assert np.array_equal(BoxRefiner(tmp_path / "qb.onnx")(gray, box), BoxRefiner(out)(gray, box))
    for extra, want in ((["--box-refiner", str(out)], str(out)), ([], str(DEFAULT_BOX_REFINER)),
                        (["--box-refiner"], str(DEFAULT_BOX_REFINER)),
                        (["--no-box-refiner"], None)):  # on by default
        assert main(["eval", "--task", "geometry", "--gt", str(labelled_set), "--test-results",
                     str(dets), *extra, "--out", str(tmp_path / "g"), "--no-progress"]) == 0
        metrics = json.loads((tmp_path / "g" / "geometry_metrics.json").read_text())
        assert metrics["settings"]["box_refiner"] == want
    assert main(["eval", "--task", "geometry", "--gt", str(labelled_set), "--out",
                 str(tmp_path / "g"), "--no-progress"]) == 0  # labelled boxes: never refined
    assert json.loads((tmp_path / "g" / "geometry_metrics.json").read_text())[
        "settings"]["box_refiner"] is None
    capsys.readouterr()
    bad = tmp_path / "bad.onnx"
    assert main(["train-box-refiner", str(labelled_set), "--detections", str(dets), "none",
                 "--out", str(bad), "--quiet"]) == 2
    assert main(["train-box-refiner", str(labelled_set), "--detections",
                 str(tmp_path / "missing.json"), "--out", str(bad), "--quiet"]) == 2
    assert main(["train-box-refiner", str(labelled_set), "--repeats", "1", "2",
                 "--out", str(bad), "--quiet"]) == 2
    assert main(["train-box-refiner", str(labelled_set), "--edges-from", str(out),
                 "--out", str(bad), "--quiet"]) == 2
    assert main(["train-box-refiner", str(labelled_set), "--quality", "0.1", "--edges-from",
                 str(tmp_path / "none.onnx"), "--out", str(bad), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 5 and "one results file" in err[0] and "missing.json" in err[1]
    assert "repeats: one positive integer per set" in err[2]
    assert "give a quality weight" in err[3] and "none.onnx: box refiner not found" in err[4]
    refined = tmp_path / "refined.json"
    refined.write_text(json.dumps([{**r, "box_refined": True} if r["category_id"] == 1 else r
                                   for r in json.loads(dets.read_text())]))
    assert main(["train-box-refiner", str(labelled_set), "--detections", str(refined),
                 "--out", str(bad), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "refined.json: result" in err[0] and "--no-box-refiner" in err[0]
    assert not bad.exists()


def test_report_box_refiner_needs_detections(labelled_set, tmp_path, shipped):
    with pytest.raises(InputError, match="box_refiner: moves a detector's boxes"):
        geometry_report(labelled_set, tmp_path, box_refiner=shipped)

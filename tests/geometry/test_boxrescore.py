"""The crater-box rescorer: its features, the fitted file, the wrapper and the CLI."""

import argparse
import json

import numpy as np
import onnx
import pytest
import torch

from lunarnav_ml.cli import main
from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.eval.cli import SHIPPED, load_box_rescorer
from lunarnav_ml.geometry.boxrefine import BoxRefinedDetector, BoxRefiner
from lunarnav_ml.geometry.boxrescore import (
    DEFAULT_BOX_RESCORER,
    FEATURES,
    GRID_BOX_RESCORER,
    NEIGHBOUR_FLOOR,
    RAW_FLOOR,
    SMALL_READ_BOX_RESCORER,
    BoxRescorer,
    file_digest,
    rescore_features,
    rescored_by,
)
from lunarnav_ml.training.box_refiner import BoxRefinerNet, export_box_refiner
from lunarnav_ml.training.box_rescorer import BoxRescorerConfig, export_box_rescorer, fit
from tests.geometry.test_boxrefine import _FixedDetector
from tests.geometry.test_report import _write_dataset

F = {name: k for k, name in enumerate(FEATURES)}


def test_features_of_a_frame():
    raw = np.array([[10.0, 10.0, 40.0, 10.0], [12.0, 10.0, 40.0, 10.0], [100.0, 50.0, 20.0, 5.0],
                    [11.0, 11.0, 40.0, 10.0]])
    refined = raw.copy()
    refined[0, 3] = 8.0  # the refiner took 2 px off the first box's height
    scores = np.array([0.8, 0.5, 0.3, 0.0001])
    quality = np.array([0.8, 0.5, 0.3, 0.5])  # sqrt(score x quality): 0.8, 0.5, 0.3, 0.007
    out = rescore_features(raw, scores, refined, quality, np.array([0, 1, 2]), (100, 200))
    assert out.shape == (3, len(FEATURES)) and out.dtype == np.float32
    a, b, c = out
    assert a[F["score"]] == pytest.approx(0.8) and a[F["quality"]] == pytest.approx(0.8)
    assert a[F["width"]] == pytest.approx(40 / 200) and a[F["height"]] == pytest.approx(8 / 100)
    assert a[F["aspect"]] == pytest.approx(5.0)
    assert a[F["centre_x"]] == pytest.approx(30 / 200) and a[F["centre_y"]] == pytest.approx(0.14)
    # the weak fourth box (0.007 < the floor) is no one's neighbour
    iou_ab = 38 * 8 / (40 * 8 + 40 * 10 - 38 * 8)
    assert a[F["neighbours_iou30"]] == 1 and a[F["neighbours_iou50"]] == int(iou_ab > 0.5)
    assert a[F["neighbour_max_score"]] == pytest.approx(0.5)
    assert a[F["neighbour_iou_score_sum"]] == pytest.approx(iou_ab * 0.5, rel=1e-5)
    assert a[F["neighbours_above"]] == 0 and b[F["neighbours_above"]] == 1
    assert a[F["shift_height"]] == pytest.approx(2 / 8) and a[F["shift_max"]] == pytest.approx(0.25)
    assert b[F["shift_max"]] == 0
    assert c[F["neighbours_iou30"]] == 0 and c[F["neighbour_max_score"]] == 0
    assert np.sqrt(0.0001 * 0.5) < NEIGHBOUR_FLOOR and RAW_FLOOR == NEIGHBOUR_FLOOR ** 2
    assert rescore_features(raw, scores, refined, quality, np.zeros(0, int), (100, 200)).shape \
        == (0, len(FEATURES))


def _toy_rows(n=600, seed=0):
    """Rows whose target follows the score and, at equal score, the box's height."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0, 1, (n, len(FEATURES))).astype(np.float32)
    y = (x[:, F["score"]] + x[:, F["height"]] + 0.1 * rng.normal(size=n) > 1.0).astype(int)
    return x, y


@pytest.fixture(scope="module")
def toy_file(tmp_path_factory):
    x, y = _toy_rows()
    model = fit(x, y, BoxRescorerConfig(trees=60, depth=2))
    path = export_box_rescorer(model, tmp_path_factory.mktemp("rescorer") / "r.onnx",
                               {"lunarnav.detector": json.dumps({"file": "d.pt",
                                                                 "sha256": "0" * 64})})
    return path, model, x


def test_export_matches_sklearn_and_learns(toy_file):
    path, model, x = toy_file
    rescorer = BoxRescorer(path)
    prob = rescorer(x)
    assert prob.shape == (len(x),) and prob.dtype == np.float32
    np.testing.assert_allclose(prob, model.predict_proba(x)[:, 1], atol=1e-5)
    hi, lo = x[:1].copy(), x[:1].copy()
    hi[0, F["score"]], lo[0, F["score"]] = 0.95, 0.05
    hi[0, F["height"]], lo[0, F["height"]] = 0.9, 0.1
    assert rescorer(hi)[0] > 0.8 and rescorer(lo)[0] < 0.2
    assert rescorer(np.zeros((0, len(FEATURES)))).shape == (0,)
    # the same seed, the same trees
    again = fit(*_toy_rows(), BoxRescorerConfig(trees=60, depth=2))
    np.testing.assert_array_equal(again.predict_proba(x), model.predict_proba(x))


def test_rescorer_input_and_file_errors(toy_file, tmp_path):
    path, _, x = toy_file
    rescorer = BoxRescorer(path)
    for bad in (x[:, :5], x[0], np.where(np.arange(x.size).reshape(x.shape) == 3, np.nan, x)):
        with pytest.raises(InputError, match="rescorer features"):
            rescorer(bad)
    with pytest.raises(InputError, match="nope.onnx"):
        BoxRescorer(tmp_path / "nope.onnx")
    torch.manual_seed(0)
    refiner = export_box_refiner(BoxRefinerNet(), tmp_path / "b.onnx")
    with pytest.raises(InputError, match="not a box rescorer"):
        BoxRescorer(refiner)
    other = onnx.load(str(path))
    for p in other.metadata_props:
        if p.key == "lunarnav.features":
            p.value = "score,quality"
    onnx.save(other, str(tmp_path / "old.onnx"))
    with pytest.raises(InputError, match="lunarnav.features"):
        BoxRescorer(tmp_path / "old.onnx")
    (tmp_path / "cut.onnx").write_bytes(path.read_bytes()[:200])
    with pytest.raises(InputError, match="cut.onnx"):
        BoxRescorer(tmp_path / "cut.onnx")
    with pytest.raises(InputError, match="both on and off"):
        fit(x, np.ones(len(x), int))
    with pytest.raises(ConfigError, match="subsample"):
        BoxRescorerConfig(subsample=0.0)


class _Quality:
    has_quality = True
    path = "quality-refiner"

    def refine_scored(self, gray, xywh):
        return xywh, np.full(len(xywh), 0.25, np.float32)


class _Rescorer:
    path = "toy"

    def __init__(self):
        self.seen = []

    def __call__(self, feats):
        self.seen.append(feats)
        return 1.0 - feats[:, F["score"]]  # turns the order of the crater boxes around


def test_refined_detector_rescores_crater_boxes():
    boxes = [[10.0, 10.0, 50.0, 30.0], [100.0, 10.0, 150.0, 30.0], [10.0, 60.0, 40.0, 80.0]]
    inner = _FixedDetector(boxes, [0.9, 0.4, 0.5], [1, 1, 2])
    rescorer = _Rescorer()
    det = BoxRefinedDetector(inner, _Quality(), rescorer)
    out = det.predict([np.zeros((100, 200, 3), np.uint8)], conf_thres=0.5)[0]
    assert inner.calls[-1][0] == pytest.approx(RAW_FLOOR)  # it sees the weak boxes too
    assert out["labels"].tolist() == [1, 2]  # the rock keeps 0.5; 1 - 0.9 drops under 0.5
    assert out["scores"].tolist() == pytest.approx([0.6, 0.5])
    assert out["boxes"][0].tolist() == boxes[1]
    assert rescorer.seen[-1].shape == (2, len(FEATURES))
    assert "scored by toy" in det.describe()
    plain = BoxRefinedDetector(inner, _Quality()).refine(
        np.zeros((100, 200), np.uint8), inner.out, 0.6, features=True)
    feats = plain["rescore_features"]
    assert plain["labels"].tolist() == [2, 1, 1]  # 0.5, sqrt(0.9 x 0.25), sqrt(0.4 x 0.25)
    assert np.isnan(feats[0]).all() and np.isfinite(feats[1:]).all()
    assert feats[1:, F["score"]].tolist() == pytest.approx([0.9, 0.4])

    class NoQuality:
        has_quality = False
        path = "edges-only"

    with pytest.raises(InputError, match="edges-only.*quality"):
        BoxRefinedDetector(inner, NoQuality(), rescorer)


@pytest.fixture(scope="module")
def labelled_set(tmp_path_factory, crater_scene):
    """One labelled frame with a detection on its crater and two off it, and a box refiner with
    a quality output."""
    root = tmp_path_factory.mktemp("rescore_ds")
    _write_dataset(root, crater_scene)
    x, y, w, h = (float(v) for v in crater_scene.box)
    dets = [{"image_id": 1, "category_id": 1, "bbox": [x, y, w, h], "score": 0.9},
            {"image_id": 1, "category_id": 1, "bbox": [0.0, 0.0, 30.0, 10.0], "score": 0.6},
            {"image_id": 1, "category_id": 1, "bbox": [5.0, 200.0, 40.0, 12.0], "score": 0.3}]
    (root / "detections.json").write_text(json.dumps(dets))
    torch.manual_seed(0)
    export_box_refiner(BoxRefinerNet(quality=True), root / "q.onnx")
    (root / "model.pt").write_bytes(b"a detector's bytes")
    return root


def test_cli_fit_and_the_default_choice(labelled_set, tmp_path, capsys):
    out, root = tmp_path / "r.onnx", labelled_set
    assert main(["train-box-rescorer", str(root), str(root), "--detections",
                 str(root / "detections.json"), str(root / "detections.json"), "--detector",
                 str(root / "model.pt"), "--box-refiner", str(root / "q.onnx"), "--out",
                 str(out), "--trees", "5", "--repeats", "1", "3", "--quiet"]) == 0
    assert "6 crater boxes (2 on a countable crater)" in capsys.readouterr().out
    props = {p.key: p.value for p in onnx.load(str(out)).metadata_props}
    assert json.loads(props["lunarnav.training"])["repeats"] == [1, 3]
    assert json.loads(props["lunarnav.small_read"]) is None  # fitted on one read
    rescorer = BoxRescorer(out)
    assert rescorer.fitted_with["detector"] == {"file": "model.pt",
                                                "sha256": file_digest(root / "model.pt")}
    refiner = BoxRefiner(root / "q.onnx")
    assert rescorer.fitted_for(root / "model.pt", refiner.path)
    (tmp_path / "other.pt").write_bytes(b"another detector")
    assert not rescorer.fitted_for(tmp_path / "other.pt", refiner.path)
    assert not rescorer.fitted_for(root / "model.pt", DEFAULT_BOX_RESCORER)
    args = argparse.Namespace(threads=1, box_rescorer=str(out))
    assert load_box_rescorer(args, tmp_path / "other.pt", refiner).path == out  # named: used
    with pytest.raises(InputError, match="quality"):
        load_box_rescorer(args, root / "model.pt", None)
    args.box_rescorer = None  # off, the default
    assert load_box_rescorer(args, root / "model.pt", refiner) is None
    args.box_rescorer = SHIPPED  # the shipped file: fitted on small.pt, refused for others
    with pytest.raises(InputError, match="fitted on the scores of small.pt"):
        load_box_rescorer(args, root / "model.pt", refiner)
    shipped = BoxRescorer(DEFAULT_BOX_RESCORER)
    from lunarnav_ml.geometry.boxrefine import DEFAULT_BOX_REFINER
    from lunarnav_ml.training.cli import DEFAULT_WEIGHTS

    assert shipped.fitted_for(DEFAULT_WEIGHTS, DEFAULT_BOX_REFINER)
    assert load_box_rescorer(args, DEFAULT_WEIGHTS, BoxRefiner()).path == DEFAULT_BOX_RESCORER
    # with --small-read the shipped file is the one fitted on that read's boxes
    args.small_read, args.small_read_below, args.small_read_band = 640, 15.0, (0.27, 0.56)
    assert BoxRescorer(SMALL_READ_BOX_RESCORER).fitted_for(DEFAULT_WEIGHTS, DEFAULT_BOX_REFINER,
                                                           {"side": 640, "below_px": 15.0})
    assert load_box_rescorer(args, DEFAULT_WEIGHTS, BoxRefiner()).path == SMALL_READ_BOX_RESCORER
    assert rescored_by(SMALL_READ_BOX_RESCORER).endswith("shipped box rescorer for --small-read")
    # small_grid.pt (trained on the paper's grid) takes its own file for that read
    grid_weights = DEFAULT_WEIGHTS.with_name("small_grid.pt")
    assert load_box_rescorer(args, grid_weights, BoxRefiner()).path == GRID_BOX_RESCORER
    assert not BoxRescorer(GRID_BOX_RESCORER).fitted_for(DEFAULT_WEIGHTS, DEFAULT_BOX_REFINER,
                                                         {"side": 640, "below_px": 15.0})
    assert "small_grid.pt" in rescored_by(GRID_BOX_RESCORER)
    args.small_read, args.small_read_band = None, None  # small_grid.pt, one read: none fits
    with pytest.raises(InputError, match="asked for .*small_grid.pt"):
        load_box_rescorer(args, grid_weights, BoxRefiner())
    args.small_read, args.small_read_band = 640, (0.27, 0.56)
    for side, below in ((768, 15.0), (640, 9.0)):  # another read: refused, not misapplied
        args.small_read, args.small_read_below = side, below
        with pytest.raises(InputError, match="fitted on the boxes of --small-read 640"):
            load_box_rescorer(args, DEFAULT_WEIGHTS, BoxRefiner())
    args.box_rescorer = str(out)  # a named file with any read: the user's choice
    assert load_box_rescorer(args, tmp_path / "other.pt", refiner).path == out
    # the read is the file's record, not a rule of the command line
    small = BoxRescorer(SMALL_READ_BOX_RESCORER)
    assert small.fitted_with["small_read"] == {"side": 640, "below_px": 15.0}
    assert not small.fitted_for(DEFAULT_WEIGHTS, DEFAULT_BOX_REFINER)  # not for one read
    assert not shipped.fitted_for(DEFAULT_WEIGHTS, DEFAULT_BOX_REFINER, small.fitted_with[
        "small_read"])  # nor the one-read file for the second read
    read_out = tmp_path / "read.onnx"
    assert main(["train-box-rescorer", str(root), "--detections", str(root / "detections.json"),
                 "--detector", str(root / "model.pt"), "--box-refiner", str(root / "q.onnx"),
                 "--out", str(read_out), "--trees", "5", "--small-read", "512", "--quiet"]) == 0
    assert BoxRescorer(read_out).fitted_with["small_read"] == {"side": 512, "below_px": 15.0}
    assert BoxRescorer(read_out).fitted_for(root / "model.pt", refiner.path,
                                            {"side": 512, "below_px": 15.0})


def test_cli_errors_are_one_line(labelled_set, tmp_path, capsys):
    root = labelled_set
    base = ["train-box-rescorer", str(root), "--detector", str(root / "model.pt"),
            "--box-refiner", str(root / "q.onnx"), "--out", str(tmp_path / "r.onnx"), "--quiet"]
    assert main([*base, "--detections", str(tmp_path / "missing.json")]) != 0
    assert "missing.json" in capsys.readouterr().err
    (tmp_path / "bad.json").write_text('[{"image_id": 1, "category_id": 1, "bbox": [1, 2]}]')
    assert main([*base, "--detections", str(tmp_path / "bad.json")]) != 0
    assert "bbox" in capsys.readouterr().err
    assert main([*base, "--detections", str(root / "detections.json"),
                 str(root / "detections.json")]) != 0
    assert "one results file per set" in capsys.readouterr().err
    assert main([*base, "--detections", str(root / "detections.json"), "--repeats", "0"]) != 0
    assert "repeats" in capsys.readouterr().err
    torch.manual_seed(0)
    export_box_refiner(BoxRefinerNet(), tmp_path / "edges.onnx")
    args = [a if a != str(root / "q.onnx") else str(tmp_path / "edges.onnx") for a in base]
    assert main([*args, "--detections", str(root / "detections.json")]) != 0
    assert "quality" in capsys.readouterr().err
    assert not (tmp_path / "r.onnx").exists()
    # asked for without the box refiner it reads: refused, not ignored
    assert main(["detect", str(root / "images/left/0.png"), "--no-box-refiner",
                 "--box-rescorer", "--out", str(tmp_path / "d"), "--quiet"]) != 0
    assert "--no-box-refiner" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()

"""benchmarks/replay_candidates.py: the replay of a raw read is the live read, and the candidates
are where they should be."""

import json
from argparse import Namespace

import numpy as np
import pytest

from lunarnav_ml.eval.predict import predict_coco
from lunarnav_ml.geometry.boxrefine import BoxRefinedDetector, BoxRefiner
from tests.bench_scripts import load_script
from tests.detector_fixtures import make_coco

replay = load_script("replay_candidates")


def _args(**kw):
    base = {"candidates": "none", "flat": 3.0, "grow": 1.0, "rows": 0.5, "gap": 0.25,
            "wider": 1.2, "floor": 0.05, "top": 30, "factor": 1.0}
    return Namespace(**{**base, **kw})


def _pred(rows):
    rows = np.array(rows, np.float64).reshape(-1, 6)
    return {"boxes": rows[:, :4], "scores": rows[:, 4].astype(np.float32),
            "labels": rows[:, 5].astype(np.int64)}


def test_flat_boxes_grow_and_halves_join():
    pred = _pred([[100, 50, 160, 60, 0.9, 1],    # flat: 60 x 10
                  [150, 51, 220, 61, 0.5, 1],    # flat, its other half
                  [10, 10, 30, 30, 0.95, 1],     # square: no candidates
                  [300, 50, 360, 60, 0.9, 2],    # a rock
                  [400, 50, 460, 60, 0.01, 1]])  # under the floor
    sides = replay.candidates(pred, (200, 500), _args(candidates="grow-sides", factor=0.5))
    np.testing.assert_allclose(sides["boxes"][5:], [[40, 50, 160, 60], [80, 51, 220, 61],
                                                    [100, 50, 220, 60], [150, 51, 290, 61]])
    np.testing.assert_allclose(sides["scores"][5:], [0.45, 0.25, 0.45, 0.25])
    assert sides["labels"][5:].tolist() == [1] * 4
    centre = replay.candidates(pred, (200, 500), _args(candidates="grow-centre"))
    np.testing.assert_allclose(centre["boxes"][5:], [[70, 50, 190, 60], [115, 51, 255, 61]])
    both = replay.candidates(pred, (200, 500), _args(candidates="unions"))
    np.testing.assert_allclose(both["boxes"][5:], [[100, 50, 220, 61]])
    np.testing.assert_allclose(both["scores"][5:], [0.9])
    clipped = replay.candidates(pred, (200, 200), _args(candidates="grow-sides"))
    assert clipped["boxes"][5:, [0, 2]].max() <= 200 and clipped["boxes"][5:].min() >= 0
    assert replay.candidates(pred, (200, 500), _args()) is pred
    top1 = replay.candidates(pred, (200, 500), _args(candidates="grow-sides", top=1))
    assert len(top1["scores"]) == 5  # the top box is the square: nothing grows


class _Shift:
    """A refiner that moves each box 10 px right, with the box's x / 100 as its quality."""
    has_quality = True

    def refine_scored(self, gray, boxes, quality=True):
        out = np.asarray(boxes, np.float64).copy()
        out[:, 0] += 10
        return out, (np.asarray(boxes)[:, 0] / 100).astype(np.float32)


@pytest.mark.parametrize("refine, quality, x, q", [("twice", "detector", 70, 0.5),
                                                   ("twice", "refined", 70, 0.6),
                                                   ("once", "refined", 60, 0.6),
                                                   ("once", "detector", 60, 0.5)])
def test_two_passes_of_the_refiner(refine, quality, x, q):
    two = replay.TwoPassRefiner(_Shift(), refine, quality)
    boxes, qual = two.refine_scored(np.zeros((8, 8), np.uint8), np.array([[50.0, 5, 20, 4]]))
    assert boxes[0, 0] == x and qual[0] == pytest.approx(q)
    empty, _ = two.refine_scored(np.zeros((8, 8), np.uint8), np.zeros((0, 4)))
    assert empty.shape == (0, 4)


def test_the_replay_of_a_raw_read_is_the_live_read(tmp_path, onnx_path, capsys):
    from lunarnav_ml.runtime import OnnxDetector

    gt = make_coco(tmp_path / "set", n_images=3, size=96)
    data = json.loads(gt.read_text())
    network = OnnxDetector(onnx_path, threads=1)
    live = predict_coco(BoxRefinedDetector(network, BoxRefiner()), data, gt.parent,
                        progress=False)
    raw = predict_coco(network, data, gt.parent, conf_thres=1e-6, progress=False)
    (tmp_path / "raw.json").write_text(json.dumps(raw))
    out = tmp_path / "r" / "replay.json"
    assert replay.main(["--gt", str(gt), "--raw", str(tmp_path / "raw.json"), "--out",
                        str(out)]) == 0
    got = json.loads(out.read_text())

    def rows(results):
        return sorted((r["image_id"], r["category_id"], round(r["score"], 4),
                       *np.round(r["bbox"], 2)) for r in results)

    assert live and rows(got) == rows(live)
    # a read joined with itself is that read joined with nothing (the NMS of a join also takes
    # out the boxes that clipping to the frame brought over 0.6 IoU); another read adds boxes
    (tmp_path / "none.json").write_text("[]")
    joined = replay.raw_reads(tmp_path / "raw.json", tmp_path / "raw.json")
    alone = replay.raw_reads(tmp_path / "raw.json", tmp_path / "none.json")
    assert joined.keys() == alone.keys() and all(
        sorted(map(tuple, joined[k]["boxes"])) == sorted(map(tuple, alone[k]["boxes"]))
        for k in alone)
    other = [{**r, "bbox": [r["bbox"][0] + 40, *r["bbox"][1:]], "score": r["score"] / 2}
             for r in raw]
    (tmp_path / "other.json").write_text(json.dumps(other))
    assert replay.main(["--gt", str(gt), "--raw", str(tmp_path / "raw.json"), "--join",
                        str(tmp_path / "other.json"), "--out", str(tmp_path / "j.json")]) == 0
    assert len(json.loads((tmp_path / "j.json").read_text())) > len(got)
    assert replay.main(["--gt", str(gt), "--raw", str(tmp_path / "raw.json"), "--out",
                        str(tmp_path / "g.json"), "--candidates", "grow-sides",
                        "--flat", "0.1"]) == 0
    assert "candidates added" in capsys.readouterr().out
    assert len(json.loads((tmp_path / "g.json").read_text())) >= len(got)


@pytest.mark.parametrize("extra, says", [(["--grow", "nan"], "--grow"),
                                         (["--top", "0"], "--top"),
                                         (["--raw", "missing.json"], "missing.json")])
def test_bad_input_is_one_line(tmp_path, capsys, extra, says):
    gt = make_coco(tmp_path / "set", n_images=1, size=96)
    (tmp_path / "raw.json").write_text("[]")
    argv = ["--gt", str(gt), "--raw", str(tmp_path / "raw.json"), "--out",
            str(tmp_path / "o.json")]
    if extra[0] == "--raw":
        argv[3] = str(tmp_path / extra[1])
    else:
        argv += extra
    assert replay.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert says in err and "\n" not in err and not (tmp_path / "o.json").exists()


def test_reads_fused_by_wbf_average_their_boxes(tmp_path):
    a = [{"image_id": 1, "category_id": 1, "bbox": [100, 50, 200, 10], "score": 0.8}]
    b = [{"image_id": 1, "category_id": 1, "bbox": [100, 52, 200, 10], "score": 0.8},
         {"image_id": 1, "category_id": 2, "bbox": [10, 10, 20, 20], "score": 0.6}]
    (tmp_path / "a.json").write_text(json.dumps(a))
    (tmp_path / "b.json").write_text(json.dumps(b))
    fused = replay.raw_reads(tmp_path / "a.json", tmp_path / "b.json", iou=0.55, fuse="wbf",
                             shapes={1: (200, 400)})[1]
    crater = fused["labels"] == 1
    np.testing.assert_allclose(fused["boxes"][crater], [[100, 51, 300, 61]], atol=1e-3)
    np.testing.assert_allclose(fused["scores"][crater], [0.8], atol=1e-6)
    rock = fused["labels"] == 2  # found by one read of two: its score halved
    np.testing.assert_allclose(fused["scores"][rock], [0.3], atol=1e-6)
    joined = replay.raw_reads(tmp_path / "a.json", tmp_path / "b.json", iou=0.6)[1]
    assert len(joined["scores"]) == 2  # NMS keeps one of the two crater boxes

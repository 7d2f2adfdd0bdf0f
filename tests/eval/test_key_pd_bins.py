import json

import cv2
import numpy as np
import pytest

from tests.bench_scripts import load_script
from tests.eval.coco_fixtures import CATEGORIES
from tests.eval.coco_fixtures import ann as _ann

bins = load_script("key_pd_bins")


def _crater(ann_id: int, bbox: list[float], dd: float, rng_m: float, rim: float = 1.0,
            diameter: float = 10.0) -> dict:
    return _ann(ann_id, 1, bbox, diameter_m=diameter, depth_m=dd * diameter,
                near_rim_range_m=rng_m, visible_rim_fraction=rim)


def _gt() -> dict:
    return {"images": [{"id": 1, "file_name": "1.png", "width": 400, "height": 200}],
            "categories": CATEGORIES,
            "annotations": [
                _crater(1, [10, 10, 60, 20], 0.20, 8.0),              # fresh, near: found
                _crater(2, [100, 10, 60, 20], 0.20, 12.0),            # fresh: missed
                _crater(3, [200, 10, 60, 20], 0.05, 16.0),            # shallow: found
                _crater(4, [300, 10, 60, 20], 0.05, 9.0, rim=0.3),    # shallow, hidden: missed
                _crater(5, [10, 100, 60, 20], 0.20, 30.0),            # too far: not key
                _crater(6, [100, 100, 60, 20], 0.20, 8.0, diameter=3.0),  # too small: not key
            ]}


def _dets() -> list[dict]:
    return [{"image_id": 1, "category_id": 1, "bbox": b, "score": s}
            for b, s in (([10, 10, 60, 20], 0.9), ([100, 10, 60, 20], 0.3),
                         ([200, 10, 60, 20], 0.8), ([10, 100, 60, 20], 0.9))]


def test_key_craters_are_split_by_attribute_at_the_threshold():
    fig, match = bins.key_bins(_gt(), _dets(), 0.5)
    assert fig["all"] == {"n": 4, "pd": 0.5}
    assert fig["fresh"] == {"n": 2, "pd": 0.5} and fig["rest"] == {"n": 2, "pd": 0.5}
    assert fig["shallow"] == {"n": 2, "pd": 0.5} and fig["cap_without_shallow"] == 0.5
    dd = {c["from"]: (c["n"], c["pd"]) for c in fig["bins"]["depth/diameter"]}
    assert dd[0.0] == (2, 0.5) and dd[0.08] == (0, None) and dd[0.16] == (2, 0.5)
    rim = {c["from"]: (c["n"], c["pd"]) for c in fig["bins"]["visible rim fraction"]}
    assert rim[0.0] == (1, 0.0) and rim[0.8] == (3, pytest.approx(2 / 3))
    rng = {c["from"]: (c["n"], c["pd"]) for c in fig["bins"]["near-rim range m"]}
    assert rng[0.0] == (2, 0.5) and rng[10.0] == (1, 0.0) and rng[15.0] == (1, 1.0)
    aspect = {c["from"]: (c["n"], c["pd"]) for c in fig["bins"]["box width/height"]}
    assert aspect[0.0] == (4, 0.5) and aspect[25.0] == (0, None)  # every box is 60 x 20
    # a lower threshold finds the second fresh crater too
    assert bins.key_bins(_gt(), _dets(), 0.2)[0]["fresh"]["pd"] == 1.0
    assert match.hit.sum() == 3  # the far crater is found, but it is not a key crater
    # only the key craters need a depth
    gt = _gt()
    del gt["annotations"][4]["depth_m"]
    assert bins.key_bins(gt, _dets(), 0.5)[0] == fig


def test_cli_prints_the_bins_and_draws_the_montage(tmp_path, capsys):
    gt = _gt()
    cv2.imwrite(str(tmp_path / "1.png"), np.full((200, 400), 128, np.uint8))
    (tmp_path / "annotations.json").write_text(json.dumps(gt))
    read = tmp_path / "read"
    read.mkdir()
    (read / "detections.json").write_text(json.dumps(_dets()))
    (read / "metrics.json").write_text(json.dumps({"threshold": 0.5}))
    png = tmp_path / "m.png"
    assert bins.main(["--gt", str(tmp_path / "annotations.json"), "--read", str(read),
                      "--montage", str(png)]) == 0
    out = capsys.readouterr().out
    assert "key Pd 0.500 (n 4)" in out and "depth/diameter: [0, 0.08) 0.500 (n 2)" in out
    assert "could reach at most 0.500" in out
    image = cv2.imread(str(png))
    # one row of shallow tiles, the white gap, one row of fresh tiles
    assert image.shape == (2 * bins.TILE_H + 8, bins.PER_ROW * bins.TILE_W, 3)
    # found in green, missed in red, on the shallow row
    top = image[:bins.TILE_H]
    assert (top[..., 1] == 200).any() and (top[..., 2] == 255).any()


def test_cli_errors_name_the_file(tmp_path, capsys):
    (tmp_path / "annotations.json").write_text(json.dumps(_gt()))
    read = tmp_path / "read"
    read.mkdir()
    (read / "detections.json").write_text(json.dumps(_dets()))
    assert bins.main(["--gt", str(tmp_path / "annotations.json"), "--read", str(read)]) == 2
    assert "metrics.json" in capsys.readouterr().err
    (read / "metrics.json").write_text(json.dumps({"threshold": None}))
    assert bins.main(["--gt", str(tmp_path / "annotations.json"), "--read", str(read)]) == 2
    assert "threshold" in capsys.readouterr().err
    gt = _gt()
    del gt["annotations"][0]["depth_m"]
    (tmp_path / "annotations.json").write_text(json.dumps(gt))
    (read / "metrics.json").write_text(json.dumps({"threshold": 0.5}))
    assert bins.main(["--gt", str(tmp_path / "annotations.json"), "--read", str(read)]) == 2
    assert "annotation 1: depth_m" in capsys.readouterr().err


def test_misses_are_told_by_their_nearest_box_and_drawn(tmp_path, capsys):
    gt = _gt()
    gt["annotations"][3]["bbox"] = [280, 10, 80, 20]  # the hidden shallow crater, widest now
    dets = _dets() + [{"image_id": 1, "category_id": 1, "bbox": [280, 10, 40, 20], "score": 0.05},
                      {"image_id": 1, "category_id": 1, "bbox": [95, 8, 90, 22], "score": 0.1}]
    _, match = bins.key_bins(gt, dets, 0.5)
    misses = bins.missed_key(match, dets)
    assert [m["ann"]["id"] for m in misses] == [4, 2]  # the widest first
    assert misses[0]["kind"] == "narrow" and misses[0]["iou"] == pytest.approx(0.5)
    assert misses[0]["score"] == pytest.approx(0.05)
    # crater 2: its own box at 0.3 outscores the wider one at 0.1
    assert misses[1]["kind"] == "placed" and misses[1]["iou"] == pytest.approx(1.0)
    assert bins.missed_key(match, _dets()[:1])[0]["kind"] == "none"

    cv2.imwrite(str(tmp_path / "1.png"), np.full((200, 400), 128, np.uint8))
    (tmp_path / "annotations.json").write_text(json.dumps(gt))
    read = tmp_path / "read"
    read.mkdir()
    (read / "detections.json").write_text(json.dumps(dets))
    (read / "metrics.json").write_text(json.dumps({"threshold": 0.5}))
    png = tmp_path / "misses.png"
    assert bins.main(["--gt", str(tmp_path / "annotations.json"), "--read", str(read),
                      "--misses", str(png)]) == 0
    assert ("2 key craters missed; the best box at IoU >= 0.3: too narrow 1, too wide 0, "
            "placed wrong 1, none 0") in capsys.readouterr().out
    image = cv2.imread(str(png))
    assert image.shape == (bins.MISS_H, bins.MISS_ROW * bins.MISS_W, 3)
    first = image[:, :bins.MISS_W].reshape(-1, 3)
    assert ((first == (0, 0, 255)).all(axis=1).any()  # the label in red
            and (first == (0, 255, 255)).all(axis=1).any())  # its nearest box in yellow
    assert not image[:, 2 * bins.MISS_W:].any()  # two tiles, the rest of the row blank

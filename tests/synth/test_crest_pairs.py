"""benchmarks/crest_pairs.py: the same craters of two renders, cut out side by side."""

import json
from pathlib import Path

import cv2
import numpy as np

from tests.bench_scripts import load_script

crest_pairs = load_script("crest_pairs")


def _crater(k, image_id, d, deg, near, box, ignore=False, **extra):
    return {"id": k, "image_id": image_id, "category_id": 1, "bbox": box, "area": 1.0,
            "iscrowd": int(ignore), "ignore": ignore, "diameter_m": d, "degradation": deg,
            "near_rim_range_m": near, "center_cam_m": [0.0, 1.5, near + d / 2], **extra}


def _dataset(root: Path, shade: int, anns: list[dict]) -> Path:
    root.mkdir()
    for i in (1, 2):
        cv2.imwrite(str(root / f"{i:06d}.png"), np.full((96, 128, 3), shade * i, np.uint8))
    data = {"images": [{"id": i, "file_name": f"{i:06d}.png", "width": 128, "height": 96}
                       for i in (1, 2)],
            "annotations": anns,
            "categories": [{"id": 1, "name": "crater"}, {"id": 2, "name": "rock"},
                           {"id": 3, "name": "artifact"}]}
    (root / "annotations.json").write_text(json.dumps(data))
    return root / "annotations.json"


def _anns(dx=0.0):
    return [_crater(1, 1, 6.0, 0.8, 10.0, [20 + dx, 30, 40, 12]),
            _crater(2, 1, 6.0, 0.2, 10.0, [70, 30, 30, 10]),        # too fresh
            _crater(3, 2, 9.0, 0.6, 15.0, [10, 50, 60, 14]),
            _crater(4, 2, 3.0, 0.9, 8.0, [90, 60, 20, 8]),          # too small
            _crater(5, 2, 7.0, 0.7, 12.0, [40, 20, 30, 9], ignore=True)]


def test_pairs_are_the_filtered_craters_most_degraded_first(tmp_path, capsys):
    a = _dataset(tmp_path / "a", 40, _anns())
    b = _dataset(tmp_path / "b", 90, _anns(dx=1.5))
    out = tmp_path / "pairs.png"
    assert crest_pairs.main([str(a), str(b), "--out", str(out)]) == 0
    assert "2 pairs" in capsys.readouterr().out
    sheet = cv2.imread(str(out))
    assert sheet.shape == (256, 4 * 256, 3)  # two pairs of tiles in one row of four
    data = json.loads(a.read_text())
    rows = crest_pairs.select(data, 0.5, 5.0, 20.0)
    assert [ann["id"] for _, ann in rows] == [1, 3]
    # the second render's tile shows its own image (shade 90 against 40)
    left, right = sheet[100:120, 5:20], sheet[100:120, 256 + 5:256 + 20]
    assert right.mean() > left.mean() + 30


def test_bad_inputs_are_one_line_errors(tmp_path, capsys):
    a = _dataset(tmp_path / "a", 40, _anns())
    other = _dataset(tmp_path / "b", 90, [_crater(1, 1, 4.5, 0.1, 9.0, [5, 5, 20, 8])])
    assert crest_pairs.main([str(a), str(other), "--out", str(tmp_path / "x.png")]) == 2
    assert "none of the chosen craters" in capsys.readouterr().err
    bare = [{k: v for k, v in _crater(1, 1, 6.0, 0.8, 10.0, [20, 30, 40, 12]).items()
             if k != "degradation"}]
    c = _dataset(tmp_path / "c", 40, bare)
    assert crest_pairs.main([str(c), str(a), "--out", str(tmp_path / "y.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert "degradation" in err and "\n" not in err
    assert crest_pairs.main([str(a), str(a), "--min-diameter", "50",
                             "--out", str(tmp_path / "z.png")]) == 2
    assert "no countable crater" in capsys.readouterr().err
    assert not any(tmp_path.glob("*.png"))

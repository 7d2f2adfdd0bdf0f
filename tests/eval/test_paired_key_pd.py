"""benchmarks/paired_key_pd.py: key craters matched at each read's threshold, frames resampled."""

import json

import numpy as np
import pytest

from tests.bench_scripts import load_script
from tests.eval.coco_fixtures import CATEGORIES
from tests.eval.coco_fixtures import ann as _ann

paired = load_script("paired_key_pd")


def _gt(n_frames: int) -> dict:
    images = [{"id": i + 1, "file_name": f"{i}.png", "width": 400, "height": 200}
              for i in range(n_frames)]
    anns = []
    for i in range(n_frames):
        anns.append(_ann(2 * i + 1, 1, [10, 10, 60, 20], diameter_m=10.0, depth_m=2.0,
                         near_rim_range_m=8.0))  # key
        anns[-1]["image_id"] = i + 1
        anns.append(_ann(2 * i + 2, 1, [100, 10, 60, 20], diameter_m=10.0, depth_m=2.0,
                         near_rim_range_m=30.0))  # too far: not key
        anns[-1]["image_id"] = i + 1
    return {"images": images, "categories": CATEGORIES, "annotations": anns}


def _read(folder, dets, threshold):
    folder.mkdir()
    (folder / "detections.json").write_text(json.dumps(dets))
    (folder / "metrics.json").write_text(json.dumps({"threshold": threshold}))
    return folder


def _det(image_id, box, score):
    return {"image_id": image_id, "category_id": 1, "bbox": box, "score": score}


def test_each_read_at_its_own_threshold(tmp_path, capsys):
    gt = _gt(10)
    (tmp_path / "annotations.json").write_text(json.dumps(gt))
    # A finds the key crater on frames 1-4 at 0.5; B on frames 1-8 at 0.3 (its own threshold);
    # both find the far crater everywhere, which is not counted
    a = [_det(i, [10, 10, 60, 20], 0.6 if i <= 4 else 0.4) for i in range(1, 11)]
    b = [_det(i, [10, 10, 60, 20], 0.35 if i <= 8 else 0.2) for i in range(1, 11)]
    far = [_det(i, [100, 10, 60, 20], 0.9) for i in range(1, 11)]
    ra = _read(tmp_path / "a", a + far, 0.5)
    rb = _read(tmp_path / "b", b + far, 0.3)
    assert paired.main(["--gt", str(tmp_path / "annotations.json"), "--a", str(ra), "--b",
                        str(rb), "--draws", "2000"]) == 0
    out = capsys.readouterr().out
    assert "key craters 10 on 10 frames: A 0.400, B 0.800; found by B only 4, by A only 0" in out
    figures = paired.paired_bootstrap(*[np.array(v) for v in (
        range(10), [1] * 4 + [0] * 6, [1] * 8 + [0] * 2)], draws=2000)
    assert figures["diff"] == pytest.approx(0.4)
    assert 0 < figures["lo"] < 0.4 < figures["hi"] <= 0.8 and figures["p_not_above"] < 0.05
    # the same seed, the same interval
    again = paired.paired_bootstrap(*[np.array(v) for v in (
        range(10), [1] * 4 + [0] * 6, [1] * 8 + [0] * 2)], draws=2000)
    assert again == figures


def test_bad_input_is_one_line(tmp_path, capsys):
    (tmp_path / "annotations.json").write_text(json.dumps(_gt(2)))
    ra = _read(tmp_path / "a", [], 0.5)
    rb = _read(tmp_path / "b", [], "high")
    assert paired.main(["--gt", str(tmp_path / "annotations.json"), "--a", str(ra), "--b",
                        str(rb)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "b/metrics.json: threshold" in err[0]
    assert paired.main(["--gt", str(tmp_path / "annotations.json"), "--a", str(ra), "--b",
                        str(tmp_path / "none")]) == 2
    assert "none" in capsys.readouterr().err

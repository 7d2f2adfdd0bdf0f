import json

import numpy as np
import pytest

from tests.bench_scripts import load_script
from tests.eval.coco_fixtures import CATEGORIES
from tests.eval.coco_fixtures import ann as _ann

ceiling = load_script("ranking_ceiling")


def _gt() -> dict:
    return {"images": [{"id": i, "file_name": f"{i}.png", "width": 400, "height": 400}
                       for i in (1, 2)],
            "categories": CATEGORIES,
            "annotations": [
                _ann(1, 1, [10, 10, 100, 40]),
                _ann(2, 1, [200, 200, 60, 30]),
                _ann(3, 2, [50, 50, 80, 40]),
                _ann(4, 2, [300, 300, 40, 20], ignore=True),
            ]}


def _det(image_id: int, bbox: list[float], score: float, category: int = 1) -> dict:
    return {"image_id": image_id, "category_id": category, "bbox": bbox, "score": score}


def _dets() -> list[dict]:
    return [
        _det(1, [10, 10, 100, 40], 0.2),    # matches crater 1, scored low
        _det(1, [12, 12, 100, 40], 0.1),    # a second box on crater 1
        _det(1, [200, 200, 25, 30], 0.9),   # loose on crater 2 (IoU 0.42)
        _det(2, [50, 50, 80, 40], 0.3),     # matches crater 3
        _det(2, [300, 300, 40, 18], 0.8),   # on the ignored crater: neither hit nor miss
        _det(2, [290, 290, 60, 40], 0.7),   # near the ignored crater, not on it
        _det(2, [0, 300, 40, 40], 0.95),    # off every crater
        _det(2, [0, 0, 20, 20], 0.99, 2),   # a rock box: not read
    ]


def test_report_splits_the_unmatched_boxes_and_reads_the_ceiling():
    fig = ceiling.report(_gt(), _dets())
    assert fig["status"].tolist() == [1, 0, 0, 1, -1, 0, 0, -1]
    assert fig["kind"].tolist() == [-1, 0, 1, -1, -1, 2, 3, -1]
    assert fig["n_matched"] == 2 and fig["n_unmatched"] == 4
    # two of three countable craters found, below three unmatched boxes
    assert fig["recall"] == pytest.approx(2 / 3) and fig["ap50"] < 0.5
    # ranked first, the two matched boxes give precision 1 up to recall 2/3
    assert fig["ceiling_recall"] == pytest.approx(2 / 3)
    assert fig["ceiling_ap50"] == pytest.approx(67 / 101)
    by_kind = {k["kind"]: k for k in fig["kinds"]}
    assert by_kind["off every crater"]["above_median_hit"] == 1
    assert by_kind["second box"]["above_median_hit"] == 0
    assert by_kind["off every crater"]["ap50_without"] > fig["ap50"]
    # the second box ranks below both hits: removing it changes nothing
    assert by_kind["second box"]["ap50_without"] == pytest.approx(fig["ap50"])


def test_report_without_crater_boxes_is_zero():
    fig = ceiling.report(_gt(), [_det(1, [0, 0, 20, 20], 0.5, 2)])
    assert fig["ap50"] == 0.0 and fig["ceiling_ap50"] == 0.0 and fig["n_matched"] == 0
    assert np.all(fig["status"] == -1)


def test_main_prints_plots_and_names_a_bad_file(tmp_path, capsys):
    gt, res, png = tmp_path / "gt.json", tmp_path / "r.json", tmp_path / "s.png"
    gt.write_text(json.dumps(_gt()))
    res.write_text(json.dumps(_dets()))
    assert ceiling.main(["--gt", str(gt), "--results", str(res), "--plot", str(png)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("crater AP50 ") and "ranking ceiling AP50 0.6634" in out[0]
    assert len(out) == 6 and png.stat().st_size > 0
    res.write_text(json.dumps([{**_det(1, [1, 2, 3, 4], 0.5), "score": float("nan")}]))
    assert ceiling.main(["--gt", str(gt), "--results", str(res)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "r.json" in err[0]

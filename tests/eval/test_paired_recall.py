import json

import numpy as np

from tests.bench_scripts import load_script
from tests.eval.coco_fixtures import CATEGORIES
from tests.eval.coco_fixtures import ann as _ann

paired = load_script("paired_recall")


def _gt() -> dict:
    return {"images": [{"id": i, "file_name": f"{i}.png", "width": 432, "height": 432}
                       for i in (1, 2, 3)],
            "categories": CATEGORIES,
            "annotations": [
                _ann(1, 1, [10, 10, 100, 20]),
                _ann(2, 1, [200, 200, 40, 20]),
                _ann(3, 2, [50, 50, 60, 30]),
                _ann(4, 2, [0, 0, 10, 10], ignore=True),   # not counted
                _ann(5, 3, [80, 80, 10, 10], category=2),  # a rock: not counted
            ]}


def _det(image_id: int, bbox: list[float], score: float) -> dict:
    return {"image_id": image_id, "category_id": 1, "bbox": bbox, "score": score}


def test_found_per_frame_counts_the_top_k_matches():
    dets = [_det(1, [12, 10, 100, 20], 0.6), _det(1, [300, 300, 20, 20], 0.9),
            _det(2, [50, 52, 60, 30], 0.15)]
    n_gt, found = paired.found_per_frame(_gt(), dets, k=5)
    assert n_gt.tolist() == [2, 1, 0] and found.tolist() == [1, 1, 0]
    _, found_top1 = paired.found_per_frame(_gt(), dets, k=1)  # the 0.9 box crowds frame 1 out
    assert found_top1.tolist() == [0, 1, 0]


def test_paired_bootstrap_is_zero_for_equal_models_and_seeded():
    n_gt, found = np.array([2, 1, 3, 0]), np.array([1, 1, 2, 0])
    assert np.all(paired.paired_bootstrap(n_gt, found, found, n_boot=200) == 0)
    better = found + np.array([1, 0, 1, 0])
    a = paired.paired_bootstrap(n_gt, found, better, n_boot=200, seed=3)
    assert np.all(a >= 0) and a.mean() > 0
    np.testing.assert_array_equal(a, paired.paired_bootstrap(n_gt, found, better, 200, seed=3))


def test_main_prints_the_difference_and_names_a_bad_file(tmp_path, capsys):
    gt, a, b = tmp_path / "gt.json", tmp_path / "a.json", tmp_path / "b.json"
    gt.write_text(json.dumps(_gt()))
    a.write_text(json.dumps([_det(1, [12, 10, 100, 20], 0.6)]))
    b.write_text(json.dumps([_det(1, [12, 10, 100, 20], 0.6), _det(2, [50, 52, 60, 30], 0.2)]))
    assert paired.main(["--gt", str(gt), "--a", str(a), "--b", str(b), "--n-boot", "100"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("recall@5 A 0.333 (1 of 3), B 0.667 (2); B - A +0.333")
    b.write_text(json.dumps([{**_det(1, [1, 2, 3, 4], 0.5), "bbox": [1, 2]}]))
    assert paired.main(["--gt", str(gt), "--a", str(a), "--b", str(b)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "b.json" in err[0]

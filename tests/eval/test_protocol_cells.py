"""benchmarks/protocol_cells.py: the frames of chosen grid cells as another annotations file."""

import json

import pytest

from lunarnav_ml.errors import InputError
from tests.bench_scripts import load_script

cells = load_script("protocol_cells")


def _coco() -> dict:
    images, anns = [], []
    for k, (d, r) in enumerate([(5.0, 13.0), (15.0, 13.0), (17.0, 21.0), (20.0, 23.0)]):
        images.append({"id": k + 1, "file_name": f"{k}.png", "width": 64, "height": 64,
                       "protocol_item": {"diameter_m": d, "near_rim_range_m": r}})
        anns.append({"id": k + 1, "image_id": k + 1, "category_id": 1, "bbox": [1, 1, 5, 5]})
    return {"images": images, "annotations": anns, "categories": [{"id": 1, "name": "crater"}]}


def test_keeps_the_cells_and_their_labels():
    out = cells.select_cells(_coco(), [15.0, 17.0, 20.0], (11.0, 21.0))
    assert [im["id"] for im in out["images"]] == [2, 3]  # 20 m at 23 m is out of range
    assert [a["image_id"] for a in out["annotations"]] == [2, 3]
    assert out["categories"] == _coco()["categories"]


def test_cli_writes_the_subset(tmp_path, capsys):
    src = tmp_path / "annotations.json"
    src.write_text(json.dumps(_coco()))
    dst = tmp_path / "big.json"
    assert cells.main([str(src), "--diameters", "5", "--ranges", "5", "29", "--out", str(dst)]) == 0
    assert [im["id"] for im in json.loads(dst.read_text())["images"]] == [1]
    assert "1 of 4 images" in capsys.readouterr().out


def test_not_a_protocol_render_is_named(tmp_path, capsys):
    coco = _coco()
    del coco["images"][2]["protocol_item"]
    with pytest.raises(InputError, match="image 3 has no protocol_item"):
        cells.select_cells(coco, [15.0], (5.0, 29.0), "x.json")
    src = tmp_path / "annotations.json"
    src.write_text(json.dumps(coco))
    assert cells.main([str(src), "--diameters", "15", "--ranges", "5", "29",
                       "--out", str(tmp_path / "o.json")]) == 2
    assert "annotations.json: image 3 has no protocol_item" in capsys.readouterr().err
    assert not (tmp_path / "o.json").exists()


def test_no_frame_in_the_cells_is_an_error(tmp_path, capsys):
    src = tmp_path / "annotations.json"
    src.write_text(json.dumps(_coco()))
    assert cells.main([str(src), "--diameters", "12", "--ranges", "5", "29",
                       "--out", str(tmp_path / "o.json")]) == 2
    assert "no frame in those cells" in capsys.readouterr().err

"""``lunarnav synth``: damaged records and bad output paths give one-line errors, found before
anything is rendered."""

import json

import pytest

from lunarnav_ml.cli import main
from lunarnav_ml.errors import InputError
from lunarnav_ml.synth import merge_annotations

ITEM = {"image": {"id": 1, "file_name": "images/left/000000.png", "width": 64, "height": 64},
        "annotations": [{"category_id": 1, "bbox": [1.0, 2.0, 3.0, 4.0], "area": 12.0}]}


def _dataset(root, manifest='{"n_items": 1}', item=ITEM):
    (root / "items").mkdir(parents=True)
    (root / "synth_manifest.json").write_text(manifest)
    (root / "items" / "000000.json").write_text(item if isinstance(item, str)
                                                else json.dumps(item))
    return root


def test_merge_of_a_good_record_writes_annotations(tmp_path):
    ann = merge_annotations(_dataset(tmp_path / "d"))
    coco = json.loads(ann.read_text())
    assert [a["image_id"] for a in coco["annotations"]] == [1]


@pytest.mark.parametrize("manifest, item, where, message", [
    ("{n_items: 1", ITEM, "synth_manifest.json", "not valid JSON"),
    ('{"seed": 0}', ITEM, "synth_manifest.json", "n_items"),
    ('{"n_items": "two"}', ITEM, "synth_manifest.json", "n_items"),
    ("[1]", ITEM, "synth_manifest.json", "object"),
    ('{"n_items": 1}', {"annotations": []}, "000000.json", "corrupt item record"),
    ('{"n_items": 1}', {"image": {"id": 1}, "annotations": [3]}, "000000.json", "corrupt item"),
    ('{"n_items": 1}', "[]", "000000.json", "corrupt item record"),
])
def test_merge_of_damaged_records_names_the_file(tmp_path, capsys, manifest, item, where,
                                                 message):
    root = _dataset(tmp_path / "d", manifest, item)
    with pytest.raises(InputError, match=message) as err:
        merge_annotations(root)
    assert where in str(err.value)
    assert main(["synth", str(root), "--merge"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and where in lines[0]
    assert not (root / "annotations.json").exists()


@pytest.fixture
def no_rendering(monkeypatch):
    from lunarnav_ml import synth

    def fail(*args, **kwargs):
        raise AssertionError("rendered before the output paths were checked")

    monkeypatch.setattr(synth, "generate_dataset", fail)


@pytest.mark.parametrize("gallery, message", [
    ("g.txt", "suffix '.txt'"),
    ("adir", "existing folder"),
    ("afile/g.png", "which is a file"),
])
def test_bad_gallery_path_is_found_before_rendering(tmp_path, capsys, no_rendering, gallery,
                                                    message):
    (tmp_path / "adir").mkdir()
    (tmp_path / "afile").write_text("x")
    code = main(["synth", str(tmp_path / "o"), "--n", "1", "--size", "64", "--no-stereo",
                 "--quiet", "--gallery", str(tmp_path / gallery)])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1
    assert str(tmp_path / gallery) in lines[0] and message in lines[0]
    assert not (tmp_path / "o").exists()


def test_output_folder_that_is_a_file_is_found_before_rendering(tmp_path, capsys, no_rendering):
    (tmp_path / "afile").write_text("x")
    code = main(["synth", str(tmp_path / "afile"), "--n", "1", "--size", "64", "--quiet"])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "afile: output folder is an existing file" in lines[0]

"""The importer on fake Roboflow COCO and YOLO-txt exports: mapping, dropping, cameras,
de-duplication, leakage, bad input (errors naming the file and item; skip-and-count)."""

import json

import numpy as np
import pytest

from lunarnav_ml.data.coco import load_coco
from lunarnav_ml.errors import InputError
from lunarnav_ml.realdata.importer import import_real
from tests.realdata.fixtures import edit_coco, make_roboflow, make_yolo, roboflow_name


@pytest.fixture
def roboflow(tmp_path):
    return make_roboflow(tmp_path / "export")


def _load(out, split):
    return json.loads((out / split / "annotations.json").read_text())


def test_roboflow_import_maps_drops_and_ignores(roboflow, tmp_path):
    out = tmp_path / "out"
    report = import_real(roboflow, out)
    train, valid = report["splits"]["train"], report["splits"]["valid"]
    assert list(report["splits"]) == ["train", "valid"]
    assert (train["images_in"], train["images_out"], train["source_frames"]) == (6, 6, 2)
    assert (train["annotations_in"], train["annotations_out"]) == (30, 24)
    assert train["per_class"] == {"crater": 6, "rock": 12, "artifact": 6}
    assert train["mapped"] == {"artifact -> artifact": 6, "boulder -> rock": 6,
                               "crater -> crater": 6, "rock -> rock": 6}
    assert train["dropped"] == {"rocky region": 6} and train["skipped"] == {}
    assert train["ignored"] == 6 and train["max_copies_per_source"] == 3
    assert train["cameras"] == {"ce4": {"images": 3, "source_frames": 1, "annotations": 12},
                                "pcam_colour": {"images": 3, "source_frames": 1,
                                                "annotations": 12}}
    assert set(valid["cameras"]) == {"ce3_tcam", "pcam_pan"} and valid["annotations_out"] == 8
    assert report["leakage_found"] == {}
    assert (out / "import_report.json").is_file() and (out / "import_report.md").is_file()


def test_output_is_our_coco_and_points_at_the_originals(roboflow, tmp_path):
    out = tmp_path / "out"
    import_real(roboflow, out)
    records = load_coco(out / "train" / "annotations.json")  # passes our validation
    assert records[0].path.resolve().parent == (roboflow / "train").resolve()
    assert not list((out / "train").glob("*.jpg"))  # nothing copied
    data = _load(out, "train")
    assert [c["name"] for c in data["categories"]] == ["crater", "rock", "artifact"]
    image = data["images"][0]
    assert image["id"] == 1 and image["camera_name"] == "pcam_colour"
    assert image["source_name"] == "PCAML-C-001_SCI_A_2C.png"
    ann = data["annotations"][0]
    assert ann["category_id"] == 1 and ann["bbox"] == [10.0, 10.0, 20.0, 16.0]
    assert ann["segmentation"] == [[10, 10, 30, 10, 30, 26, 10, 26]]
    small = [a for a in data["annotations"] if a["source_category"] == "rock"]
    assert all(a["ignore"] and a["iscrowd"] == 1 for a in small)
    np.testing.assert_allclose(records[0].boxes[0], [10, 10, 30, 26])


def test_single_split_folder_and_split_selection(roboflow, tmp_path):
    report = import_real(roboflow / "valid", tmp_path / "one")
    assert list(report["splits"]) == ["valid"]
    report = import_real(roboflow, tmp_path / "sel", splits=["valid"])
    assert list(report["splits"]) == ["valid"]
    with pytest.raises(InputError, match="no split test"):
        import_real(roboflow, tmp_path / "bad", splits=["test"])


def test_leakage_between_splits(tmp_path):
    src = make_roboflow(tmp_path / "export", {
        "train": [("PCAML-C-001_A.png", 3), ("chang4_1.png", 2)],
        "valid": [("PCAML-C-001_A.png", 1), ("chang4_2.png", 1)],
    })
    with pytest.raises(InputError, match=r"train and valid share 1 source frame.*PCAML-C-001_A"):
        import_real(src, tmp_path / "out")
    assert not (tmp_path / "out").exists()
    report = import_real(src, tmp_path / "out", skip_bad=True)
    train, valid = report["splits"]["train"], report["splits"]["valid"]
    assert report["leakage_found"] == {"train/valid": 1}
    assert train["skipped"] == {"leaked_source_image": 3, "annotation_of_skipped_image": 12}
    assert (train["images_out"], valid["images_out"]) == (2, 2)  # the held-out split keeps it
    records = load_coco(tmp_path / "out" / "train" / "annotations.json")
    assert [r.image_id for r in records] == [1, 2]


def _remove_first_image(root):
    data = json.loads((root / "train" / "_annotations.coco.json").read_text())
    (root / "train" / data["images"][0]["file_name"]).unlink()
    return data["images"][0]["file_name"]


def _set(k, key, value):
    def edit(data):
        data["annotations"][k][key] = value
    return edit


@pytest.mark.parametrize("edit, match, reason", [
    (_set(0, "bbox", [50, 50, 20, 20]), r"annotations\[0\] \(id 1\): bbox .* outside its image",
     "box_outside_image"),
    (_set(1, "category_id", 42), r"annotations\[1\] \(id 2\): unknown category_id 42",
     "unknown_category"),
    (_set(2, "image_id", 99), r"annotations\[2\] \(id 3\): unknown image_id 99",
     "unknown_image_id"),
    (_set(0, "bbox", [1, 2, 0, 5]), r"annotations\[0\] \(id 1\): bbox .* non-positive size",
     "bad_box"),
])
def test_bad_annotations_raise_or_are_counted(roboflow, tmp_path, edit, match, reason):
    ann_file = roboflow / "train" / "_annotations.coco.json"
    edit_coco(ann_file, edit)
    with pytest.raises(InputError, match=match) as err:
        import_real(roboflow, tmp_path / "out")
    assert str(ann_file) in str(err.value)
    report = import_real(roboflow, tmp_path / "out", skip_bad=True)
    train = report["splits"]["train"]
    assert train["skipped"] == {reason: 1} and train["annotations_out"] == 23
    assert len(train["skipped_examples"]) == 1


def test_missing_image_file(roboflow, tmp_path):
    name = _remove_first_image(roboflow)
    with pytest.raises(InputError, match=rf"images\[0\] \(id 0, {name}\): image file .* not found"):
        import_real(roboflow, tmp_path / "out")
    train = import_real(roboflow, tmp_path / "out", skip_bad=True)["splits"]["train"]
    assert train["skipped"] == {"missing_image": 1, "annotation_of_skipped_image": 5}
    assert (train["images_in"], train["images_out"], train["annotations_out"]) == (6, 5, 20)


def test_unmapped_category_with_error_policy(roboflow, tmp_path):
    cmap = tmp_path / "map.yaml"
    cmap.write_text("map: {crater: crater, rock: rock, boulder: rock, artifact: artifact}\n"
                    "unmapped: error\n")
    with pytest.raises(InputError, match=r"annotations\[3\] \(id 4\): category 'rocky region' "
                                         r"is not in the category map .*map.yaml"):
        import_real(roboflow, tmp_path / "out", map_file=cmap)
    train = import_real(roboflow, tmp_path / "out", map_file=cmap,
                        skip_bad=True)["splits"]["train"]
    assert train["skipped"] == {"unmapped_category": 6} and train["dropped"] == {}


def test_output_folder_safety(roboflow, tmp_path):
    with pytest.raises(InputError, match="must not overlap"):
        import_real(roboflow, roboflow / "converted")
    other = tmp_path / "precious"
    other.mkdir()
    (other / "notes.txt").write_text("keep me")
    with pytest.raises(InputError, match="not an earlier import-real output"):
        import_real(roboflow, other)
    assert (other / "notes.txt").is_file()
    import_real(roboflow, tmp_path / "out")
    import_real(roboflow, tmp_path / "out")  # an earlier import is replaced


def test_yolo_import(tmp_path):
    src = make_yolo(tmp_path / "yolo")
    report = import_real(src, tmp_path / "out")
    assert report["format"] == "yolo"
    train = report["splits"]["train"]
    assert (train["images_in"], train["images_out"], train["annotations_in"]) == (3, 3, 8)
    assert train["per_class"] == {"crater": 2, "rock": 2, "artifact": 2}
    assert train["dropped"] == {"rover path": 2}
    assert set(train["cameras"]) == {"pcam_colour", "ce4", "ce3_tcam"}
    records = {r.path.name.split("_")[0]: r for r in
               load_coco(tmp_path / "out" / "train" / "annotations.json")}
    np.testing.assert_allclose(records["chang4"].boxes, [[24, 24, 40, 40], [12, 12, 20, 20],
                                                         [6.4, 6.4, 19.2, 19.2]], atol=1e-4)
    assert records["chang4"].labels.tolist() == [1, 2, 3]
    assert len(records["C3"].boxes) == 0  # an image without a label file: background


def test_yolo_bad_input(tmp_path):
    src = make_yolo(tmp_path / "yolo")
    orphan = src / "train" / "labels" / "gone.txt"
    orphan.write_text("1 0.5 0.5 0.2 0.2\n")
    with pytest.raises(InputError, match=r"gone.txt: labels an image gone\.\* that is not in"):
        import_real(src, tmp_path / "out")
    orphan.unlink()
    label = src / "valid" / "labels" / f"{roboflow_name('PCAML-Q-004_A_2A.png', 0)[:-4]}.txt"
    label.write_text("9 0.5 0.5 0.2 0.2\n1 0.9 0.9 0.5 0.5\n")
    with pytest.raises(InputError, match=r"\.txt:1: class 9 has no name"):
        import_real(src, tmp_path / "out")
    valid = import_real(src, tmp_path / "out", skip_bad=True)["splits"]["valid"]
    assert valid["skipped"] == {"unknown_category": 1, "box_outside_image": 1}


def test_format_detection_errors(tmp_path):
    with pytest.raises(InputError, match="source folder not found"):
        import_real(tmp_path / "nope", tmp_path / "out")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="give --format"):
        import_real(tmp_path / "empty", tmp_path / "out")


@pytest.mark.parametrize("edit, match", [
    (lambda d: d["categories"][1].update(id=[1]),
     r"categories\[1\] \('artifact'\): 'id' must be an integer, got \[1\]"),
    (lambda d: d["categories"][2].update(id=d["categories"][1]["id"]),
     r"categories\[2\] \(.*\) reuses the id 1 of 'artifact'"),
])
def test_bad_category_ids_name_the_file(roboflow, tmp_path, edit, match):
    ann_file = roboflow / "train" / "_annotations.coco.json"
    edit_coco(ann_file, edit)
    with pytest.raises(InputError, match=match) as err:
        import_real(roboflow, tmp_path / "out")
    assert str(err.value).startswith(f"{ann_file}: ")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("edit, match, reason", [
    (lambda d: d["images"][0].update(id=[0]), r"images\[0\]: 'id' must be a number or a",
     "bad_image_entry"),
    (_set(0, "image_id", [0]), r"annotations\[0\] \(id 1\): unknown image_id \[0\]",
     "unknown_image_id"),
    (_set(0, "category_id", {"id": 1}), r"annotations\[0\] \(id 1\): unknown category_id",
     "unknown_category"),
])
def test_list_ids_are_bad_entries_not_type_errors(roboflow, tmp_path, edit, match, reason):
    ann_file = roboflow / "train" / "_annotations.coco.json"
    edit_coco(ann_file, edit)
    with pytest.raises(InputError, match=match):
        import_real(roboflow, tmp_path / "out")
    train = import_real(roboflow, tmp_path / "out", skip_bad=True)["splits"]["train"]
    assert train["skipped"].get(reason) == 1


def test_yolo_label_file_that_is_not_text(tmp_path):
    src = make_yolo(tmp_path / "yolo")
    label = src / "valid" / "labels" / f"{roboflow_name('PCAML-Q-004_A_2A.png', 0)[:-4]}.txt"
    label.write_bytes(b"0 0.5 0.5 0.2 0.2\n\x80\xff\x00 binary\n")
    with pytest.raises(InputError, match=r"\.txt: not a YOLO label file \(not UTF-8 text: "
                                         r"byte 0x80 at offset 18\)") as err:
        import_real(src, tmp_path / "out")
    assert "\n" not in str(err.value) and str(label) in str(err.value)
    valid = import_real(src, tmp_path / "out", skip_bad=True)["splits"]["valid"]
    assert valid["skipped"] == {"unreadable_labels": 1}
    assert (valid["images_in"], valid["images_out"], valid["annotations_in"]) == (1, 0, 2)
    orphan = src / "train" / "labels" / "gone.txt"  # a binary label without its image
    orphan.write_bytes(b"\x80\x81\n")
    with pytest.raises(InputError, match="gone.txt: labels an image gone"):
        import_real(src, tmp_path / "out2")


@pytest.mark.parametrize("name, content, match", [
    ("data.yaml", "names: [a, \n", r"data.yaml: not a YAML mapping with a 'names' entry \("),
    ("data.yaml", b"names: [\xff]\n", r"data.yaml: not a class names file \(not UTF-8 text\)"),
])
def test_bad_class_name_files_are_one_line(tmp_path, name, content, match):
    src = make_yolo(tmp_path / "yolo")
    path = src / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    with pytest.raises(InputError, match=match) as err:
        import_real(src, tmp_path / "out")
    assert "\n" not in str(err.value)

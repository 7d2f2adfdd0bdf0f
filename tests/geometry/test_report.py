import json

import cv2
import numpy as np
import pytest

from lunarnav_ml.errors import InputError
from lunarnav_ml.geometry.frames import rover_to_camera
from lunarnav_ml.geometry.lifter import LifterConfig
from lunarnav_ml.geometry.report import geometry_report, jitter_box, markdown_table, summarize


def _write_dataset(root, sc) -> None:
    (root / "images" / "left").mkdir(parents=True)
    (root / "images" / "right").mkdir(parents=True)
    cv2.imwrite(str(root / "images/left/0.png"), sc.left)
    cv2.imwrite(str(root / "images/right/0.png"), sc.right)
    r = sc.rig
    cam = {"height_m": r.height_m, "pitch_deg": r.pitch_deg, "roll_deg": 0.0, "fov_deg": 90.0,
           "baseline_m": r.baseline_m, "fx": r.focal_px, "fy": r.focal_px, "cx": r.cx, "cy": r.cy}
    center_cam = rover_to_camera(sc.center_rover, r.height_m, r.pitch_deg)[0]
    box = [float(sc.box[0] + 0.5), float(sc.box[1] + 0.5), float(sc.box[2]), float(sc.box[3])]
    ann = {"id": 1, "image_id": 1, "category_id": 1, "bbox": box, "ignore": False, "iscrowd": 0,
           "diameter_m": sc.crater.diameter, "center_cam_m": center_cam.tolist(),
           "near_rim_range_m": 8.0, "ellipse": sc.ellipse.to_array().tolist()}
    small = {**ann, "id": 2, "diameter_m": 1.0}  # below min_diameter_m: not evaluated
    coco = {"images": [{"id": 1, "file_name": "images/left/0.png", "right_file": "images/right/0.png",
                        "width": sc.left.shape[1], "height": sc.left.shape[0], "camera": cam}],
            "annotations": [ann, small], "categories": [{"id": 1, "name": "crater"}]}
    (root / "annotations.json").write_text(json.dumps(coco))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, crater_scene):
    root = tmp_path_factory.mktemp("geo_ds")
    _write_dataset(root, crater_scene)
    return root


def test_report_on_labelled_boxes(dataset, tmp_path):
    m = geometry_report(dataset, tmp_path / "out")
    assert m["overall"]["n"] == 1 and m["overall"]["n_lifted"] == 1
    assert m["overall"]["pd_3d"] == 1.0
    assert m["overall"]["center_3sigma_m"] < 1.0
    for name in ("geometry_metrics.json", "geometry_craters.json", "geometry_report.md",
                 "geometry_errors.png"):
        assert (tmp_path / "out" / name).stat().st_size > 0
    md = (tmp_path / "out" / "geometry_report.md").read_text()
    assert "paper stereo" in md
    assert f"σ (its larger horizontal axis) {m['center_err_over_sigma_median']:.2f}" in md
    rows = json.loads((tmp_path / "out" / "geometry_craters.json").read_text())
    assert rows[0]["ok"] and rows[0]["center_err_m"] < 0.35
    assert rows[0]["crest_search_px"] in (6, 12)


def test_report_with_detections(dataset, tmp_path):
    ann = json.loads((dataset / "annotations.json").read_text())["annotations"][0]
    far = [{"image_id": 1, "category_id": 1, "bbox": [0, 0, 10, 10], "score": 0.9}]
    m = geometry_report(dataset, tmp_path / "a", detections=far, plots=False)
    assert m["reasons"] == {"not_detected": 1} and m["overall"]["pd_3d"] == 0.0
    hit = [{"image_id": 1, "category_id": 1, "bbox": ann["bbox"], "score": 0.9}]
    m = geometry_report(dataset, tmp_path / "b", detections=hit, ellipse_source="label", plots=False)
    assert m["overall"]["n_lifted"] == 1


def test_box_jitter_moves_each_edge_by_its_fraction_of_the_side():
    box = np.array([100.0, 200.0, 80.0, 20.0])
    rng = np.random.default_rng(0)
    moved = np.array([jitter_box(box, 0.05, rng) for _ in range(4000)])
    left, top = moved[:, 0] - box[0], moved[:, 1] - box[1]
    right, bottom = moved[:, 0] + moved[:, 2] - 180.0, moved[:, 1] + moved[:, 3] - 220.0
    for edge, side in ((left, 80), (right, 80), (top, 20), (bottom, 20)):
        assert abs(edge.mean()) < 0.1 * side * 0.05 * 3
        assert edge.std() == pytest.approx(0.05 * side, rel=0.05)
    assert np.all(jitter_box(np.array([0.0, 0.0, 1.0, 1.0]), 0.4, rng)[2:] >= 2.0)


def test_report_with_jittered_boxes(dataset, tmp_path):
    a = geometry_report(dataset, tmp_path / "a", box_jitter=0.05, seed=3, plots=False)
    b = geometry_report(dataset, tmp_path / "b", box_jitter=0.05, seed=3, plots=False)
    c = geometry_report(dataset, tmp_path / "c", box_jitter=0.05, seed=4, plots=False)
    rows = [json.loads((tmp_path / k / "geometry_craters.json").read_text())[0] for k in "abc"]
    assert rows[0] == {**rows[1], "fit_s": rows[0]["fit_s"], "lift_s": rows[0]["lift_s"],
                       "stereo_s": rows[0]["stereo_s"]}  # same seed, same result
    assert rows[0]["ellipse"] != rows[2]["ellipse"]  # another seed, another box
    assert a["settings"]["box_jitter"] == 0.05 and c["settings"]["seed"] == 4
    assert b["overall"]["n"] == 1
    assert "moved by N(0, 0.05" in (tmp_path / "a" / "geometry_report.md").read_text()
    with pytest.raises(InputError, match="box_jitter"):
        geometry_report(dataset, tmp_path / "d", box_jitter=float("nan"))
    with pytest.raises(InputError, match="box_jitter"):
        geometry_report(dataset, tmp_path / "d", box_jitter=0.1, detections=[])


def test_report_bad_inputs(tmp_path, dataset):
    with pytest.raises(InputError, match="annotations"):
        geometry_report(tmp_path / "nowhere", tmp_path / "out")
    with pytest.raises(InputError, match="ellipse_source"):
        geometry_report(dataset, tmp_path / "out", ellipse_source="magic")


@pytest.mark.parametrize("field, value, message", [
    ("bbox", None, r"annotations\[0\] \(id 1\): bbox: expected shape \(4\)"),
    ("bbox", [1.0, 2.0, -3.0, 4.0], "non-positive width or height"),
    ("diameter_m", None, "diameter_m must be a positive finite number"),
    ("diameter_m", float("nan"), "diameter_m must be a positive finite number"),
    ("center_cam_m", [float("nan"), 0.0, 9.0], "center_cam_m: contains NaN"),
    ("center_cam_m", [0.0, 9.0], r"center_cam_m: expected shape \(3\)"),
])
def test_malformed_crater_labels_name_the_file_and_field(dataset, tmp_path, field, value, message):
    coco = json.loads((dataset / "annotations.json").read_text())
    coco["annotations"][0][field] = value
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(coco))
    with pytest.raises(InputError, match=f"bad.json: {message}" if "annotations" in message
                       else message) as err:
        geometry_report(bad, tmp_path / "out", plots=False)
    assert str(bad) in str(err.value)
    assert not (tmp_path / "out").exists()  # nothing written


def test_corrupt_json_and_bad_detections_name_the_file(dataset, tmp_path):
    bad = tmp_path / "corrupt.json"
    bad.write_text('{"images": [')
    with pytest.raises(InputError, match="corrupt.json: annotations is not valid JSON"):
        geometry_report(bad, tmp_path / "out")
    listed = tmp_path / "listed.json"
    listed.write_text("[]")
    with pytest.raises(InputError, match="listed.json: annotations must hold an object"):
        geometry_report(listed, tmp_path / "out")
    dets = tmp_path / "dets.json"
    dets.write_text(json.dumps([{"image_id": 1, "category_id": 1, "bbox": [1, 2, None, 3]}]))
    with pytest.raises(InputError, match=r"dets.json: detections\[0\]: bbox"):
        geometry_report(dataset, tmp_path / "out", detections=dets)
    (tmp_path / "cam.json").write_text(json.dumps({**json.loads(
        (dataset / "annotations.json").read_text()), "images": [
        {**json.loads((dataset / "annotations.json").read_text())["images"][0], "camera": {"fx": 100.0}}]}))
    with pytest.raises(InputError, match=r"0.png \(image id 1\): camera: missing key"):
        geometry_report(tmp_path / "cam.json", tmp_path / "out")


def test_summarize_three_sigma_known_answer():
    rows = [{"diameter_m": 5.0, "near_rim_range_m": 16.0, "ok": True, "reason": "ok",
             "center_err_m": e, "center_err_xy_m": [e, 0.0], "diameter_err_m": -e,
             "sigma_h_m": 0.5} for e in (0.3, 0.4, 1.4)]
    rows.append({"diameter_m": 5.0, "near_rim_range_m": 9.0, "ok": False, "reason": "lift:x"})
    m = summarize(rows)
    near = m["per_diameter"]["5.0"]["range_15_20"]
    assert near["n"] == 3 and near["n_lifted"] == 3
    assert near["center_3sigma_m"] == pytest.approx(3 * np.sqrt((0.09 + 0.16 + 1.96) / 3))
    # the paper's sigma_p: spread about the mean error vector (0.7, 0)
    assert near["center_3sigma_paper_m"] == pytest.approx(
        3 * np.sqrt((0.16 + 0.09 + 0.49) / 3))
    assert near["pd_3d"] == pytest.approx(2 / 3)  # 1.4 m > max(1 m, 0.25 D = 1.25 m): a miss


def test_the_paper_stereo_convention_keeps_the_ranges_with_significant_detection():
    def row(rng, e):
        return {"diameter_m": 5.0, "near_rim_range_m": rng, "ok": True, "reason": "ok",
                "center_err_m": e, "center_err_xy_m": [e, 0.0], "diameter_err_m": 0.0}
    rows = [row(16.0, e) for e in (0.3, 0.4, 1.4)] + [row(12.2, 3.0), row(11.8, 2.0)]
    m = summarize(rows)["per_diameter"]["5.0"]
    sig, allr = m["significant_ranges"], m["all_ranges"]
    assert sig["n"] == 3 and allr["n"] == 5  # the 12 m bin (Pd 0) is left out
    assert sig["center_3sigma_paper_m"] == pytest.approx(3 * np.sqrt((0.16 + 0.09 + 0.49) / 3))
    assert "3σp center, significant ranges" in markdown_table(
        {**summarize(rows), "settings": {"ellipse_source": "fit", "n_images": 1}})


def test_report_on_rendered_disparity(tmp_path, crater_scene):
    """The dataset's own disparity isolates the lifter: exact inputs, exact answer."""
    root = tmp_path / "ds"
    _write_dataset(root, crater_scene)
    with pytest.raises(InputError, match="disparity_file"):
        geometry_report(root, tmp_path / "a", disparity="rendered", plots=False)
    with pytest.raises(InputError, match="disparity"):
        geometry_report(root, tmp_path / "a", disparity="magic", plots=False)
    r = crater_scene.rig
    np.save(root / "disp.npy", (r.focal_px * r.baseline_m / crater_scene.depth).astype(np.float32))
    coco = json.loads((root / "annotations.json").read_text())
    coco["images"][0]["disparity_file"] = "disp.npy"
    (root / "annotations.json").write_text(json.dumps(coco))
    m = geometry_report(root, tmp_path / "b", disparity="rendered", ellipse_source="label",
                        lifter=LifterConfig(rim_offset=0.0, rim_offset_m=0.0,
                                                rim_offset_view=0.0), plots=False)
    assert m["settings"]["disparity"] == "rendered" and m["overall"]["n_lifted"] == 1
    assert m["overall"]["center_median_m"] < 0.05


def test_eval_cli_geometry_options(dataset, tmp_path, capsys):
    from lunarnav_ml.cli import main

    out = tmp_path / "cli"
    assert main(["eval", "--task", "geometry", "--gt", str(dataset), "--ellipse-source", "box",
                 "--box-jitter", "0.02", "--seed", "7", "--out", str(out)]) == 0
    m = json.loads((out / "geometry_metrics.json").read_text())
    assert m["settings"]["ellipse_source"] == "box" and m["settings"]["disparity"] == "sgbm"
    assert m["settings"]["box_jitter"] == 0.02 and m["settings"]["seed"] == 7
    assert m["overall"]["n_lifted"] > 0
    # the stricter hidden-rim test, far above any crest's rise: every lift rejected by it
    assert main(["eval", "--task", "geometry", "--gt", str(dataset), "--min-flank-rise-px",
                 "1000", "--out", str(tmp_path / "strict")]) == 0
    strict = json.loads((tmp_path / "strict" / "geometry_metrics.json").read_text())
    assert strict["overall"]["n_lifted"] == 0 and strict["reasons"]["lift:near_rim_hidden"] > 0
    assert main(["eval", "--task", "geometry", "--gt", str(dataset), "--min-flank-rise-px",
                 "-1", "--out", str(tmp_path / "z")]) == 2
    assert "--min-flank-rise-px must be a finite number >= 0 or 'none'" in capsys.readouterr().err
    assert not (tmp_path / "z").exists()
    # a jitter with detections: one line, exit 2
    dets = tmp_path / "dets.json"
    dets.write_text("[]")
    assert main(["eval", "--task", "geometry", "--gt", str(dataset), "--test-results", str(dets),
                 "--box-jitter", "0.02", "--out", str(tmp_path / "y")]) == 2
    assert "box_jitter" in capsys.readouterr().err
    # no rendered disparity in this dataset: one line, exit 2
    assert main(["eval", "--task", "geometry", "--gt", str(dataset), "--disparity", "rendered",
                 "--out", str(tmp_path / "x")]) == 2
    assert "disparity_file" in capsys.readouterr().err


def test_rendered_disparity_reader_names_the_file(tmp_path):
    from lunarnav_ml.utils.images import read_disparity

    (tmp_path / "bad.npy").write_bytes(b"not an array")
    with pytest.raises(InputError, match="bad.npy"):
        read_disparity(tmp_path, {"id": 3, "disparity_file": "bad.npy"})
    with pytest.raises(InputError, match="gone.npy"):
        read_disparity(tmp_path, {"id": 3, "disparity_file": "gone.npy"})
    np.save(tmp_path / "ok.npy", np.ones((2, 3), np.float32))
    assert read_disparity(tmp_path, {"id": 3, "disparity_file": "ok.npy"}).dtype == np.float64

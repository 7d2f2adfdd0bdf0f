"""Baseline report: protocol targets are scored whether or not the camera labelled them."""

import numpy as np
import pytest

from lunarnav_ml.baselines.report import _targets, match_detections, with_protocol_target
from lunarnav_ml.errors import InputError

CAMERA = {"height_m": 1.5, "pitch_deg": 20.0, "roll_deg": 0.0}


def _img(d=5.0, near=15.0):
    return {"id": 1, "camera": CAMERA,
            "protocol_item": {"diameter_m": d, "near_rim_range_m": near, "approach_deg": 0.0}}


def test_unlabelled_target_is_added_straight_ahead():
    background = {"diameter_m": 3.9879, "near_rim_range_m": 15.2,
                  "center_cam_m": [0.0, 1.0, 17.0]}
    crs = with_protocol_target(_img(), [background])
    assert len(crs) == 2 and crs[-1]["protocol_target"]
    (target,) = _targets(_img(), crs, 0.0)
    assert target["diameter_m"] == 5.0  # never the 4 m background crater
    dets = [np.array([17.7, 0.1, 0.0]), np.array([40.0, 5.0, 0.0])]
    records, false_alarms = match_detections([target], dets, crs, _img())
    assert records[0]["hit"] and records[0]["dx"] == pytest.approx(0.2)
    assert false_alarms == 1  # the detection 40 m out matches no crater


def test_labelled_target_is_not_duplicated():
    labelled = {"diameter_m": 5.0, "near_rim_range_m": 15.3, "center_cam_m": [0.0, 1.0, 17.0]}
    assert with_protocol_target(_img(), [labelled]) == [labelled]
    assert with_protocol_target({"id": 2, "camera": CAMERA}, [labelled]) == [labelled]


def test_missed_target_counts_as_a_miss():
    crs = with_protocol_target(_img(d=10.0, near=19.0), [])
    records, _ = match_detections(_targets(_img(10.0, 19.0), crs, 0.0), [], crs,
                                  _img(10.0, 19.0))
    (rec,) = records
    assert rec["diameter_m"] == 10.0 and rec["near_rim_range_m"] == 19.0
    assert not rec["hit"] and np.isnan(rec["dx"])


def test_lidar_target_hidden_without_returns_on_its_far_half(tmp_path):
    from lunarnav_ml.baselines.report import _visible

    img = {**_img(d=10.0, near=15.0), "lidar_file": "scan.npz"}
    (target,) = with_protocol_target(img, [])  # centre (20, 0)
    far_wall = np.column_stack([np.linspace(21, 24.5, 30), np.zeros(30), np.zeros(30)])
    np.savez(tmp_path / "scan.npz", points_true=far_wall)
    assert _visible(tmp_path, img, target, "lidar")
    np.savez(tmp_path / "scan.npz", points_true=far_wall - (10.0, 0.0, 0.0))  # in front of the crater
    assert not _visible(tmp_path, img, target, "lidar")
    assert _visible(tmp_path, img, target, "stereo")
    assert not _visible(tmp_path, img, {**target, "ignore_reasons": ["occluded"]}, "stereo")


def test_lidar_prior_offset_limit_follows_the_prior_sigma(tmp_path, monkeypatch):
    """Without a lidar_config the placement limit is four prior standard deviations (at
    least 1 m); a NaN sigma is refused."""
    import json

    from lunarnav_ml.baselines import report

    (tmp_path / "annotations.json").write_text(
        json.dumps({"images": [{**_img(), "lidar_file": "x.npz"}], "annotations": []}))
    seen = []
    monkeypatch.setattr(report, "_run_lidar", lambda root, img, crs, rng, cfg, *a: (
        seen.append(cfg.max_prior_offset_m), ([], 0.0))[1])
    monkeypatch.setattr(report, "_visible", lambda *a: True)
    for sigma in (1.0, 2.5, 0.1):
        m = report.baseline_report(tmp_path, tmp_path / "out", prior_sigma_m=sigma,
                                   progress=False)
        assert m["pd_all"] == 0.0
    assert seen == [4.0, 10.0, 1.0]
    with pytest.raises(InputError, match="prior_sigma_m"):
        report.baseline_report(tmp_path, tmp_path / "out", prior_sigma_m=float("nan"))


_LABEL = ('{"images": [], "annotations": [{"id": 7, "image_id": 1, "category_id": 1, '
          '"bbox": [1, 1, 2, 2], "diameter_m": %s, "center_cam_m": %s}]}')


@pytest.mark.parametrize("text, message", [
    ('{"images": [', "not valid JSON"),
    ('{"images": [], "annotations": {}}', "missing the 'annotations' list"),
    (_LABEL % ("-5", "[0, 1, 9]"), r"annotations\[0\] \(id 7\): diameter_m"),
    (_LABEL % ("5", "[0, NaN, 9]"), r"\(id 7\): center_cam_m: contains NaN"),
])
def test_malformed_annotations_name_the_file_and_field(tmp_path, text, message):
    from lunarnav_ml.baselines.report import baseline_report

    bad = tmp_path / "bad.json"
    bad.write_text(text)
    with pytest.raises(InputError, match=message) as err:
        baseline_report(bad, tmp_path / "out", method="stereo")
    assert str(bad) in str(err.value)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("bad", ["right", "left", "right_missing"])
def test_stereo_baseline_names_the_unreadable_image_and_the_annotation_file(tmp_path, bad):
    import json

    import cv2

    from lunarnav_ml.baselines.report import baseline_report

    cam = {**CAMERA, "fx": 32.0, "fy": 32.0, "cx": 31.5, "cy": 31.5, "baseline_m": 0.3}
    img = {"id": 1, "file_name": "left.png", "right_file": "right.png", "width": 64,
           "height": 64, "camera": cam}
    for name in ("left.png", "right.png"):
        cv2.imwrite(str(tmp_path / name), np.full((64, 64), 100, np.uint8))
    if bad == "right_missing":
        (tmp_path / "right.png").unlink()
    else:
        (tmp_path / f"{bad}.png").write_text("not a png")
    ann = tmp_path / "annotations.json"
    ann.write_text(json.dumps({"images": [img], "annotations": []}))
    key, name = ("file_name", "left.png") if bad == "left" else ("right_file", "right.png")
    with pytest.raises(InputError, match=rf"^{ann}: image id 1: cannot read its {key} "
                                         rf"{tmp_path / name} \(missing, corrupt"):
        baseline_report(tmp_path, tmp_path / "out", method="stereo", progress=False)
    assert not (tmp_path / "out").exists()

"""``lunarnav import-real`` and ``lunarnav eval --task transfer``: outputs, and bad input as
one line on stderr with exit code 2."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from lunarnav_ml.cli import main
from tests.realdata.fixtures import make_roboflow


def _one_line_error(capsys, *needles):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    assert all(n in err[0] for n in needles), err[0]


def test_import_real_then_transfer_eval(tmp_path, capsys):
    src, out = make_roboflow(tmp_path / "export"), tmp_path / "imported"
    assert main(["import-real", str(src), "--out", str(out), "--splits", "valid"]) == 0
    assert "valid: 2/2 images (2 source frames), 8/10 boxes" in capsys.readouterr().out
    gt_path = out / "valid" / "annotations.json"
    gt = json.loads(gt_path.read_text())
    perfect = [{"image_id": a["image_id"], "category_id": a["category_id"], "bbox": a["bbox"],
                "score": 0.9} for a in gt["annotations"]]
    (tmp_path / "dets.json").write_text(json.dumps(perfect))
    report = tmp_path / "transfer"
    assert main(["eval", "--task", "transfer", "--gt", str(gt_path), "--test-results",
                 str(tmp_path / "dets.json"), "--out", str(report), "--no-progress"]) == 0
    assert "crater recall@1/3/5/10 1.000 / 1.000 / 1.000 / 1.000" in capsys.readouterr().out
    metrics = json.loads((report / "transfer_metrics.json").read_text())
    assert metrics["all"]["per_class"]["crater"]["recall@1"] == 1.0
    assert set(metrics["per_camera"]) == {"ce3_tcam", "pcam_pan"}
    assert (report / "gallery.png").is_file() and (report / "transfer_report.md").is_file()


def test_import_real_bad_input_is_one_line_exit_2(tmp_path, capsys):
    src = make_roboflow(tmp_path / "export")
    ann_file = src / "valid" / "_annotations.coco.json"
    data = json.loads(ann_file.read_text())
    data["annotations"][0]["bbox"] = [60, 60, 30, 30]
    ann_file.write_text(json.dumps(data))
    assert main(["import-real", str(src), "--out", str(tmp_path / "o")]) == 2
    _one_line_error(capsys, "lunarnav import-real: error:", str(ann_file), "annotations[0]")
    assert not (tmp_path / "o").exists()
    assert main(["import-real", str(src), "--out", str(tmp_path / "o"), "--skip-bad"]) == 0
    report = json.loads((tmp_path / "o" / "import_report.json").read_text())
    assert report["splits"]["valid"]["skipped"] == {"box_outside_image": 1}


def test_transfer_needs_exactly_one_detection_source(tmp_path, capsys):
    src, out = make_roboflow(tmp_path / "export"), tmp_path / "imported"
    main(["import-real", str(src), "--out", str(out)])
    gt = str(out / "valid" / "annotations.json")
    assert main(["eval", "--task", "transfer", "--gt", gt, "--out", str(tmp_path / "r")]) == 2
    _one_line_error(capsys, "--checkpoint, --onnx", "got none")
    assert main(["eval", "--task", "transfer", "--gt", gt, "--onnx", "m.onnx", "--test-results",
                 "r.json", "--out", str(tmp_path / "r")]) == 2
    _one_line_error(capsys, "got --onnx, --test-results")


def test_missing_source_in_a_fresh_process(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "lunarnav_ml.cli", "import-real",
                           str(tmp_path / "nope"), "--out", str(tmp_path / "o")],
                          check=False, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines() == [
        f"lunarnav import-real: error: {tmp_path / 'nope'}: source folder not found"]


def test_help(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["import-real", "--help"])
    assert exc.value.code == 0 and "--skip-bad" in capsys.readouterr().out


def test_transfer_eval_with_tta_names_it_and_rejects_bad_scales(tmp_path, capsys):
    src, out = make_roboflow(tmp_path / "export"), tmp_path / "imported"
    main(["import-real", str(src), "--out", str(out), "--splits", "valid"])
    gt = str(out / "valid" / "annotations.json")
    weights = str(Path(__file__).resolve().parents[2] / "lunarnav_ml" / "weights" / "small.pt")
    report = tmp_path / "tta"
    assert main(["eval", "--task", "transfer", "--gt", gt, "--checkpoint", weights, "--img-size",
                 "160", "--tta", "--out", str(report), "--no-progress", "--overlays", "0"]) == 0
    assert "crater recall@1/3/5/10" in capsys.readouterr().out
    text = (report / "transfer_report.md").read_text()
    assert "test-time augmentation: sides [128, 160, 192] px, each mirrored" in text
    assert json.loads((report / "detections.json").read_text())
    assert main(["eval", "--task", "transfer", "--gt", gt, "--checkpoint", weights, "--tta",
                 "--tta-scales", "1", "-0.5", "--out", str(tmp_path / "bad")]) == 2
    _one_line_error(capsys, "tta scales")
    assert not (tmp_path / "bad").exists()

"""The command line: every subcommand has --help; bad input is one line on stderr, exit 2."""

import subprocess
import sys

import pytest

from lunarnav_ml.cli import build_parser, main

SUBCOMMANDS = ("synth", "train", "eval", "export", "detect", "average", "demo")


def test_every_subcommand_is_registered():
    parser = build_parser()
    choices = parser._subparsers._group_actions[0].choices
    for name in SUBCOMMANDS:
        assert name in choices


@pytest.mark.parametrize("name", SUBCOMMANDS)
def test_help(name, capsys):
    with pytest.raises(SystemExit) as exc:
        main([name, "--help"])
    assert exc.value.code == 0
    assert "usage: lunarnav" in capsys.readouterr().out


def test_missing_file_is_one_line_exit_2(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "lunarnav_ml.cli", "eval", "--gt", str(tmp_path / "nope.json"),
         "--threshold", "0.5", "--test-results", str(tmp_path / "r.json"),
         "--out", str(tmp_path / "o")],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "nope.json" in lines[0] and "Traceback" not in proc.stderr
    assert not (tmp_path / "o").exists()


def test_corrupt_json_names_the_file(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    proc = subprocess.run(
        [sys.executable, "-m", "lunarnav_ml.cli", "eval", "--gt", str(bad), "--threshold", "0.5",
         "--test-results", str(bad), "--out", str(tmp_path / "o")],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert proc.returncode == 2 and "bad.json" in proc.stderr and "Traceback" not in proc.stderr


def test_eval_detection_report_from_results(tiny_coco, tmp_path):
    import json

    gt_path = tiny_coco["val"]
    gt = json.loads(gt_path.read_text())
    results = [{"image_id": a["image_id"], "category_id": a["category_id"], "bbox": a["bbox"],
                "score": 0.9} for a in gt["annotations"] if not a.get("ignore")]
    res_path = tmp_path / "res.json"
    res_path.write_text(json.dumps(results))
    out = tmp_path / "report"
    code = main(["eval", "--gt", str(gt_path), "--test-results", str(res_path),
                 "--threshold", "0.5", "--out", str(out), "--overlays", "2", "--no-progress"])
    assert code == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["coco"]["per_class"]["crater"]["AP50"] > 0.99


def test_demo_bad_settings_are_one_line_and_leave_nothing(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--synth-config", str(tmp_path / "nope.yaml")]) == 2
    assert main(["demo", "--out", str(out), "--image-size", "100"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "nope.yaml" in err[0] and "multiple of 32" in err[1]
    assert not out.exists()


def test_an_output_path_that_is_a_file_is_one_line_exit_2(tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("not a folder")
    code = main(["synth", str(afile), "--n", "1", "--size", "64", "--no-stereo"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "afile" in err
    assert afile.read_text() == "not a folder"


def test_geometry_eval_bad_edge_offsets_is_one_line(tmp_path, capsys):
    bad = tmp_path / "rim_offset.json"
    bad.write_text('{"box_ellipses": {"box_rim_offset": NaN}}')
    assert main(["eval", "--task", "geometry", "--gt", str(tmp_path / "a.json"),
                 "--edge-offsets", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "box_ellipses.box_rim_offset" in err[0]

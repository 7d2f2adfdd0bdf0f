"""benchmarks/time_small_read.py: every design read on the same frames, one row each."""

import pytest

from tests.bench_scripts import load_script
from tests.detector_fixtures import make_coco

timing = load_script("time_small_read")


def test_designs_are_timed_in_turns_and_rows_name_them(tmp_path, onnx_path, capsys):
    gt = make_coco(tmp_path / "set", n_images=3, size=96)
    assert timing.main(["--frames", str(gt), "--n", "2", "--model", str(onnx_path),
                        "--repeats", "2", "--design=--no-box-refiner",
                        "--design=--small-read 192 --no-box-refiner",
                        "--design=--small-read 192 --small-read-band 0.2 0.7"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith("2 frames of ") and len(lines) == 4
    ms = [float(line.split()[0]) for line in lines[1:]]
    assert all(t > 0 for t in ms) and "x 1.00  --no-box-refiner" in lines[1]
    assert lines[2].endswith("  --small-read 192 --no-box-refiner")
    ratio = float(lines[3].split("x")[1].split()[0])  # each row against the first design
    assert ratio == pytest.approx(ms[2] / ms[0], rel=0.05) and "-band 0.2 0.7" in lines[3]


def test_a_tta_design_is_parsed_as_the_commands_parse_it(tmp_path, onnx_path, capsys):
    gt = make_coco(tmp_path / "set", n_images=2, size=96)
    assert timing.main(["--frames", str(gt), "--n", "1", "--model", str(onnx_path),
                        "--repeats", "1", "--design=--no-box-refiner",
                        "--design=--tta --tta-scales 1 1.5 --no-box-refiner"]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1].endswith("--tta-scales 1 1.5 "
                                                                      "--no-box-refiner")

"""``lunarnav export`` / ``lunarnav bench`` and the top-level export/ scripts."""

import subprocess
import sys
from pathlib import Path

import cv2
import pytest

from lunarnav_ml.cli import build_parser
from lunarnav_ml.errors import ConfigError, InputError, LunarNavError
from lunarnav_ml.export.bench import synthetic_frame
from lunarnav_ml.export.cli import main
from lunarnav_ml.runtime import OnnxDetector

ROOT = Path(__file__).parents[2]


@pytest.fixture(scope="module")
def checkpoint(parts, tmp_path_factory):
    from lunarnav_ml.training.api import Detector

    out = tmp_path_factory.mktemp("ckpt") / "nano.pt"
    return Detector(parts.model, 128, list(parts.class_names), "nano").save(out)


def parse(*argv):
    return build_parser(("lunarnav_ml.export.cli",)).parse_args(argv)


def test_export_with_int8(checkpoint, tmp_path, capsys):
    calib = tmp_path / "calib"
    calib.mkdir()
    for i in range(3):
        cv2.imwrite(str(calib / f"{i}.png"), synthetic_frame(128, seed=i))
    args = parse("export", "--checkpoint", str(checkpoint), "--out", str(tmp_path / "m.onnx"),
                 "--nms", "--int8-out", str(tmp_path / "m8.onnx"), "--calib", str(calib))
    assert args.func(args) == 0
    assert "m8.onnx (int8, 3 calibration images)" in capsys.readouterr().out
    fp32, int8 = OnnxDetector(tmp_path / "m.onnx"), OnnxDetector(tmp_path / "m8.onnx")
    assert fp32.metadata.nms_in_graph and fp32.metadata.precision == "fp32"
    assert int8.metadata.nms_in_graph and int8.metadata.precision == "int8"
    assert len(int8.predict([synthetic_frame(128)], conf_thres=0.001)[0]["boxes"]) > 0


def test_int8_needs_calibration_images(checkpoint, tmp_path):
    args = parse("export", "--checkpoint", str(checkpoint), "--out", str(tmp_path / "m.onnx"),
                 "--int8-out", str(tmp_path / "m8.onnx"))
    with pytest.raises(ConfigError, match="--calib"):
        args.func(args)
    assert not (tmp_path / "m.onnx").exists()


def test_bench_prints_median_and_p90(onnx_path, capsys):
    args = parse("bench", "--onnx", str(onnx_path), "--sizes", "64", "--runs", "2",
                 "--warmup", "0", "--threads", "1", "2")
    assert args.func(args) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2 and all("median" in ln and "p90" in ln and "GFLOP/s" in ln
                                   for ln in lines)


def test_bench_eager_torch(checkpoint, capsys):
    args = parse("bench", "--checkpoint", str(checkpoint), "--sizes", "64", "--runs", "1",
                 "--warmup", "0")
    assert args.func(args) == 0
    assert "torch-eager" in capsys.readouterr().out


def test_bench_frame_size_reaches_the_timer(onnx_path, capsys, monkeypatch):
    from lunarnav_ml.export import bench

    seen = []
    real = bench.bench_onnx
    monkeypatch.setattr(bench, "bench_onnx",
                        lambda *a, **kw: seen.append(kw["frame_size"]) or real(*a, **kw))
    args = parse("bench", "--onnx", str(onnx_path), "--sizes", "64", "--runs", "1",
                 "--warmup", "0", "--frame-size", "128")
    assert args.func(args) == 0
    assert seen == [128] and "median" in capsys.readouterr().out
    args = parse("bench", "--onnx", str(onnx_path), "--frame-size", "0")
    with pytest.raises(ConfigError, match="--frame-size"):
        args.func(args)


def test_bench_needs_a_model():
    args = parse("bench")
    with pytest.raises(ConfigError, match="--onnx"):
        args.func(args)


def test_bench_checks_every_file_before_timing(onnx_path, tmp_path, capsys):
    bad = tmp_path / "cut.onnx"
    bad.write_bytes(onnx_path.read_bytes()[:300])
    args = parse("bench", "--onnx", str(onnx_path), str(bad), "--sizes", "64", "--runs", "1")
    with pytest.raises(InputError, match="cut.onnx: not a loadable ONNX model"):
        args.func(args)
    assert capsys.readouterr().out == ""  # no timing line printed before the error


def test_errors_are_one_line_exit_2(tmp_path, capsys):
    code = main(["export", "--checkpoint", str(tmp_path / "nope.pt"), "--out",
                 str(tmp_path / "m.onnx")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "nope.pt" in err


@pytest.mark.parametrize(("script", "command"), [("export_onnx.py", "export"),
                                                  ("bench.py", "bench")])
def test_top_level_scripts_are_thin_entry_points(script, command):
    proc = subprocess.run([sys.executable, str(ROOT / "export" / script), "--help"],
                          check=False, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert f"usage: lunarnav {command}" in proc.stdout


@pytest.mark.parametrize("calib", ["missing", "empty", "text"])
def test_bad_calibration_images_are_found_before_export(checkpoint, tmp_path, calib):
    folder = tmp_path / "calib"
    if calib != "missing":
        folder.mkdir()
    if calib == "text":
        (folder / "a.png").write_text("not a png")
    args = parse("export", "--checkpoint", str(checkpoint), "--out", str(tmp_path / "m.onnx"),
                 "--int8-out", str(tmp_path / "m8.onnx"), "--calib", str(folder))
    with pytest.raises(InputError, match="calib"):
        args.func(args)
    assert sorted(p.name for p in tmp_path.iterdir()) == (["calib"] if calib != "missing"
                                                          else [])


def _calib_folder(tmp_path):
    calib = tmp_path / "calib"
    calib.mkdir()
    cv2.imwrite(str(calib / "0.png"), synthetic_frame(128))
    return calib


@pytest.mark.parametrize(("option", "where", "match"), [
    ("--int8-out", "folder", "adir: output file is an existing folder"),
    ("--int8-out", "under_file", "m.onnx: cannot write under .*afile, which is a file"),
    ("--int8-out", "same", "--int8-out: .* is also --out"),
    ("--out", "folder", "adir: output file is an existing folder"),
    ("--out", "under_file", "m.onnx: cannot write under .*afile"),
])
def test_unwritable_outputs_are_refused_before_export(checkpoint, tmp_path, monkeypatch,
                                                      option, where, match):
    from lunarnav_ml.export import onnx_export

    monkeypatch.setattr(onnx_export, "export_onnx", lambda *a, **kw: pytest.fail("exported"))
    calib = _calib_folder(tmp_path)
    (tmp_path / "afile").write_text("x")
    (tmp_path / "adir").mkdir()
    target = {"folder": tmp_path / "adir", "under_file": tmp_path / "afile" / "m.onnx",
              "same": tmp_path / "m.onnx"}[where]
    paths = {"--out": tmp_path / "m.onnx", "--int8-out": tmp_path / "m8.onnx", option: target}
    args = parse("export", "--checkpoint", str(checkpoint), "--out", str(paths["--out"]),
                 "--int8-out", str(paths["--int8-out"]), "--calib", str(calib))
    with pytest.raises(LunarNavError, match=match):
        args.func(args)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir", "afile", "calib"]


def test_failed_quantization_leaves_no_fp32_file(checkpoint, tmp_path, monkeypatch):
    from lunarnav_ml.export import quantize

    def fail(*a, **kw):
        raise InputError("quantization failed")

    monkeypatch.setattr(quantize, "quantize_int8", fail)
    calib = _calib_folder(tmp_path)
    args = parse("export", "--checkpoint", str(checkpoint), "--out", str(tmp_path / "m.onnx"),
                 "--int8-out", str(tmp_path / "m8.onnx"), "--calib", str(calib))
    with pytest.raises(InputError, match="quantization failed"):
        args.func(args)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calib"]


@pytest.mark.parametrize("model", ["onnx", "checkpoint"])
def test_bench_sizes_must_be_multiples_of_the_stride(onnx_path, checkpoint, capsys, model):
    path = onnx_path if model == "onnx" else checkpoint
    args = parse("bench", f"--{model}", str(path), "--sizes", "64", "100", "--runs", "1",
                 "--warmup", "0")
    with pytest.raises(ConfigError, match=rf"--sizes 100: .*multiples of 32 .*{path.name}"):
        args.func(args)
    assert capsys.readouterr().out == ""  # refused before the first timing


def test_bench_fixed_input_model_takes_its_own_size_only(onnx_static_path, capsys):
    args = parse("bench", "--onnx", str(onnx_static_path), "--sizes", "64", "--runs", "1")
    with pytest.raises(ConfigError, match="--sizes 64: .*fixed input"):
        args.func(args)
    assert capsys.readouterr().out == ""


@pytest.mark.parametrize(("argv", "match"), [
    (["--warmup", "-1"], "--warmup must be >= 0, got -1"),
    (["--runs", "0"], "--runs must be >= 1"),
    (["--threads", "1", "0"], "--threads must be >= 1"),
    (["--sizes", "-32"], "--sizes must be >= 1"),
    (["--frame-size", "100000"], "--frame-size must be in 1..16384"),
])
def test_bench_options_are_named(onnx_path, argv, match):
    args = parse("bench", "--onnx", str(onnx_path), *argv)
    with pytest.raises(ConfigError, match=match):
        args.func(args)


def test_bench_frame_size_needs_an_onnx_model(checkpoint):
    args = parse("bench", "--checkpoint", str(checkpoint), "--frame-size", "256")
    with pytest.raises(ConfigError, match="--frame-size applies to --onnx"):
        args.func(args)

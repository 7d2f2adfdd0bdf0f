import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.training import cli, detect


def _parser():
    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers(dest="command"))
    return parser


@pytest.fixture()
def weights(trained):
    return trained[0]


def test_detect_folder_writes_results_and_overlays(weights, tiny_coco, tmp_path):
    folder = tiny_coco["val"].parent / "images" / "left"
    args = _parser().parse_args(["detect", str(folder), "--weights", str(weights), "--out",
                                 str(tmp_path), "--quiet", "--overlay-conf", "0"])
    assert args.func(args) == 0
    results = json.loads((tmp_path / "results.json").read_text())
    images = json.loads((tmp_path / "images.json").read_text())
    assert len(images) == 8 and len(list((tmp_path / "overlays").glob("*.jpg"))) == 8
    assert results and {r["image_id"] for r in results} <= {i["id"] for i in images}
    assert set(results[0]) - {"box_refined"} == {"image_id", "category_id", "bbox", "score"}
    refined = {r.get("box_refined", False) for r in results if r["category_id"] == 1}
    assert refined == {True}  # the shipped box refiner, on by default
    assert not any("box_refined" in r for r in results if r["category_id"] != 1)
    args = _parser().parse_args(["detect", str(folder), "--weights", str(weights), "--out",
                                 str(tmp_path / "raw"), "--quiet", "--no-box-refiner"])
    assert args.func(args) == 0
    raw = json.loads((tmp_path / "raw" / "results.json").read_text())
    assert not any("box_refined" in r for r in raw)
    assert sorted(r["score"] for r in raw if r["category_id"] != 1) == sorted(
        r["score"] for r in results if r["category_id"] != 1)  # other classes as they were
    sheet = cv2.imread(str(tmp_path / "gallery.png"))
    assert sheet.shape == (2 * 320, 4 * 320, 3)  # 8 images: two rows of four tiles


def test_detect_gallery_size_and_off(weights, tiny_coco, tmp_path):
    folder = tiny_coco["val"].parent / "images" / "left"
    args = _parser().parse_args(["detect", str(folder), "--weights", str(weights), "--out",
                                 str(tmp_path / "a"), "--quiet", "--gallery", "3"])
    assert args.func(args) == 0
    assert cv2.imread(str(tmp_path / "a" / "gallery.png")).shape == (320, 4 * 320, 3)
    args = _parser().parse_args(["detect", str(folder), "--weights", str(weights), "--out",
                                 str(tmp_path / "b"), "--quiet", "--gallery", "0"])
    assert args.func(args) == 0
    assert not (tmp_path / "b" / "gallery.png").exists()
    args = _parser().parse_args(["detect", str(folder), "--weights", str(weights), "--gallery",
                                 "-1"])
    with pytest.raises(ConfigError, match="--gallery must be >= 0"):
        args.func(args)


def test_detect_at_another_input_size(weights, tiny_coco, tmp_path):
    folder = tiny_coco["val"].parent / "images" / "left"
    runs = {}
    for size in (None, 128):
        out = tmp_path / str(size)
        argv = ["detect", str(folder), "--weights", str(weights), "--out", str(out), "--quiet",
                "--gallery", "0"] + ([] if size is None else ["--img-size", str(size)])
        args = _parser().parse_args(argv)
        assert args.func(args) == 0
        runs[size] = json.loads((out / "results.json").read_text())
    width = cv2.imread(str(min(folder.glob("*.png")))).shape[1]
    boxes = np.array([r["bbox"] for r in runs[128]])
    assert len(boxes) and boxes[:, 0].min() >= -1 and (boxes[:, 0] + boxes[:, 2]).max() <= width + 1
    assert runs[128] != runs[None]  # the network really ran at the other size
    args = _parser().parse_args(["detect", str(folder), "--weights", str(weights),
                                 "--img-size", "100"])
    with pytest.raises(ConfigError, match="img_size: expected a positive multiple of 32"):
        args.func(args)


def test_eval_loads_the_model_at_another_input_size(weights):
    from lunarnav_ml.eval.cli import load_predictor

    assert load_predictor(weights, 1).img_size != 128
    assert load_predictor(weights, 1, 128).img_size == 128
    with pytest.raises(ConfigError, match="img_size"):
        load_predictor(weights, 1, 130)


def test_gallery_indices_spread_over_files():
    assert detect.gallery_indices(100, 5) == {0, 25, 50, 74, 99}
    assert detect.gallery_indices(3, 12) == {0, 1, 2}
    assert detect.gallery_indices(10, 0) == set() and detect.gallery_indices(0, 4) == set()


def test_detect_bad_inputs(weights, tmp_path):
    parser = _parser()
    args = parser.parse_args(["detect", str(tmp_path / "none"), "--weights", str(weights)])
    with pytest.raises(InputError, match="no such image or folder"):
        args.func(args)
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"xx")
    args = parser.parse_args(["detect", str(bad), "--weights", str(weights), "--out",
                              str(tmp_path / "o"), "--quiet"])
    with pytest.raises(InputError, match="bad.png: not a readable image"):
        args.func(args)
    args = parser.parse_args(["detect", str(bad), "--weights", str(weights), "--conf", "2"])
    with pytest.raises(ConfigError, match="--conf must lie in"):
        args.func(args)


def test_detect_runs_an_exported_onnx_model_like_its_checkpoint(weights, tiny_coco, tmp_path):
    """An .onnx file runs through the torch-free runtime; same boxes as the checkpoint."""
    from lunarnav_ml.export.onnx_export import export_onnx

    onnx_file = export_onnx(weights, tmp_path / "model.onnx")
    folder = tiny_coco["val"].parent / "images" / "left"
    out = {}
    for name, w in (("ckpt", weights), ("onnx", onnx_file)):
        args = _parser().parse_args(["detect", str(folder), "--weights", str(w), "--out",
                                     str(tmp_path / name), "--quiet", "--conf", "0.001",
                                     "--threads", "1"])
        assert args.func(args) == 0
        out[name] = json.loads((tmp_path / name / "results.json").read_text())
    assert out["ckpt"]
    for a in out["ckpt"]:  # each checkpoint box has its twin from onnxruntime
        twins = [b for b in out["onnx"] if (b["image_id"], b["category_id"]) ==
                 (a["image_id"], a["category_id"]) and abs(b["score"] - a["score"]) < 1e-3
                 and np.abs(np.subtract(b["bbox"], a["bbox"])).max() < 0.5]
        assert twins, a
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(onnx_file.read_bytes()[:200])
    args = _parser().parse_args(["detect", str(folder), "--weights", str(bad), "--out",
                                 str(tmp_path / "x"), "--quiet"])
    with pytest.raises(InputError, match="bad.onnx"):
        args.func(args)
    assert not (tmp_path / "x").exists()


def test_train_forwards_to_lightning_cli(capsys):
    args = _parser().parse_args(["train", "fit", "--help"])
    assert args.cli_args == ["fit", "--help"]
    with pytest.raises(SystemExit) as exit_:
        args.func(args)
    assert exit_.value.code == 0
    assert "--model.preset" in capsys.readouterr().out


def test_single_image(weights, tmp_path):
    image = tmp_path / "one.png"
    cv2.imwrite(str(image), np.full((70, 90), 128, np.uint8))
    args = _parser().parse_args(["detect", str(image), "--weights", str(weights), "--out",
                                 str(tmp_path / "o"), "--quiet"])
    assert args.func(args) == 0
    assert (tmp_path / "o" / "overlays" / "one.jpg").is_file()


class _NoBoxes:
    """A stand-in detector that finds nothing (detect_files needs predict and class_names)."""

    class_names = ("crater", "rock", "artifact")

    def predict(self, images, conf_thres, iou_thres):
        return [{"boxes": np.zeros((0, 4), np.float32), "scores": np.zeros(0, np.float32),
                 "labels": np.zeros(0, np.int64)} for _ in images]


def _run(files, out, **kw):
    return detect.detect_files(_NoBoxes(), files, out, conf_thres=0.1, iou_thres=0.5,
                               overlay_thres=0.5, progress=False, **kw)


def test_detect_output_is_all_or_nothing(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    cv2.imwrite(str(src / "a.png"), np.full((40, 50), 99, np.uint8))
    (src / "b.png").write_bytes(b"not a png")
    out = tmp_path / "out"
    with pytest.raises(InputError, match="b.png: not a readable image"):
        _run(detect.list_images(src), out, batch=1)  # b.png fails in the second batch
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["src"]
    _run([src / "a.png"], out, gallery=2)
    assert sorted(p.name for p in out.iterdir()) == ["gallery.png", "images.json", "overlays",
                                                     "results.json"]
    with pytest.raises(InputError, match="b.png"):  # a failed re-run keeps the old output
        _run(detect.list_images(src), out, batch=1)
    assert (out / "gallery.png").is_file() and (out / "overlays" / "a.jpg").is_file()
    _run([src / "a.png"], out, gallery=0)  # a re-run replaces the output: no stale gallery
    assert not (out / "gallery.png").exists() and (out / "results.json").is_file()


def test_detect_will_not_replace_a_folder_it_did_not_write(tmp_path):
    image = tmp_path / "a.png"
    cv2.imwrite(str(image), np.full((40, 50), 99, np.uint8))
    with pytest.raises(ConfigError, match="--out holds the input image"):
        _run([image], tmp_path)
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("keep")
    with pytest.raises(ConfigError, match=r"other: --out holds files detect did not write "
                                          r"\(notes.txt\)"):
        _run([image], other)
    afile = tmp_path / "afile"
    afile.write_text("keep")
    with pytest.raises(ConfigError, match="afile: --out exists and is not a folder"):
        _run([image], afile)
    assert (other / "notes.txt").read_text() == "keep" and afile.read_text() == "keep"


def test_detect_takes_several_sources_and_keeps_every_overlay(tmp_path):
    """Files and folders together (a shell glob gives several files); stems that repeat across
    folders or suffixes get their own overlays; a file named twice is read once."""
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        cv2.imwrite(str(tmp_path / folder / "000001.png"), np.full((40, 50), 99, np.uint8))
    cv2.imwrite(str(tmp_path / "a" / "000001.jpg"), np.full((40, 50), 50, np.uint8))
    cv2.imwrite(str(tmp_path / "x.png"), np.full((30, 30), 10, np.uint8))
    args = _parser().parse_args(["detect", str(tmp_path / "a"), str(tmp_path / "b"),
                                 str(tmp_path / "x.png"), str(tmp_path / "b" / "000001.png")])
    files = detect.list_images(args.source)
    assert [f.relative_to(tmp_path).as_posix() for f in files] == [
        "a/000001.jpg", "a/000001.png", "b/000001.png", "x.png"]
    out = tmp_path / "out"
    _run(files, out)
    images = json.loads((out / "images.json").read_text())
    assert [i["overlay"] for i in images] == ["overlays/000001.jpg", "overlays/000001-2.jpg",
                                              "overlays/000001-3.jpg", "overlays/x.jpg"]
    assert sorted(p.name for p in (out / "overlays").iterdir()) == [
        "000001-2.jpg", "000001-3.jpg", "000001.jpg", "x.jpg"]
    with pytest.raises(InputError, match="nothing: no such image or folder"):
        detect.list_images([tmp_path / "x.png", tmp_path / "nothing"])


def test_overlay_names_stay_unique_when_a_file_is_named_like_a_renamed_one():
    names = detect.overlay_names([Path("a.png"), Path("a-2.png"), Path("d/a.png")])
    assert names == ["a.jpg", "a-2.jpg", "a-3.jpg"]


def test_average_writes_slim_weights_and_refuses_bad_input(weights, tmp_path, capsys):
    from lunarnav_ml.cli import main
    from lunarnav_ml.training.api import load_detector

    out = tmp_path / "soup.pt"
    assert main(["average", str(weights), str(weights), "--out", str(out), "--half"]) == 0
    assert load_detector(out).class_names == ["crater", "rock", "artifact"]
    assert not list(tmp_path.glob("*.tmp*"))
    capsys.readouterr()
    missing = tmp_path / "missing.pt"
    assert main(["average", str(weights), str(missing), "--out", str(tmp_path / "b.pt")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "missing.pt" in err and "Traceback" not in err
    assert not (tmp_path / "b.pt").exists()
    assert main(["average", str(weights), "--out", str(tmp_path / "c.pt")]) == 2
    assert "two or more" in capsys.readouterr().err

import argparse
import json

import cv2
import numpy as np
import pytest

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.training import cli


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
    assert set(results[0]) == {"image_id", "category_id", "bbox", "score"}


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

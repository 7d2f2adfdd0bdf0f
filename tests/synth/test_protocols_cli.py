"""Protocol grids, the synth subcommand, calibration readers and the gallery."""

import json
import subprocess
import sys

import numpy as np
import pytest

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.synth import calibrate, generate_dataset
from lunarnav_ml.synth.protocols import DIAMETERS_M, grid

CLI = ("import sys; from lunarnav_ml.cli import build_parser; from lunarnav_ml.errors import "
       "LunarNavError\np = build_parser(('lunarnav_ml.synth.cli',)); a = p.parse_args(sys.argv[1:])"
       "\ntry:\n    sys.exit(a.func(a))\nexcept LunarNavError as e:\n"
       "    print(f'lunarnav synth: error: {e}', file=sys.stderr); sys.exit(2)")


def test_protocol_sizes():
    assert len(grid("paper-stereo")) == 1792
    assert len(grid("paper-lidar")) == 7 * 4 * 16
    mono = grid("paper-mono")
    assert max(r for _, _, r, _, _ in mono) == 29.0
    assert {z for *_, z, _ in mono} == {0.0, 20.0, 40.0, 60.0, 80.0}
    assert {a for *_, a in mono} == {0.0, 30.0, 60.0, 90.0, 120.0, 150.0, 180.0}
    with pytest.raises(ConfigError, match="paper-foo"):
        grid("paper-foo")


def test_protocol_item_places_the_target_crater(tmp_path, small_cfg):
    ann = generate_dataset(tmp_path / "p", n_images=1, protocol="paper-lidar", config=small_cfg,
                           image_size=96, progress=False)
    coco = json.loads(ann.read_text())
    im = coco["images"][0]
    item = im["protocol_item"]
    assert item["diameter_m"] == DIAMETERS_M[0] and item["near_rim_range_m"] == 5.0
    target = [a for a in coco["annotations"] if a.get("diameter_m") == item["diameter_m"]]
    assert len(target) == 1 and abs(target[0]["near_rim_range_m"] - 5.0) < 1e-3
    scan = np.load(ann.parent / im["lidar_file"])
    assert scan["points"].shape[1] == 3 and scan["range_m"].shape == (226, 1081)


def test_cli_bad_shard_is_one_line(tmp_path):
    proc = subprocess.run([sys.executable, "-c", CLI, "synth", str(tmp_path / "o"), "--shard",
                           "3/2"], capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "shard" in proc.stderr


def test_cli_bad_config_names_file_and_key(tmp_path):
    bad = tmp_path / "c.yaml"
    bad.write_text("craters:\n  min_diameter_m: -2\n")
    proc = subprocess.run([sys.executable, "-c", CLI, "synth", str(tmp_path / "o"), "--config",
                           str(bad)], capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 2
    assert "c.yaml" in proc.stderr and "craters.min_diameter_m" in proc.stderr


def test_calibration_readers(tmp_path):
    import cv2

    rng = np.random.default_rng(0)
    cv2.imwrite(str(tmp_path / "t.png"), np.zeros((100, 100), np.uint8))
    d = 8 * (1 - rng.uniform(size=400)) ** -0.5  # N(>=D) ~ D^-2 above 8 px
    lines = ["ID,X,Y,W,H,C_X,CY"] + [f"{i},0,0,{v},{v},0,0" for i, v in enumerate(d)]
    (tmp_path / "t.txt").write_text("\n".join(lines))
    fit = calibrate.crater_sfd_from_boxes(tmp_path, m_per_px=0.5, d_min_m=4.0, d_max_m=40.0)
    assert abs(fit.slope - 2.0) < 0.25
    (tmp_path / "t.txt").write_text("ID,X,Y,W,H,C_X,CY\n1,2,3\n")
    with pytest.raises(InputError, match="t.txt:2"):
        calibrate.read_crater_boxes(tmp_path)


def test_gallery_writes_an_image(tmp_path, small_cfg, monkeypatch):
    from lunarnav_ml.synth import gallery

    monkeypatch.setattr(gallery, "SUN_GRID", ((30.0, 90.0), (80.0, 180.0)))
    path = gallery.write_gallery(tmp_path / "g.png", config=small_cfg, image_size=64, columns=2)
    import cv2

    img = cv2.imread(str(path))
    assert img.shape == (64, 128, 3)

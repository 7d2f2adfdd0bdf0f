"""generate_dataset: layout, same seed same bytes, shards and resume."""

import hashlib
import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lunarnav_ml.errors import InputError
from lunarnav_ml.synth import generate_dataset


def _digest(root):
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_layout_and_same_seed_same_bytes(tmp_path, small_cfg):
    a = generate_dataset(tmp_path / "a", n_images=2, seed=5, config=small_cfg, image_size=96,
                         progress=False)
    b = generate_dataset(tmp_path / "b", n_images=2, seed=5, config=small_cfg, image_size=96,
                         progress=False)
    assert a.name == "annotations.json"
    assert _digest(a.parent) == _digest(b.parent)
    coco = json.loads(a.read_text())
    assert [c["name"] for c in coco["categories"]] == ["crater", "rock", "artifact"]
    im = coco["images"][0]
    for key in ("file_name", "right_file", "depth_file", "disparity_file"):
        assert (a.parent / im[key]).is_file()
    for key in ("sun_zenith_deg", "sun_azimuth_deg", "camera", "seed"):
        assert key in im
    for ann in coco["annotations"]:
        assert ann["iscrowd"] == int(ann["ignore"])


def test_different_seed_differs(tmp_path, small_cfg):
    a = generate_dataset(tmp_path / "a", n_images=1, seed=1, config=small_cfg, image_size=64,
                         stereo=False, progress=False)
    b = generate_dataset(tmp_path / "b", n_images=1, seed=2, config=small_cfg, image_size=64,
                         stereo=False, progress=False)
    assert _digest(a.parent)["images/left/000000.png"] != _digest(b.parent)["images/left/000000.png"]


def test_shards_and_resume_equal_one_run(tmp_path, small_cfg):
    kw = {"n_images": 3, "seed": 2, "config": small_cfg, "image_size": 64, "stereo": False,
          "progress": False}
    whole = generate_dataset(tmp_path / "whole", **kw)
    part = generate_dataset(tmp_path / "sharded", shard=(1, 2), **kw)
    assert part.name == "annotations.shard-1-of-2.json"
    assert len(json.loads(part.read_text())["images"]) == 1
    rec = tmp_path / "sharded" / "items" / "000001.json"
    mtime = rec.stat().st_mtime_ns
    merged = generate_dataset(tmp_path / "sharded", shard=(0, 2), **kw)
    assert merged.name == "annotations.json"
    assert rec.stat().st_mtime_ns == mtime  # finished item skipped
    assert merged.read_bytes() == whole.read_bytes()
    last = json.loads((tmp_path / "sharded" / "annotations.shard-0-of-2.json").read_text())
    assert [im["id"] for im in last["images"]] == [1, 3]  # the shard that finished the set


def test_items_subset_renders_only_those_with_the_same_bytes(tmp_path, small_cfg):
    kw = {"n_images": 3, "seed": 2, "config": small_cfg, "image_size": 64, "stereo": False,
          "progress": False}
    whole = generate_dataset(tmp_path / "whole", **kw)
    part = generate_dataset(tmp_path / "part", items=[2], **kw)
    assert part.name == "annotations.shard-0-of-1.json"
    assert [im["id"] for im in json.loads(part.read_text())["images"]] == [3]
    assert not (tmp_path / "part" / "items" / "000000.json").exists()
    a, b = _digest(whole.parent), _digest(part.parent)
    assert b["images/left/000002.png"] == a["images/left/000002.png"]
    with pytest.raises(InputError, match="items"):
        generate_dataset(tmp_path / "part", items=[3], **kw)


def test_bad_arguments(tmp_path, small_cfg):
    with pytest.raises(InputError, match="shard"):
        generate_dataset(tmp_path / "x", n_images=1, shard=(2, 2), config=small_cfg)
    with pytest.raises(InputError, match="image_size"):
        generate_dataset(tmp_path / "x", n_images=1, image_size=0, config=small_cfg)


def test_worker_processes_give_the_same_bytes(tmp_path, small_cfg):
    kw = {"n_images": 2, "seed": 4, "config": small_cfg, "image_size": 64, "progress": False}
    one = generate_dataset(tmp_path / "one", workers=1, **kw)
    two = generate_dataset(tmp_path / "two", workers=2, **kw)
    assert _digest(one.parent) == _digest(two.parent)


def test_field_of_view_is_drawn_per_scene_without_moving_the_other_draws():
    import dataclasses
    import math

    import numpy as np

    from lunarnav_ml.synth import SynthConfig
    from lunarnav_ml.synth.generate import item_seed
    from lunarnav_ml.synth.pipeline import TerrainCache, make_scene_rig
    from lunarnav_ml.synth.scene import sample_scene

    fixed = SynthConfig()
    varied = SynthConfig.from_dict({"camera": {"fov_deg": [18.0, 90.0]}})
    fovs = []
    for i in range(6):
        a, b = sample_scene(fixed, item_seed(4, i)), sample_scene(varied, item_seed(4, i))
        assert a.fov_deg == 90.0  # the paper's rig, as before FOV could vary
        assert dataclasses.replace(b, fov_deg=90.0) == a  # every other draw is the same
        assert b == sample_scene(varied, item_seed(4, i))  # same seed, same scene
        fovs.append(b.fov_deg)
    assert all(18.0 <= f <= 90.0 for f in fovs) and np.ptp(fovs) > 10.0
    small = SynthConfig.from_dict({"terrain": {"extent_m": 40.0, "resolution_m": 0.1},
                                   "craters": {"max_diameter_m": 12.0}})
    spec = dataclasses.replace(sample_scene(small, item_seed(4, 0)), fov_deg=30.0)
    rig = make_scene_rig(spec, TerrainCache().get(spec.terrain, small), small, 64)
    assert math.isclose(rig.left.fx, 32.0 / math.tan(math.radians(15.0)))
    assert rig.camera_dict()["fov_deg"] == 30.0


def test_pixel_aspect_is_drawn_after_the_field_of_view_and_stretches_the_image_vertically():
    import dataclasses

    import numpy as np

    from lunarnav_ml.synth import SynthConfig
    from lunarnav_ml.synth.camera import make_rig
    from lunarnav_ml.synth.generate import item_seed
    from lunarnav_ml.synth.scene import sample_scene

    fov = SynthConfig.from_dict({"camera": {"fov_deg": [18.0, 90.0]}})
    both = SynthConfig.from_dict({"camera": {"fov_deg": [18.0, 90.0], "aspect": [1.0, 1.5]}})
    aspects = []
    for i in range(6):
        a, b = sample_scene(fov, item_seed(4, i)), sample_scene(both, item_seed(4, i))
        assert a.aspect == 1.0 and b.fov_deg == a.fov_deg  # drawn after everything else
        assert dataclasses.replace(b, aspect=1.0) == a
        aspects.append(b.aspect)
    assert all(1.0 <= x <= 1.5 for x in aspects) and np.ptp(aspects) > 0.1
    kw = {"width": 64, "height": 64, "fov_deg": 30.0, "height_m": 1.5, "yaw_deg": 0.0,
          "pitch_deg": 20.0, "roll_deg": 0.0, "baseline_m": 0.3}
    square, tall = make_rig(np.zeros(3), **kw), make_rig(np.zeros(3), aspect=1.36, **kw)
    assert tall.left.fx == square.left.fx and np.isclose(tall.left.fy, 1.36 * square.left.fy)
    pts = np.array([[10.0, 1.0, 0.0], [12.0, -1.0, 0.2]])  # ground ahead of the camera
    (uv_s, _), (uv_t, _) = square.left.project(pts), tall.left.project(pts)
    assert np.allclose(uv_t[:, 0], uv_s[:, 0])
    assert np.allclose(uv_t[:, 1] - 31.5, 1.36 * (uv_s[:, 1] - 31.5))


def _stat(pid):
    """(state, parent pid) of a process from Linux /proc, or None once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return fields[0], int(fields[1])


def _children(pid):
    pids = (int(p.name) for p in Path("/proc").iterdir() if p.name.isdigit())
    return [c for c in pids if (_stat(c) or (None, None))[1] == pid]


def _running(pid):
    stat = _stat(pid)
    return stat is not None and stat[0] != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_render_workers_exit_when_the_run_is_killed(tmp_path):
    """A killed `lunarnav synth` (SIGKILL: no clean-up in the parent) leaves no idle workers."""
    script = (
        "from lunarnav_ml.synth import SynthConfig, generate_dataset\n"
        "cfg = SynthConfig.from_dict({'terrain': {'extent_m': 40.0, 'resolution_m': 0.1},"
        " 'craters': {'max_diameter_m': 12.0, 'min_diameter_m': 1.0}})\n"
        f"generate_dataset({str(tmp_path / 'd')!r}, n_images=500, seed=1, config=cfg,"
        " image_size=64, workers=2, progress=False)\n")
    run = subprocess.Popen([sys.executable, "-c", script])
    try:
        deadline = time.monotonic() + 180
        while not list((tmp_path / "d" / "items").glob("*.json")):
            assert run.poll() is None, "the render run ended early"
            assert time.monotonic() < deadline, "no item rendered in 180 s"
            time.sleep(0.2)
        workers = _children(run.pid)
        assert len(workers) >= 2
    finally:
        run.kill()
        run.wait()
    deadline = time.monotonic() + 20
    while any(_running(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not [w for w in workers if _running(w)], "workers outlived the killed run"

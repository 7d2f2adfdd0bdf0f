"""The SGBM disparity refiner: features, region refinement, the shipped file, training, export."""

import json

import numpy as np
import onnx
import pytest
import torch

from lunarnav_ml.cli import main
from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.geometry.lifter import LifterConfig
from lunarnav_ml.geometry.refine import (
    DEFAULT_REFINER,
    DisparityRefiner,
    gated_boxes,
    refine_regions,
    refiner_features,
    warp_right,
)
from lunarnav_ml.geometry.report import geometry_report
from lunarnav_ml.training.refiner import (
    RefinerConfig,
    RefinerNet,
    build_crops,
    export_refiner,
    train_refiner,
)
from tests.geometry.test_report import _write_dataset


def _texture(h=96, w=160, seed=0):
    rng = np.random.default_rng(seed)
    import cv2

    return cv2.GaussianBlur(rng.uniform(0, 255, (h, w)), (0, 0), 2.0).astype(np.float32)


def test_warp_right_lines_up_with_left():
    tex = _texture()
    left = tex[:, 20:140].round().astype(np.uint8)
    right = tex[:, 24:144].round().astype(np.uint8)  # right(u - 4) = left(u): disparity 4
    d = np.full(left.shape, 4.0, np.float32)
    warped = warp_right(right, d)
    assert np.array_equal(warped[:, 8:], left[:, 8:])
    d[:, :50] = np.nan  # invalid pixels are warped at disparity 0
    assert np.array_equal(warp_right(right, d)[:, :50], right[:, :50])


def test_features_channels():
    left = np.full((1, 4, 5), 255, np.uint8)
    warped = np.zeros((1, 4, 5), np.uint8)
    d = np.full((1, 4, 5), 16.0, np.float32)
    d[0, 0, 0] = np.nan
    f = refiner_features(left, warped, d)
    assert f.shape == (1, 5, 4, 5) and f.dtype == np.float32
    assert f[0, 0, 1, 1] == 0.5 and f[0, 1, 1, 1] == -0.5 and f[0, 2, 1, 1] == 4.0
    assert f[0, 3, 1, 1] == 0.5 and f[0, 3, 0, 0] == 0.0
    assert f[0, 4, 0, 0] == 0.0 and f[0, 4, 1, 1] == 1.0


def _shifted_pair(shift=6, seed=1):
    tex = _texture(160, 260, seed=seed)  # right(u - shift) = left(u)
    left = tex[:, 30:250].round().astype(np.uint8)
    right = tex[:, 30 + shift:250 + shift].round().astype(np.uint8)
    return left, right


@pytest.fixture(scope="module")
def shipped():
    return DisparityRefiner()


def test_shipped_refiner_regions_equal_the_whole_band(shipped):
    rng = np.random.default_rng(1)
    left, right = _shifted_pair()
    d = np.full(left.shape, np.nan, np.float32)
    d[20:150] = 6.0 + rng.normal(0, 0.3, (130, left.shape[1]))
    d[60:64, 100:120] = np.nan
    boxes = np.array([[40.0, 70.0, 50.0, 30.0], [150.0, 40.0, 40.0, 60.0]])
    whole = shipped.refine(left, right, d)
    part = shipped.refine(left, right, d, boxes)
    assert np.array_equal(np.isnan(whole), np.isnan(d)) and np.array_equal(np.isnan(part),
                                                                            np.isnan(d))
    inside = np.zeros(d.shape, bool)
    for r0, r1, c0, c1 in refine_regions(boxes, d.shape):
        inside[r0:r1, c0:c1] = True
    fin = np.isfinite(d)
    np.testing.assert_allclose(part[inside & fin], whole[inside & fin], atol=1e-5)
    assert np.array_equal(part[~inside & fin], d[~inside & fin])  # the rest as it was
    assert np.abs(whole - d)[fin].max() > 1e-3  # the net does change the map


def test_gated_boxes():
    d = np.full((100, 200), 8.0, np.float32)
    d[:, 100:] = 20.0
    d[60:, 170:] = np.nan
    boxes = np.array([[10.0, 20.0, 40.0, 30.0],  # disparity 8
                      [120.0, 20.0, 40.0, 30.0],  # 20
                      [172.0, 70.0, 20.0, 20.0],  # no valid pixel in its lower half
                      [80.0, 20.0, 40.0, 30.0]])  # half 8, half 20: median on the line
    assert gated_boxes(d, boxes, None).tolist() == [True] * 4
    assert gated_boxes(d, boxes, 16.0).tolist() == [True, False, True, False]
    assert gated_boxes(d, boxes, 25.0).tolist() == [True, True, True, True]
    d[35:, 10:51] = 30.0  # the box's lower half decides, not its upper
    assert gated_boxes(d, boxes[:1], 16.0).tolist() == [False]


def test_gate_and_passes():
    left, right = _shifted_pair()
    rng = np.random.default_rng(3)
    d = np.full(left.shape, np.nan, np.float32)
    d[20:150] = 6.0 + rng.normal(0, 0.3, (130, left.shape[1]))
    d[20:150, 120:] += 12.0  # a nearer right half (its matches wrong, but the gate reads d)
    boxes = np.array([[30.0, 70.0, 50.0, 30.0], [150.0, 60.0, 40.0, 40.0]])
    ungated = DisparityRefiner(max_disparity_px=None)
    one = ungated.refine(left, right, d, boxes)
    gated = DisparityRefiner(max_disparity_px=12.0)
    assert gated.passes == ungated.passes == 1
    part = gated.refine(left, right, d, boxes)
    far_box = np.zeros(d.shape, bool)  # the far box's region is refined, the near one's not
    for r0, r1, c0, c1 in refine_regions(boxes[:1], d.shape):
        far_box[r0:r1, c0:c1] = True
    fin = np.isfinite(d)
    np.testing.assert_allclose(part[far_box & fin], one[far_box & fin], atol=1e-5)
    assert np.array_equal(part[~far_box & fin], d[~far_box & fin])
    assert not np.array_equal(one[~far_box & fin], d[~far_box & fin])
    twice = DisparityRefiner(max_disparity_px=None, passes=2).refine(left, right, d, boxes)
    np.testing.assert_allclose(twice, ungated.refine(left, right, one, boxes), atol=1e-5)
    assert np.nanmax(np.abs(twice - one)) > 1e-3
    assert np.array_equal(np.isnan(twice), np.isnan(d))
    for kwargs, field in (({"max_disparity_px": 0.0}, "max_disparity_px"),
                          ({"max_disparity_px": "16"}, "max_disparity_px"),
                          ({"passes": 0}, "passes"), ({"passes": 1.5}, "passes")):
        with pytest.raises(InputError, match=field):
            DisparityRefiner(**kwargs)


def test_shipped_refiner_metadata(shipped):
    assert shipped.path == DEFAULT_REFINER and shipped.receptive_px == RefinerNet().receptive_px
    assert (shipped.max_disparity_px, shipped.passes) == (16.0, 1)  # the gate since session 66
    cfg = shipped.lifter_config(LifterConfig(max_rim_residual_rel=0.2))
    assert cfg.max_rim_residual_rel == 0.2
    for key, value in shipped.edge_offsets.items():
        assert getattr(cfg, key) == value


def test_refine_rejects_bad_images(shipped):
    d = np.ones((20, 30), np.float32)
    img = np.zeros((20, 30), np.uint8)
    with pytest.raises(InputError, match="right: expected a uint8 gray image"):
        shipped.refine(img, np.zeros((20, 31), np.uint8), d)
    with pytest.raises(InputError, match="left: expected a uint8 gray image"):
        shipped.refine(img.astype(np.float32), img, d)


def _export(tmp_path, name, **meta):
    net = RefinerNet(4, (1,))
    return export_refiner(net, tmp_path / name, meta)


def test_refiner_file_errors(tmp_path):
    with pytest.raises(InputError, match="nope.onnx: disparity refiner not found"):
        DisparityRefiner(tmp_path / "nope.onnx")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"\x08\x01garbage")
    with pytest.raises(InputError, match="bad.onnx: not a loadable ONNX model"):
        DisparityRefiner(bad)
    path = _export(tmp_path, "foreign.onnx")
    model = onnx.load(str(path))
    del model.metadata_props[:]
    onnx.save(model, str(path))
    with pytest.raises(InputError, match="foreign.onnx: not a disparity refiner"):
        DisparityRefiner(path)
    path = _export(tmp_path, "offsets.onnx", **{"lunarnav.edge_offsets": '{"rim_offset": "x"}'})
    with pytest.raises(InputError, match="offsets.onnx: metadata lunarnav.edge_offsets"):
        DisparityRefiner(path)
    for key, value in (("lunarnav.max_disparity_px", "-3"), ("lunarnav.passes", "two")):
        path = _export(tmp_path, "settings.onnx", **{key: value})
        with pytest.raises(InputError, match=f"settings.onnx: metadata {key}"):
            DisparityRefiner(path)
    path = _export(tmp_path, "fine.onnx", **{"lunarnav.edge_offsets": '{"box_rim_offset": 0.01}'})
    assert DisparityRefiner(path).lifter_config().box_rim_offset == 0.01


def test_export_matches_torch(tmp_path):
    torch.manual_seed(0)
    net = RefinerNet(8, (1, 2))
    path = export_refiner(net, tmp_path / "r.onnx")
    ref = DisparityRefiner(path)
    rng = np.random.default_rng(2)
    left, warped = (rng.integers(0, 256, (37, 53)).astype(np.uint8) for _ in range(2))
    d = rng.uniform(1, 30, (37, 53)).astype(np.float32)
    with torch.no_grad():
        want = net(torch.from_numpy(refiner_features(left[None], warped[None], d[None])))[0]
    np.testing.assert_allclose(ref.correction(left, warped, d), want.numpy(), atol=1e-5)


@pytest.fixture(scope="module")
def rendered_set(tmp_path_factory, crater_scene):
    root = tmp_path_factory.mktemp("refine_ds")
    _write_dataset(root, crater_scene)
    r = crater_scene.rig
    (root / "disparity").mkdir()
    np.save(root / "disparity/0.npy", r.focal_px * r.baseline_m / crater_scene.depth)
    coco = json.loads((root / "annotations.json").read_text())
    coco["images"][0]["disparity_file"] = "disparity/0.npy"
    (root / "annotations.json").write_text(json.dumps(coco))
    return root


def test_training_fits_crops_and_is_seeded(rendered_set):
    crops = build_crops([rendered_set], seed=3, progress=False)
    assert len(crops) >= 8 and crops.left.shape[1:] == (64, 64)
    again = build_crops([rendered_set], seed=3, progress=False)
    assert np.array_equal(crops.left, again.left)
    medians = np.nanmedian(crops.sgbm.reshape(len(crops), -1), axis=1)
    cut = float(np.median(medians))
    far = build_crops([rendered_set], seed=3, progress=False, max_disparity_px=cut)
    assert 0 < len(far) < len(crops)
    assert np.array_equal(far.left, crops.left[medians < cut])  # the same crops, filtered
    cfg = RefinerConfig(channels=16, dilations=(1, 2), steps=300, batch=4, lr=3e-3,
                        val_fraction=0.2, seed=3)
    net, report = train_refiner(crops, cfg, log=None)
    assert report.n_val >= 1 and report.steps == 300
    # the fit to the training crops beats SGBM's own error (it can fail: a broken loss,
    # features or target sign does not learn)
    from lunarnav_ml.training.refiner import _loss

    with torch.no_grad():
        fitted, base = _loss(net, crops, np.arange(len(crops)))
    assert fitted.item() < 0.8 * base
    net2, _ = train_refiner(crops, cfg, log=None)
    for a, b in zip(net.parameters(), net2.parameters(), strict=True):
        assert torch.equal(a, b)


def test_training_config_checks():
    with pytest.raises(ConfigError, match="steps"):
        RefinerConfig(steps=0)
    with pytest.raises(ConfigError, match="val_fraction"):
        RefinerConfig(val_fraction=0.7)
    with pytest.raises(ConfigError, match="max_disparity_px"):
        RefinerConfig(max_disparity_px=-1.0)


def test_cli_train_refiner_then_eval(rendered_set, tmp_path, capsys):
    out = tmp_path / "r.onnx"
    assert main(["train-refiner", str(rendered_set), "--out", str(out), "--steps", "10",
                 "--batch", "4", "--channels", "4", "--quiet", "--threads", "1"]) == 0
    assert "held-out L1" in capsys.readouterr().out
    assert DisparityRefiner(out).receptive_px > 0
    assert DisparityRefiner(out).max_disparity_px is None
    gated = tmp_path / "gated.onnx"
    assert main(["train-refiner", str(rendered_set), "--out", str(gated), "--steps", "2",
                 "--batch", "2", "--channels", "4", "--quiet", "--threads", "1",
                 "--max-disparity", "400"]) == 0
    assert DisparityRefiner(gated).max_disparity_px == 400.0
    assert main(["eval", "--task", "geometry", "--gt", str(rendered_set), "--refiner", str(out),
                 "--threads", "1", "--out", str(tmp_path / "geo"), "--no-progress"]) == 0
    metrics = json.loads((tmp_path / "geo" / "geometry_metrics.json").read_text())
    assert metrics["settings"]["refiner"] == str(out) and metrics["overall"]["n"] == 1
    rows = json.loads((tmp_path / "geo" / "geometry_craters.json").read_text())
    assert [r["refined"] for r in rows] == [True]  # ungated: every box
    for extra, want in (([], str(DEFAULT_REFINER)), (["--no-refiner"], None),
                        (["--disparity", "rendered"], None)):  # on by default, on SGBM only
        assert main(["eval", "--task", "geometry", "--gt", str(rendered_set), *extra,
                     "--out", str(tmp_path / "g2"), "--no-progress"]) == 0
        metrics = json.loads((tmp_path / "g2" / "geometry_metrics.json").read_text())
        assert metrics["settings"]["refiner"] == want
        rows = json.loads((tmp_path / "g2" / "geometry_craters.json").read_text())
        if want is None:
            assert [r["refined"] for r in rows] == [False]


def test_cli_train_refiner_bad_input(tmp_path, rendered_set, capsys):
    coco = json.loads((rendered_set / "annotations.json").read_text())
    del coco["images"][0]["disparity_file"]
    (tmp_path / "annotations.json").write_text(json.dumps(coco))
    for sub in ("images/left", "images/right"):
        (tmp_path / sub).mkdir(parents=True)
        (tmp_path / sub / "0.png").write_bytes((rendered_set / sub / "0.png").read_bytes())
    assert main(["train-refiner", str(tmp_path), "--out", str(tmp_path / "r.onnx"),
                 "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no disparity_file" in err[0]
    assert not (tmp_path / "r.onnx").exists()


def test_report_refiner_needs_sgbm(rendered_set, tmp_path, shipped):
    with pytest.raises(InputError, match="refiner: refines SGBM's disparity"):
        geometry_report(rendered_set, tmp_path, disparity="rendered", refiner=shipped)


def test_refiner_study_script(rendered_set, tmp_path, capsys):
    from tests.bench_scripts import load_script

    study = load_script("refiner_study")
    coco = json.loads((rendered_set / "annotations.json").read_text())
    coco["annotations"][0]["near_rim_range_m"] = 16.0  # an example for the figure
    ds = tmp_path / "ds"
    ds.mkdir()
    for rel in ("images/left/0.png", "images/right/0.png", "disparity/0.npy"):
        (ds / rel).parent.mkdir(parents=True, exist_ok=True)
        (ds / rel).write_bytes((rendered_set / rel).read_bytes())
    (ds / "annotations.json").write_text(json.dumps(coco))
    assert study.main([str(ds), "--out", str(tmp_path / "out"), "--examples", "1"]) == 0
    metrics = json.loads((tmp_path / "out" / "refiner_study.json").read_text())
    assert metrics["n_pixels"] > 1000 and metrics["sgbm"] > 0 and metrics["refined"] > 0
    assert metrics["n_edge_pixels"] <= metrics["n_pixels"]
    assert metrics["n_refined_boxes"] == metrics["n_boxes"] == 1
    assert (tmp_path / "out" / "refiner_examples.png").stat().st_size > 10_000
    assert "mean |error| px in the refined regions" in capsys.readouterr().out
    (ds / "disparity/0.npy").write_bytes(b"junk")
    assert study.main([str(ds), "--out", str(tmp_path / "bad")]) == 2
    assert "0.npy: cannot read disparity" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_stamp_edge_offsets(tmp_path):
    from lunarnav_ml.training.refiner import stamp_edge_offsets

    path = _export(tmp_path, "r.onnx", **{"lunarnav.edge_offsets": '{"box_rim_offset": 0.5}'})
    stamp_edge_offsets(path, {"box_rim_offset_m": -0.03, "box_rim_offset_view": -0.1})
    ref = DisparityRefiner(path)
    assert ref.edge_offsets == {"box_rim_offset_m": -0.03, "box_rim_offset_view": -0.1}
    assert ref.max_disparity_px is None and ref.passes == 1
    stamp_edge_offsets(path, {"box_rim_offset": 0.01}, max_disparity_px=16, passes=2)
    ref = DisparityRefiner(path)
    assert (ref.max_disparity_px, ref.passes) == (16.0, 2)
    assert DisparityRefiner(path, max_disparity_px=None, passes=1).max_disparity_px is None
    assert ref.receptive_px == RefinerNet(4, (1,)).receptive_px  # the rest of the metadata kept
    before = path.read_bytes()
    with pytest.raises(InputError, match="lunarnav.edge_offsets"):
        stamp_edge_offsets(path, {"ground_rows": 3.0})
    with pytest.raises(InputError, match="lunarnav.edge_offsets"):
        stamp_edge_offsets(path, {"box_rim_offset": float("nan")})
    with pytest.raises(InputError, match="passes"):
        stamp_edge_offsets(path, {"box_rim_offset": 0.01}, passes=0)
    assert path.read_bytes() == before

"""benchmarks/crossfit_rescorer.py: the level-ground features of a crater box, and bad
arguments."""

import json
import math
import shutil

import numpy as np
import pytest

from tests.bench_scripts import load_script

crossfit = load_script("crossfit_rescorer")

CAMERA = {"fx": 512.0, "fy": 512.0, "cx": 511.5, "cy": 511.5, "pitch_deg": 20.0,
          "height_m": 1.5}


def _circle_box(diameter, rng, camera=CAMERA):
    """The image box of a level circle straight ahead, its centre at horizontal range ``rng``."""
    t = np.linspace(0, 2 * math.pi, 721)
    fwd, side = rng + diameter / 2 * np.cos(t), diameter / 2 * np.sin(t)
    p = math.radians(camera["pitch_deg"])
    z = fwd * math.cos(p) + camera["height_m"] * math.sin(p)  # along the optical axis
    down = camera["height_m"] * math.cos(p) - fwd * math.sin(p)  # under it
    x = camera["cx"] + camera["fx"] * side / z
    y = camera["cy"] + camera["fy"] * down / z
    return np.array([x.min(), y.min(), x.max(), y.max()])


@pytest.mark.parametrize("diameter, rng", [(5.0, 8.0), (10.0, 15.0), (20.0, 30.0)])
def test_a_level_circle_reads_its_diameter_and_an_aspect_near_one(diameter, rng):
    box = _circle_box(diameter, rng)
    d, aspect = crossfit.ground_features(box[None], CAMERA)[0]
    assert d == pytest.approx(diameter, rel=0.15)
    assert aspect == pytest.approx(1.0, abs=0.15)
    half = box.copy()
    half[2] = 0.5 * (box[0] + box[2])  # a box on the left half of the rim
    d_half, aspect_half = crossfit.ground_features(half[None], CAMERA)[0]
    assert d_half < 0.6 * d
    assert aspect_half > 1.6 * aspect


def test_a_box_over_the_horizon_has_no_ground_features():
    horizon = CAMERA["cy"] - CAMERA["fy"] * math.tan(math.radians(CAMERA["pitch_deg"]))
    over = np.array([[100.0, horizon - 20, 200.0, horizon - 5]])
    assert crossfit.ground_features(over, CAMERA).tolist() == [[crossfit.NO_GROUND] * 2]
    across = np.array([[100.0, horizon - 20, 200.0, horizon + 10]])  # its bottom on the ground
    assert (crossfit.ground_features(across, CAMERA) > 0).all()


def test_a_set_fitted_on_itself_is_refused(tmp_path, capsys):
    code = crossfit.main(["--gt", "a.json", "b.json", "--raw", "ra.json", "rb.json",
                          "--fit-on", "0", "0", "--out", str(tmp_path / "out")])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--fit-on" in err[0] and "not its own" in err[0]
    assert not (tmp_path / "out").exists()


def _set_with_camera(root, seed):
    """A small labelled set whose frames carry a camera record and whose craters are key ones,
    and a raw read of it: each crater label's box and two boxes off it."""
    from tests.detector_fixtures import make_coco

    gt = make_coco(root, n_images=4, size=96, seed=seed, with_ignore=False)
    data = json.loads(gt.read_text())
    for im in data["images"]:
        im["camera"] = {**CAMERA, "fx": 48.0, "fy": 48.0, "cx": 47.5, "cy": 47.5}
    raw = []
    for a in data["annotations"]:
        a.update(diameter_m=6.0, near_rim_range_m=10.0)
        x, y, w, h = a["bbox"]
        raw.append({"image_id": a["image_id"], "category_id": a["category_id"],
                    "bbox": [x, y, w, h], "score": 0.9})
        raw += [{"image_id": a["image_id"], "category_id": 1,
                 "bbox": [(x + 37 * k) % 70, (y + 23 * k) % 70, 20.0, 8.0], "score": 0.4 / k}
                for k in (1, 2)]
    gt.write_text(json.dumps(data))
    (root / "raw.json").write_text(json.dumps(raw))
    return gt, root / "raw.json"


def test_two_sets_read_each_with_the_others_rescorer(tmp_path, capsys):
    (g0, r0), (g1, r1) = (_set_with_camera(tmp_path / f"s{k}", k) for k in (0, 1))
    out = tmp_path / "cf"
    argv = ["--gt", str(g0), str(g1), "--raw", str(r0), str(r1), "--fit-on", "1", "0"]
    assert crossfit.main([*argv, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "set 1 ground: fit on [0]" in printed and "ground - base" in printed
    assert "set 1 photo: fit on [0]" in printed
    assert f"{2 * len(crossfit.ARMS)} rescorer(s) fitted" in printed  # two sets, every arm
    summary = json.loads((out / "summary.json").read_text())
    for arm in crossfit.ARMS:
        cells = summary["arms"][arm]["sets"]
        assert [c["key"] for c in cells] == [
            sum(a["category_id"] == 1 for a in json.loads(g.read_text())["annotations"])
            for g in (g0, g1)]
        assert len(summary["arms"][arm]["found"]) == sum(c["key"] for c in cells)
        assert all(0.0 <= c["ap50"] <= 1.0 for c in cells)
    assert (out / "set0.pkl").exists() and (out / "set1_ground" / "eval" / "metrics.json").exists()
    # the same reads again from the cache, one set's eval folder reused, paired with the first
    again = tmp_path / "again"
    shutil.copytree(out / "set0_base", again / "set0_base")
    for name in ("set0.pkl", "set1.pkl"):
        shutil.copy(out / name, again / name)
    assert crossfit.main([*argv, "--arms", "base", "--jobs", "2", "--reuse", "--against",
                          str(out / "summary.json"), "--out", str(again)]) == 0
    printed = capsys.readouterr().out
    assert "set 0 base: fit on [1] (reused rows" in printed
    assert "1 rescorer(s) fitted" in printed  # set 1's alone
    twice = json.loads((again / "summary.json").read_text())
    assert twice["arms"]["base"]["found"] == summary["arms"]["base"]["found"]
    assert twice["against"]["diff"] == 0.0


def test_sets_that_fit_on_the_same_others_share_one_fit(tmp_path, capsys):
    sets = [_set_with_camera(tmp_path / f"s{k}", k) for k in range(3)]
    out = tmp_path / "cf"
    assert crossfit.main(["--gt", *[str(g) for g, _ in sets], "--raw", *[str(r) for _, r in sets],
                          "--fit-on", "1,2", "0", "0", "--arms", "base", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "2 rescorer(s) fitted" in printed
    assert "set 1 base: fit on [0]" in printed and "set 2 base: fit on [0]" in printed
    first = json.loads((out / "set1_base" / "detections.json").read_text())
    assert len(first) > 0


def _edge_on_crater(width=200, height=120):
    """A gray frame (level 120) with an edge-on crater: a dark band (shadowed wall, 20) over a
    bright one (lit wall, 220), 8 rows each, across columns 60-140."""
    gray = np.full((height, width), 120.0, np.float32)
    gray[50:58, 60:140] = 20.0
    gray[58:66, 60:140] = 220.0
    return gray


def test_a_box_on_a_whole_edge_on_crater_reads_its_bands_and_no_sides():
    gray = _edge_on_crater()
    whole, part, flat = crossfit.photo_features(
        gray, np.array([[60, 50, 140, 66], [60, 50, 100, 66], [60, 80, 140, 96]], np.float64))
    names = crossfit.PHOTO_FEATURES
    f = dict(zip(names, whole, strict=True))
    assert f["photo_rows"] > 10 and f["photo_dark"] == pytest.approx(0.5)
    assert f["photo_fill"] == 1.0 and f["photo_sides"] < 0.05 and f["photo_edges"] > 2
    g = dict(zip(names, part, strict=True))  # the left half: its bands go on past its right side
    assert g["photo_sides"] > 0.9 and g["photo_rows"] == pytest.approx(f["photo_rows"])
    h = dict(zip(names, flat, strict=True))  # plain ground
    assert h["photo_rows"] == h["photo_dark"] == h["photo_fill"] == h["photo_edges"] == 0
    # the crater's bands over half the box's width: half its strips follow them
    half = crossfit.photo_features(gray, np.array([[100, 50, 180, 66]], np.float64))[0]
    assert dict(zip(names, half, strict=True))["photo_fill"] == pytest.approx(0.5)


def test_boxes_at_and_off_the_frame_edge_read_finite_or_zero():
    gray = _edge_on_crater()
    boxes = np.array([[-10, -5, 30, 4], [190, 110, 260, 140], [50, 50, 50.2, 60]], np.float64)
    out = crossfit.photo_features(gray, boxes)
    assert np.isfinite(out).all()
    assert out[2].tolist() == [0.0] * len(crossfit.PHOTO_FEATURES)  # no whole pixel


def test_a_cache_without_pixel_features_gets_them_as_a_fresh_read_has_them(tmp_path, capsys):
    import pickle

    (g0, r0), (g1, r1) = (_set_with_camera(tmp_path / f"s{k}", k) for k in (0, 1))
    argv = ["--gt", str(g0), str(g1), "--raw", str(r0), str(r1), "--fit-on", "1", "0",
            "--arms", "base", "photo"]
    fresh = tmp_path / "fresh"
    assert crossfit.main([*argv, "--out", str(fresh)]) == 0
    old = tmp_path / "old"  # the caches as a run before the pixel features wrote them
    old.mkdir()
    n_old = len(crossfit.FEATURES) + len(crossfit.GROUND_FEATURES)
    for k in (0, 1):
        data = pickle.loads((fresh / f"set{k}.pkl").read_bytes())
        for f in data["frames"]:
            f["features"] = f["features"][:, :n_old]
        (old / f"set{k}.pkl").write_bytes(pickle.dumps(data))
    capsys.readouterr()
    assert crossfit.main([*argv, "--out", str(old)]) == 0
    assert "pixel features of 4/4 frames" in capsys.readouterr().out
    for k in (0, 1):
        a, b = (pickle.loads((d / f"set{k}.pkl").read_bytes()) for d in (fresh, old))
        for fa, fb in zip(a["frames"], b["frames"], strict=True):
            np.testing.assert_array_equal(fa["features"], fb["features"])
    assert (json.loads((old / "summary.json").read_text())["arms"]["photo"]["found"]
            == json.loads((fresh / "summary.json").read_text())["arms"]["photo"]["found"])

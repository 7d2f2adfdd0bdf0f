"""``lunarnav localize``: a rendered stereo pair with known truth, through the CLI."""

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from lunarnav_ml.cli import main
from lunarnav_ml.errors import InputError
from lunarnav_ml.geometry.boxrefine import DEFAULT_BOX_REFINER
from lunarnav_ml.geometry.refine import DEFAULT_REFINER
from lunarnav_ml.runtime.cli import DEFAULT_WEIGHTS, read_camera
from tests.geometry.geometry_scene import render_crater_scene


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """A 5 m crater 8 m ahead at 640 x 480: left, right and camera files, and the scene."""
    sc = render_crater_scene(5.0, 8.0, size=(640, 480), pitch_deg=10.0, sun_zenith_deg=60.0,
                             sun_azimuth_deg=30.0, seed=3)
    root = tmp_path_factory.mktemp("pair")
    cv2.imwrite(str(root / "left.png"), sc.left)
    cv2.imwrite(str(root / "right.png"), sc.right)
    r = sc.rig
    camera = {"fx": r.focal_px, "fy": r.focal_px, "cx": r.cx, "cy": r.cy,
              "baseline_m": r.baseline_m, "height_m": r.height_m, "pitch_deg": r.pitch_deg}
    (root / "camera.json").write_text(json.dumps({"id": 1, "camera": camera}))  # an image record
    return root, sc


def _run(root, *extra):
    return main(["localize", str(root / "left.png"), str(root / "right.png"), "--camera",
                 str(root / "camera.json"), *extra])


def _same_craters_as_detect(root, out, small_read=None, rescorer=None, conf=0.2):
    """``out``'s crater boxes and scores are those `lunarnav detect` gives at ``conf``."""
    from lunarnav_ml.eval.cli import load_predictor
    from lunarnav_ml.geometry.boxrefine import BoxRefinedDetector, BoxRefiner
    from lunarnav_ml.utils.images import read_rgb

    detector = load_predictor(DEFAULT_WEIGHTS, 2, None, small_read=small_read)
    want = BoxRefinedDetector(detector, BoxRefiner(), rescorer).predict(
        [read_rgb(root / "left.png")], conf, 0.6)[0]
    craters = want["labels"] == 1
    assert [c["score"] for c in out["craters"]] == pytest.approx(want["scores"][craters].tolist())
    assert np.allclose([c["box"] for c in out["craters"]], want["boxes"][craters], atol=1e-3)


def test_the_shipped_model_puts_the_crater_where_it_is(pair, tmp_path, capsys):
    """At --conf 0.2: the box refiner's quality rates this toy scene's crater low (its refined
    score is about 0.22, the network's 0.74), under the default 0.3 chosen on the renders."""
    root, sc = pair
    assert DEFAULT_WEIGHTS.is_file()
    assert _run(root, "--conf", "0.2", "--out", str(tmp_path)) == 0
    out = json.loads((tmp_path / "craters3d.json").read_text())
    _same_craters_as_detect(root, out)
    lifted = [c for c in out["craters"] if c["ok"]]
    assert lifted, out["craters"]
    best = max(lifted, key=lambda c: c["score"])
    d = sc.crater.diameter
    assert np.hypot(*(np.array(best["center_m"][:2]) - sc.center_rover[:2])) < max(1.0, 0.25 * d)
    assert abs(best["diameter_m"] - d) < 0.25 * d
    assert out["sgbm"] == {"mode": "hh", "num_disparities": 80} and out["lift_from"] == "box"
    assert out["refiner"] == str(DEFAULT_REFINER)  # on by default
    assert all(isinstance(c["refined"], bool) for c in out["craters"])
    assert np.array(best["covariance_xyzd"]).shape == (4, 4) and best["sigma_horizontal_m"] > 0
    # what the lift read, for a map-matching step to weigh landmarks by
    assert best["lift"]["crest_step"] in ("largest", "lowest", "both")
    assert best["lift"]["flank_rise_m"] > 0 and best["lift"]["rim_disparity_px"] > 0
    assert best["lift"]["n_rim"] >= 8 and 0 <= best["lift"]["crest_fraction"] <= 1
    assert out["min_flank_rise_px"] == 0.12  # the hidden-rim test read to scale, by default
    assert out["small_read"] is None and out["box_rescorer"] is None  # by default
    assert cv2.imread(str(tmp_path / "overlay.jpg")).shape == (480, 640, 3)
    assert set(out["timing_ms"]) == {"detect", "box_refine", "stereo", "craters"}
    assert out["box_refiner"] == str(DEFAULT_BOX_REFINER)  # on by default
    assert all(v > 0 for v in out["timing_ms"].values())
    assert "in 3D (detect " in capsys.readouterr().out


def test_a_second_read_of_the_small_boxes(pair, tmp_path):
    """``--small-read``: the crater boxes are the wrapped detector's, refined as by default."""
    root, sc = pair
    assert _run(root, "--conf", "0.2", "--small-read", "640", "--out", str(tmp_path)) == 0
    out = json.loads((tmp_path / "craters3d.json").read_text())
    assert out["small_read"] == {"side": 640, "below_px": 15.0, "band": None}
    from lunarnav_ml.eval.smallread import SmallBoxReadConfig

    _same_craters_as_detect(root, out, SmallBoxReadConfig(640))
    assert any(c["ok"] and abs(c["diameter_m"] - sc.crater.diameter) < 0.25 * sc.crater.diameter
               for c in out["craters"])
    # a band over the horizon of this camera: pitch 10 deg, fy 320 px, cy 240 of 480 rows
    assert _run(root, "--conf", "0.2", "--small-read", "640", "--small-read-horizon", "15", "31",
                "--out", str(tmp_path / "band")) == 0
    out = json.loads((tmp_path / "band" / "craters3d.json").read_text())
    r = sc.rig
    top = (r.cy - r.focal_px * np.tan(np.radians(25.0))) / 480
    bottom = (r.cy + r.focal_px * np.tan(np.radians(21.0))) / 480
    assert out["small_read"]["band"] == pytest.approx([top, bottom])
    _same_craters_as_detect(root, out, SmallBoxReadConfig(640, band=(top, bottom)))


def test_the_box_rescorer_needs_its_own_threshold(pair, tmp_path, capsys):
    root, _ = pair
    assert _run(root, "--box-rescorer", "--out", str(tmp_path / "a")) == 2
    assert "--box-rescorer: give --conf" in capsys.readouterr().err
    assert not (tmp_path / "a").exists()
    assert _run(root, "--box-rescorer", "--conf", "0.05", "--out", str(tmp_path / "b")) == 0
    out = json.loads((tmp_path / "b" / "craters3d.json").read_text())
    from lunarnav_ml.geometry.boxrescore import DEFAULT_BOX_RESCORER, BoxRescorer

    assert out["box_rescorer"] == str(DEFAULT_BOX_RESCORER) and out["conf"] == 0.05
    _same_craters_as_detect(root, out, rescorer=BoxRescorer(), conf=0.05)
    assert out["craters"], "the toy crater scores above 0.05 with the rescorer"
    assert _run(root, "--box-rescorer", "--conf", "0.05", "--no-box-refiner", "--out",
                str(tmp_path / "c")) == 2
    assert "--no-box-refiner" in capsys.readouterr().err


def test_an_onnx_model_runs_through_the_onboard_runtime(pair, onnx_path, tmp_path):
    root, _ = pair
    assert _run(root, "--weights", str(onnx_path), "--conf", "0.01", "--threads", "1",
                "--sgbm-mode", "3way", "--lift-from", "fit", "--no-refiner",
                "--no-box-refiner", "--out", str(tmp_path)) == 0
    out = json.loads((tmp_path / "craters3d.json").read_text())
    assert out["lift_from"] == "fit" and out["refiner"] is None and out["box_refiner"] is None
    assert out["timing_ms"]["box_refine"] == 0.0
    assert not any(c["refined"] for c in out["craters"])
    assert out["sgbm"] == {"mode": "3way", "num_disparities": 80}  # sized to 640 px
    assert all(c["ok"] == ("center_m" in c) for c in out["craters"])
    assert out["weights"] == str(onnx_path)


def test_a_strict_hidden_rim_test_rejects_the_lifts_it_reads_as_brows(pair, tmp_path):
    """``--min-flank-rise-px`` far above any real crest's rise: every lift that got as far as
    the test is rejected as near_rim_hidden, and the record says which threshold ran."""
    root, _ = pair
    assert _run(root, "--conf", "0.2", "--min-flank-rise-px", "1000", "--out", str(tmp_path)) == 0
    out = json.loads((tmp_path / "craters3d.json").read_text())
    assert out["min_flank_rise_px"] == 1000.0
    assert out["craters"] and not any(c["ok"] for c in out["craters"])
    hidden = [c for c in out["craters"] if c["reason"] == "lift:near_rim_hidden"]
    assert hidden and all(c["lift"]["flank_rise_m"] > 0 for c in hidden)
    # 'none' turns the test off: the record says so
    assert _run(root, "--min-flank-rise-px", "none", "--out", str(tmp_path / "off")) == 0
    assert json.loads((tmp_path / "off" / "craters3d.json").read_text())["min_flank_rise_px"] is None


def test_localize_with_an_onnx_model_never_imports_torch(pair, onnx_path, tmp_path):
    """The whole ``lunarnav`` command, parser and all stage registrations included."""
    root, _ = pair
    probe = ("import sys; from lunarnav_ml.cli import main; code = main(sys.argv[1:]); "
             "heavy = sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'torchvision', "
             "'lightning', 'albumentations'}); print('HEAVY', heavy); sys.exit(code)")
    out = subprocess.run(
        [sys.executable, "-c", probe, "localize", str(root / "left.png"), str(root / "right.png"),
         "--camera", str(root / "camera.json"), "--weights", str(onnx_path), "--conf", "0.01",
         "--out", str(tmp_path)], capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 0, out.stderr
    assert "HEAVY []" in out.stdout
    assert (tmp_path / "craters3d.json").is_file()


def test_read_camera(tmp_path):
    path = tmp_path / "cam.json"
    cam = {"fx": 500, "fy": 500, "cx": 320, "cy": 240, "baseline_m": 0.3, "height_m": 1.5,
           "pitch_deg": 10}
    path.write_text(json.dumps(cam))
    assert read_camera(path) == {**{k: float(v) for k, v in cam.items()}, "roll_deg": 0.0}
    path.write_text(json.dumps({**cam, "baseline_m": None}))
    with pytest.raises(InputError, match="cam.json: camera: missing key 'baseline_m'"):
        read_camera(path)
    path.write_text(json.dumps({**cam, "fx": "wide"}))
    with pytest.raises(InputError, match="cam.json: camera: fx must be a finite number"):
        read_camera(path)


CAMERA_FAULTS = {  # case: (camera fields, expected message)
    "camera_nan": ({"fx": float("nan")}, "camera.json: camera: fx must be a finite number"),
    "cx_far": ({"cx": 5000.0}, "camera: cx (5000.0) lies outside the image, which is 640 px"),
    "cy_negative": ({"cy": -40.0}, "camera: cy (-40.0) lies outside the image, which is 480"),
    "height_negative": ({"height_m": -1}, "camera.json: camera: height_m must be positive"),
    "pitch_400": ({"pitch_deg": 400}, "camera: pitch_deg must lie in [-90, 90], got 400.0"),
    "fx_negative": ({"fx": -1.0}, "camera.json: camera: fx must be positive, got -1.0"),
    "baseline_zero": ({"baseline_m": 0}, "camera: baseline_m must be positive, got 0.0"),
}


@pytest.mark.parametrize("case", [*CAMERA_FAULTS, "camera_corrupt", "sizes", "left_missing",
                                  "conf", "refiner_missing", "rise_negative", "rise_nan"])
def test_bad_inputs_are_one_line_and_write_nothing(pair, tmp_path, capsys, case):
    root, _ = pair
    work = tmp_path / "in"
    work.mkdir()
    for name in ("left.png", "right.png", "camera.json"):
        (work / name).write_bytes((root / name).read_bytes())
    extra, expect = [], {
        **{k: v[1] for k, v in CAMERA_FAULTS.items()},
        "camera_corrupt": "camera.json: camera is not valid JSON",
        "sizes": "right.png: 320x240 px, but the left image is 640x480",
        "left_missing": "left.png: image file not found",
        "conf": "--conf must lie in [0, 1]",
        "refiner_missing": "nope.onnx: disparity refiner not found",
        "rise_negative": "--min-flank-rise-px must be a finite number >= 0 or 'none', got -0.1",
        "rise_nan": "--min-flank-rise-px must be a finite number >= 0 or 'none', got nan"}[case]
    if case in CAMERA_FAULTS:
        rec = json.loads((work / "camera.json").read_text())
        rec["camera"].update(CAMERA_FAULTS[case][0])
        (work / "camera.json").write_text(json.dumps(rec))
    elif case == "camera_corrupt":
        (work / "camera.json").write_text('{"camera": {')
    elif case == "sizes":
        cv2.imwrite(str(work / "right.png"), np.zeros((240, 320), np.uint8))
    elif case == "left_missing":
        (work / "left.png").unlink()
    elif case == "conf":
        extra = ["--conf", "1.5"]
    elif case.startswith("rise_"):
        extra = ["--min-flank-rise-px", {"rise_negative": "-0.1", "rise_nan": "nan"}[case]]
    else:
        extra = ["--refiner", str(work / "nope.onnx")]
    code = _run(work, *extra, "--out", str(tmp_path / "out"))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and expect in err[0], err
    assert not (tmp_path / "out").exists()

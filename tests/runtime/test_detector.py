"""OnnxDetector: the predict contract, torch-free imports (detector and stereo crater stages), threads and sizes, bad files."""

import json
import subprocess
import sys

import numpy as np
import onnx
import pytest
import torch

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.export.bench import synthetic_frame
from lunarnav_ml.runtime import OnnxDetector

# Top-level packages the onboard runtime must never load.
HEAVY = ("torch", "torchvision", "lightning", "kornia", "albumentations", "onnx")

PROBE = """
import json, sys
HEAVY = sys.argv[2].split(",")
import numpy as np
for name in sys.argv[3:]:
    __import__(name)
from lunarnav_ml.runtime import OnnxDetector
det = OnnxDetector(sys.argv[1], threads=1)
out = det.predict([np.zeros((100, 140, 3), np.uint8) + 90], conf_thres=0.001)
from lunarnav_ml.geometry.frames import StereoRig
from lunarnav_ml.runtime import StereoCraterLocalizer
rng = np.random.default_rng(0)
left = (rng.random((100, 140, 3)) * 255).astype(np.uint8)
right = np.roll(left, -4, axis=1)
loc = StereoCraterLocalizer(det, StereoRig(70.0, 0.3, 69.5, 49.5, 1.5, 10.0), conf_thres=0.02)
craters = loc(left, right)
one = loc.localize_box(left, loc.disparity(left, right), np.array([30., 20., 90., 70.]), 0.5)
craters = [*craters, one]
heavy = sorted({m.split('.')[0] for m in sys.modules} & set(HEAVY))
print(json.dumps({"n": len(out[0]["boxes"]), "craters": len(craters), "heavy": heavy}))
"""


def run_probe(onnx_path, *imports):
    proc = subprocess.run([sys.executable, "-c", PROBE, str(onnx_path), ",".join(HEAVY), *imports],
                          check=False, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_importing_and_running_never_imports_torch(onnx_path):
    result = run_probe(onnx_path)
    assert result["n"] > 0 and result["craters"] > 0 and result["heavy"] == []


def test_the_probe_sees_a_heavy_import(onnx_path):
    assert run_probe(onnx_path, "onnx")["heavy"] == ["onnx"]


def test_predict_contract(onnx_path):
    images = [synthetic_frame(128), synthetic_frame(200, seed=1)[:100]]
    out = OnnxDetector(onnx_path).predict(images, conf_thres=0.01, max_det=20)
    assert len(out) == 2
    for det, image in zip(out, images):
        n = len(det["boxes"])
        assert 0 < n <= 20 and det["boxes"].shape == (n, 4) and det["boxes"].dtype == np.float32
        assert det["scores"].shape == (n,) and np.all(np.diff(det["scores"]) <= 0)
        assert det["labels"].dtype == np.int64 and set(det["labels"]) <= {1, 2, 3}
        assert det["boxes"][:, [0, 2]].max() <= image.shape[1]
        assert det["boxes"][:, [1, 3]].max() <= image.shape[0]
        assert det["scores"].min() > 0.01
    assert OnnxDetector(onnx_path).predict([]) == []


def test_threads_do_not_change_results(onnx_path):
    image = [synthetic_frame(128, seed=4)]
    one = OnnxDetector(onnx_path, threads=1).predict(image, conf_thres=0.01)[0]
    two = OnnxDetector(onnx_path, threads=2).predict(image, conf_thres=0.01)[0]
    np.testing.assert_allclose(one["boxes"], two["boxes"], atol=1e-3)
    with pytest.raises(ConfigError, match="threads"):
        OnnxDetector(onnx_path, threads=0)


def test_img_size(onnx_path, onnx_static_path):
    assert OnnxDetector(onnx_path, img_size=(96, 160)).img_size == (96, 160)
    with pytest.raises(ConfigError, match="multiples of 32"):
        OnnxDetector(onnx_path, img_size=100)
    with pytest.raises(ConfigError, match="fixed input"):
        OnnxDetector(onnx_static_path, img_size=160)
    static = OnnxDetector(onnx_static_path)
    with pytest.raises(InputError, match="batch 1"):
        static.forward(np.zeros((2, 3, 128, 128), np.float32))


@pytest.mark.parametrize(("batch", "match"), [
    (np.zeros((1, 3, 128, 128), np.float64), "float32"),
    (np.zeros((1, 4, 128, 128), np.float32), r"\(B, 3, H, W\)"),
    (np.zeros((1, 3, 100, 128), np.float32), "multiples of 32"),
])
def test_bad_batches(onnx_path, batch, match):
    with pytest.raises(InputError, match=match):
        OnnxDetector(onnx_path).forward(batch)


def test_bad_images(onnx_path):
    det = OnnxDetector(onnx_path)
    with pytest.raises(InputError, match=r"images\[0\].*uint8"):
        det.predict([np.zeros((64, 64, 3), np.float32)])
    with pytest.raises(InputError, match=r"images\[0\].*3 channels"):
        det.predict([np.zeros((64, 64, 1), np.uint8)])
    with pytest.raises(ConfigError, match="conf_thres"):
        det.predict([np.zeros((64, 64, 3), np.uint8)], conf_thres=1.5)


def test_missing_and_truncated_files(onnx_path, tmp_path):
    with pytest.raises(InputError, match="not found"):
        OnnxDetector(tmp_path / "none.onnx")
    cut = tmp_path / "cut.onnx"
    cut.write_bytes(onnx_path.read_bytes()[:5000])
    with pytest.raises(InputError, match="cut.onnx: not a loadable ONNX model"):
        OnnxDetector(cut)
    text = tmp_path / "text.onnx"
    text.write_text("hello")
    with pytest.raises(InputError, match="text.onnx"):
        OnnxDetector(text)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_foreign_onnx_file(tmp_path):
    path = tmp_path / "foreign.onnx"
    torch.onnx.export(torch.nn.Conv2d(3, 8, 3), (torch.zeros(1, 3, 32, 32),), path,
                      dynamo=False, input_names=["images"])
    with pytest.raises(InputError, match="foreign.onnx: not a lunarnav export"):
        OnnxDetector(path)


def test_incompatible_export_version(onnx_path, tmp_path):
    model = onnx.load(onnx_path)
    for prop in model.metadata_props:
        if prop.key == "lunarnav.format_version":
            prop.value = "2"
    path = tmp_path / "future.onnx"
    onnx.save(model, path)
    with pytest.raises(InputError, match="format version 2.*re-export"):
        OnnxDetector(path)


def test_metadata_inconsistent_with_graph(onnx_path, tmp_path):
    model = onnx.load(onnx_path)
    for prop in model.metadata_props:
        if prop.key == "lunarnav.class_names":
            prop.value = json.dumps(["crater", "rock"])
    path = tmp_path / "two.onnx"
    onnx.save(model, path)
    with pytest.raises(InputError, match="2 classes"):
        OnnxDetector(path)


def test_class_names_that_disagree_with_the_graph_name_the_key(onnx_path, tmp_path):
    model = onnx.load(onnx_path)
    for prop in model.metadata_props:
        if prop.key == "lunarnav.class_names":
            prop.value = json.dumps(["crater"])
    path = tmp_path / "one.onnx"
    onnx.save(model, path)
    with pytest.raises(InputError, match="one.onnx: metadata lunarnav.class_names names 1 class "
                                         "but output 'decoded' scores 3"):
        OnnxDetector(path)

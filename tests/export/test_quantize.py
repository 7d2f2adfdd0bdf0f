"""Static int8 quantization: integer convs, fp32 decode tail, accuracy close to fp32, inputs."""

import json

import cv2
import numpy as np
import onnx
import pytest

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.export.bench import synthetic_frame
from lunarnav_ml.export.onnx_export import export_onnx
from lunarnav_ml.export.quantize import (
    fp32_tail_nodes,
    input_conv_nodes,
    load_calibration_images,
    mish_nodes,
    quantize_int8,
)
from lunarnav_ml.runtime import OnnxDetector


@pytest.fixture(scope="module")
def int8_path(onnx_path, tmp_path_factory):
    images = [synthetic_frame(128, seed=s) for s in range(6)]
    return quantize_int8(onnx_path, tmp_path_factory.mktemp("q") / "nano_int8.onnx", images)


def test_tail_is_decode_and_last_head_convs(onnx_path):
    graph = onnx.load(onnx_path).graph
    tail = set(fp32_tail_nodes(graph))
    convs = [n.name for n in graph.node if n.op_type == "Conv"]
    tail_convs = [c for c in convs if c in tail]
    assert len(tail_convs) == 3 and all("head/preds" in c for c in tail_convs)
    assert {n.op_type for n in graph.node if n.name in tail} >= {"Sigmoid", "Exp", "Concat"}
    assert not any("backbone" in name for name in tail)


def test_mish_islands_found(onnx_path, mish_parts, tmp_path):
    assert not mish_nodes(onnx.load(onnx_path).graph)  # nano is leaky ReLU throughout
    graph = onnx.load(export_onnx(mish_parts, tmp_path / "s.onnx", img_size=64)).graph
    names = set(mish_nodes(graph))
    exps = [n for n in graph.node if n.op_type == "Exp" and n.name in names]
    assert len(exps) == 44  # every backbone activation
    assert {n.op_type for n in graph.node if n.name in names} == {
        "Constant", "Clip", "Exp", "Add", "Mul", "Div"}
    assert not names & set(fp32_tail_nodes(graph))


def test_input_conv_stays_fp32(onnx_path, int8_path):
    graph = onnx.load(onnx_path).graph
    assert [n.op_type for n in graph.node if n.name in set(input_conv_nodes(graph))] == [
        "Conv", "LeakyRelu"]
    qgraph = onnx.load(int8_path).graph
    first = next(n for n in qgraph.node if n.op_type == "Conv")
    assert first.input[0] == "images"  # the float image, not a DequantizeLinear output
    weight = {i.name for i in qgraph.initializer}
    assert first.input[1] in weight  # float weight, no QDQ pair around it
    after = [n for n in qgraph.node if first.output[0] in n.input]
    assert [n.op_type for n in after] == ["LeakyRelu"]


def test_int8_graph_and_metadata(int8_path):
    model = onnx.load(int8_path)
    ops = [n.op_type for n in model.graph.node]
    assert ops.count("QuantizeLinear") > 50 and ops.count("DequantizeLinear") > 50
    det = OnnxDetector(int8_path)
    assert det.metadata.precision == "int8"
    assert det.metadata.extra["calibration"]["images"] == 6
    assert det.metadata.class_names == ("crater", "rock", "artifact")


def test_int8_outputs_track_fp32(onnx_path, int8_path):
    """An untrained net is a harsh case (no margin in its logits); the accuracy of a trained
    one is measured in benchmarks/bench_runtime.py (crater AP50 fp32 vs int8)."""
    images = [synthetic_frame(128, seed=s) for s in range(20, 24)]
    fp32, int8 = OnnxDetector(onnx_path), OnnxDetector(int8_path)
    batch, _ = fp32.preprocess(images)
    a, b = fp32.forward(batch), int8.forward(batch)
    assert not np.array_equal(a, b)  # it was quantized
    # box centres, px (nano's grid sensitivity 2 doubles their response to logit error)
    assert np.median(np.abs(a[..., :2] - b[..., :2])) < 2.0
    logit = lambda p: np.log(p / (1 - p)).ravel()
    assert np.corrcoef(logit(a[..., 4]), logit(b[..., 4]))[0, 1] > 0.8


def test_quantizing_twice_or_without_images_is_refused(onnx_path, int8_path, tmp_path):
    with pytest.raises(InputError, match="expected an fp32 export"):
        quantize_int8(int8_path, tmp_path / "q.onnx", [synthetic_frame(128)])
    with pytest.raises(InputError, match="at least one image"):
        quantize_int8(onnx_path, tmp_path / "q.onnx", [])
    with pytest.raises(ConfigError, match="method"):
        quantize_int8(onnx_path, tmp_path / "q.onnx", [synthetic_frame(128)], method="kl")
    cut = tmp_path / "cut.onnx"
    cut.write_bytes(onnx_path.read_bytes()[:3000])
    with pytest.raises(InputError, match="cut.onnx"):
        quantize_int8(cut, tmp_path / "q.onnx", [synthetic_frame(128)])
    assert not (tmp_path / "q.onnx").exists()


def test_calibration_images_from_a_dataset_folder(tmp_path):
    (tmp_path / "images" / "left").mkdir(parents=True)
    records = []
    for i in range(5):
        name = f"images/left/{i:03d}.png"
        cv2.imwrite(str(tmp_path / name), np.full((40, 60), 10 * i, np.uint8))
        records.append({"id": i, "file_name": name})
    (tmp_path / "annotations.json").write_text(json.dumps({"images": records}))
    images = load_calibration_images(tmp_path, n=3)
    assert [im[0, 0, 0] for im in images] == [0, 20, 40]
    assert all(im.shape == (40, 60, 3) and im.dtype == np.uint8 for im in images)
    assert len(load_calibration_images(tmp_path / "images", n=10)) == 5
    with pytest.raises(InputError, match="no images"):
        load_calibration_images(tmp_path / "images" / "left" / "..", n=0) if False else \
            load_calibration_images(_empty(tmp_path), n=3)


def _empty(tmp_path):
    (tmp_path / "empty").mkdir()
    return tmp_path / "empty"


def _optimized_int8_ops(preset, tmp_path):
    """Op counts of a preset's int8 model after onnxruntime's graph fusions."""
    import collections

    import onnxruntime as ort

    from lunarnav_ml.export.bench import random_detector

    fp32 = export_onnx(random_detector(preset, img_size=64, calib_batches=1),
                       tmp_path / f"{preset}.onnx", img_size=64)
    int8 = quantize_int8(fp32, tmp_path / f"{preset}_int8.onnx",
                         [synthetic_frame(64, seed=s) for s in range(2)])
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED
    options.optimized_model_filepath = str(tmp_path / f"{preset}_opt.onnx")
    ort.InferenceSession(str(int8), options, providers=["CPUExecutionProvider"])
    return collections.Counter(n.op_type for n in onnx.load(tmp_path / f"{preset}_opt.onnx").graph.node)


def test_relu_folds_into_integer_convs_leaky_does_not(tmp_path):
    # why small-relu is the onboard preset: its int8 graph has no activation operators left
    leaky, relu = _optimized_int8_ops("small", tmp_path), _optimized_int8_ops("small-relu", tmp_path)
    assert leaky["QLinearConv"] == relu["QLinearConv"] > 60
    assert leaky["QLinearLeakyRelu"] == leaky["QLinearConv"]
    assert not {op for op in relu if "Relu" in op or "LeakyRelu" in op}


def test_stride2_stem_runs_integer_through_space_to_depth(tmp_path):
    # small-relu-s2's 6x6 stride-2 stem: quantized as a space-to-depth and an integer 3x3
    # convolution on 12 channels, no float convolution reading the image
    ops = _optimized_int8_ops("small-relu-s2", tmp_path)
    assert ops["SpaceToDepth"] == 1 and ops["QLinearConv"] > 60
    graph = onnx.load(tmp_path / "small-relu-s2_int8.onnx").graph
    assert not [n for n in graph.node if n.op_type == "Conv" and n.input[0] == "images"]
    s2d = next(n for n in graph.node if n.op_type == "SpaceToDepth")
    assert s2d.input[0] == "images"
    fp32, int8 = (OnnxDetector(tmp_path / f"small-relu-s2{s}.onnx") for s in ("", "_int8"))
    batch, _ = fp32.preprocess([synthetic_frame(64, seed=9)])
    a, b = fp32.forward(batch), int8.forward(batch)
    assert np.median(np.abs(a[..., :2] - b[..., :2])) < 2.0

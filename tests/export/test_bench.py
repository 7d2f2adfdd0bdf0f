"""Benchmark plumbing: latency statistics, conv FLOPs (known answer), untrained presets."""

import numpy as np
import onnx
import pytest
import torch
from onnx import TensorProto, helper, numpy_helper

from lunarnav_ml.export.bench import (
    bench_onnx,
    bench_torch,
    conv_flops,
    random_detector,
    stage_of,
    stage_times,
    synthetic_frame,
    time_calls,
)


def test_time_calls_statistics():
    calls = []
    stats = time_calls(lambda: calls.append(1), runs=5, warmup=2)
    assert len(calls) == 7 and stats.runs == 5
    assert 0 <= stats.min_ms <= stats.median_ms <= stats.p90_ms
    with pytest.raises(ValueError):
        time_calls(lambda: None, runs=0)


def test_conv_flops_known_answer(tmp_path):
    w1 = numpy_helper.from_array(np.zeros((8, 3, 3, 3), np.float32), "w1")
    w2 = numpy_helper.from_array(np.zeros((4, 4, 1, 1), np.float32), "w2")  # 2 groups
    graph = helper.make_graph(
        [helper.make_node("Conv", ["images", "w1"], ["y"], pads=[1, 1, 1, 1], strides=[2, 2]),
         helper.make_node("Conv", ["y", "w2"], ["z"], group=2)],
        "g", [helper.make_tensor_value_info("images", TensorProto.FLOAT, ["b", 3, "h", "w"])],
        [helper.make_tensor_value_info("z", TensorProto.FLOAT, ["b", 4, "h2", "w2"])], [w1, w2])
    path = tmp_path / "c.onnx"
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), path)
    # conv1: 8 x 16 x 16 outputs x 27 MACs; conv2: 4 x 16 x 16 outputs x 4 MACs
    assert conv_flops(path, 32) == 2 * (8 * 256 * 27 + 4 * 256 * 4)


def test_nano_flops_scale_with_pixels(onnx_path):
    small, big = conv_flops(onnx_path, 256), conv_flops(onnx_path, 512)
    assert big == pytest.approx(4 * small, rel=1e-6) and 0.5e9 < small < 5e9


def test_random_detector_has_live_activations():
    parts = random_detector("nano", img_size=64, seed=1)
    x = torch.rand(1, 3, 64, 64)
    with torch.no_grad():
        raw = parts.model(x)
    assert all(r.std() > 0.1 for r in raw)
    assert parts.img_size == (64, 64) and parts.name == "nano"


def test_bench_runs_both_runtimes(parts, onnx_path):
    assert bench_onnx(onnx_path, 64, runs=2, warmup=1).median_ms > 0
    assert bench_onnx(onnx_path, 64, runs=1, warmup=0, network_only=True).median_ms > 0
    assert bench_onnx(onnx_path, 64, runs=1, warmup=0, frame_size=128).median_ms > 0
    assert bench_torch(parts, 64, runs=1, warmup=0).median_ms > 0


def test_synthetic_frame_is_textured_rgb():
    frame = synthetic_frame(64, seed=2)
    assert frame.shape == (64, 64, 3) and frame.dtype == np.uint8 and frame.std() > 20
    np.testing.assert_array_equal(frame, synthetic_frame(64, seed=2))


def test_stage_of_names_the_module():
    assert stage_of("/model/backbone/stages.0/down/down.2/Relu_output_0_nchwc") \
        == "backbone/stages.0"
    assert stage_of("/model/backbone/stem/stem.0/Conv_token_23") == "backbone/stem"
    assert stage_of("/model/head/convs.1/convs.1.0/Conv") == "head/convs.1"
    assert stage_of("/model/neck/Concat_1") == "neck (joins)"
    assert stage_of("reorder_token_7") == "other"


def test_stage_times_split_the_network(onnx_path):
    by_stage, by_op = stage_times(onnx_path, 64, runs=2, warmup=1)
    assert {"backbone/stem", "backbone/stages.0", "backbone/stages.4"} <= set(by_stage)
    assert any(k.startswith("head/") for k in by_stage)
    assert sum(by_stage.values()) == pytest.approx(sum(by_op.values()))
    assert by_op["Conv"] > 0 and all(v >= 0 for v in by_stage.values())
    with pytest.raises(ValueError):
        stage_times(onnx_path, 64, runs=0)

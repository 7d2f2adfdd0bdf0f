"""ONNX export: checker, metadata, dynamic axes, parity with eager PyTorch (pre-NMS and final
detections), in-graph NMS, OpenCV DNN as a second runtime, bad arguments."""

import copy
import dataclasses

import cv2
import numpy as np
import onnx
import pytest
import torch

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.export.bench import synthetic_frame
from lunarnav_ml.export.onnx_export import ExportMish, export_onnx
from lunarnav_ml.models.decode import decode, postprocess
from lunarnav_ml.runtime import OnnxDetector
from lunarnav_ml.runtime.preprocess import prepare_batch


def torch_decoded(parts, batch: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        raw = parts.model(torch.from_numpy(batch))
        return decode(raw, parts.anchors, parts.strides, parts.scale_xy).numpy()


def torch_predict(parts, images, size, conf, iou):
    """Reference pipeline: the runtime's letterbox, eager model, torch decode + NMS."""
    batch, boxes = prepare_batch(images, (size, size))
    dets = postprocess(torch.from_numpy(torch_decoded(parts, batch)), conf, iou)
    return [{"boxes": lb.boxes_to_image(d["boxes"].numpy()), "scores": d["scores"].numpy(),
             "labels": d["labels"].numpy()} for d, lb in zip(dets, boxes)]


def assert_decoded_close(got, ref):
    """rtol 1e-3 everywhere; absolute floors of 0.01 px on box fields, 1e-5 on probabilities
    (a relative test alone is meaningless for a value near 0: on an AVX2-only CPU the float
    summation order of onnxruntime and PyTorch differs enough to move a 0.4 px box side of
    this untrained net by 0.002 px)."""
    np.testing.assert_allclose(got[..., :4], ref[..., :4], rtol=1e-3, atol=1e-2)
    np.testing.assert_allclose(got[..., 4:], ref[..., 4:], rtol=1e-3, atol=1e-5)


def assert_same_detections(ref, got, tol_px=0.5):
    assert len(ref["boxes"]) == len(got["boxes"]) > 0
    for box, label in zip(ref["boxes"], ref["labels"]):
        err = np.abs(got["boxes"] - box).max(axis=1)
        err[got["labels"] != label] = np.inf
        assert err.min() <= tol_px, f"no runtime box within {tol_px} px of {box}"


def test_checker_opset_and_metadata(onnx_path, parts):
    model = onnx.load(onnx_path)
    onnx.checker.check_model(model, full_check=True)
    assert {o.domain: o.version for o in model.opset_import}[""] == 17
    det = OnnxDetector(onnx_path)
    meta = det.metadata
    assert meta.class_names == ("crater", "rock", "artifact")
    assert meta.input_size == (128, 128) and meta.strides == (8, 16, 32)
    np.testing.assert_allclose(np.array(meta.anchors), parts.anchors.numpy())
    assert meta.scale_xy == pytest.approx(parts.scale_xy)
    assert meta.mean == (0, 0, 0) and meta.std == (1, 1, 1) and meta.model == "nano"
    assert meta.project_version and meta.precision == "fp32" and not meta.nms_in_graph


def test_dynamic_and_static_axes(onnx_path, onnx_static_path):
    dyn = onnx.load(onnx_path).graph.input[0].type.tensor_type.shape.dim
    assert [d.dim_param for d in dyn] == ["batch", "", "height", "width"]
    static = onnx.load(onnx_static_path).graph.input[0].type.tensor_type.shape.dim
    assert [d.dim_value for d in static] == [1, 3, 128, 128]


@pytest.mark.parametrize("size", [128, 192])
def test_pre_nms_parity_with_eager_torch(parts, onnx_path, size):
    batch = np.random.default_rng(size).random((2, 3, size, size), dtype=np.float32)
    ref = torch_decoded(parts, batch)
    got = OnnxDetector(onnx_path, img_size=size).forward(batch)
    assert got.shape == ref.shape == (2, 3 * 21 * (size // 32) ** 2, 8)
    assert_decoded_close(got, ref)


def test_final_detections_match_over_a_test_set(parts, onnx_path):
    images = [synthetic_frame(s, seed=i) for i, s in enumerate((128, 200, 96, 256))]
    images.append(np.ascontiguousarray(synthetic_frame(300, seed=9)[:150]))  # 150 x 300
    ref = torch_predict(parts, images, 128, conf=0.01, iou=0.6)
    got = OnnxDetector(onnx_path).predict(images, conf_thres=0.01, iou_thres=0.6)
    for r, g in zip(ref, got, strict=True):
        assert_same_detections(r, g)


def test_nms_in_graph_matches_numpy_nms(onnx_path, onnx_nms_path):
    images = [synthetic_frame(128, seed=s) for s in range(3)]
    ref = OnnxDetector(onnx_path).predict(images, conf_thres=0.005, iou_thres=0.5, max_det=50)
    got = OnnxDetector(onnx_nms_path).predict(images, conf_thres=0.005, iou_thres=0.5,
                                              max_det=50)
    for r, g in zip(ref, got):
        np.testing.assert_allclose(g["scores"], r["scores"], rtol=1e-6)
        np.testing.assert_allclose(g["boxes"], r["boxes"], atol=1e-4)
        np.testing.assert_array_equal(g["labels"], r["labels"])


@pytest.mark.parametrize("size", [128, 192])
def test_opencv_dnn_matches_onnxruntime(onnx_path, size):
    net = cv2.dnn.readNetFromONNX(str(onnx_path))
    batch = np.random.default_rng(7).random((1, 3, size, size), dtype=np.float32)
    net.setInput(batch)
    got = net.forward()
    ref = OnnxDetector(onnx_path, img_size=size).forward(batch)
    assert_decoded_close(got, ref)


def test_export_mish_is_mish():
    x = torch.linspace(-60, 60, 20001)
    torch.testing.assert_close(ExportMish()(x), torch.nn.functional.mish(x), rtol=1e-5,
                               atol=1e-6)


def test_caller_model_left_in_train_mode(mish_parts, tmp_path):
    parts = mish_parts
    parts.model.train()
    export_onnx(parts, tmp_path / "m.onnx", img_size=64)
    assert parts.model.training
    assert any(isinstance(m, torch.nn.Mish) for m in parts.model.modules())  # swap undone


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"opset": 9}, "opset"), ({"img_size": 100}, "multiples of 32"),
    ({"img_size": (128, 128, 3)}, "img_size"),
])
def test_bad_arguments_raise_config_error_and_write_nothing(parts, tmp_path, kwargs, match):
    with pytest.raises(ConfigError, match=match):
        export_onnx(parts, tmp_path / "m.onnx", **kwargs)
    assert list(tmp_path.iterdir()) == []


def test_missing_checkpoint_names_the_file(tmp_path):
    with pytest.raises(InputError, match="nope.ckpt"):
        export_onnx(tmp_path / "nope.ckpt", tmp_path / "m.onnx")


def test_object_without_detector_attributes_is_rejected(tmp_path):
    with pytest.raises(InputError, match="anchors"):
        export_onnx(torch.nn.Conv2d(3, 8, 1), tmp_path / "m.onnx")


def test_runtime_matches_detector_predict(parts, onnx_path):
    """The contract: OnnxDetector.predict == training.api.Detector.predict (boxes within 0.5
    px) on images of several sizes and aspect ratios (letterbox included)."""
    from lunarnav_ml.training.api import Detector

    detector = Detector(parts.model, 128, list(parts.class_names), "nano")
    images = [synthetic_frame(s, seed=10 + i) for i, s in enumerate((128, 160, 64, 512))]
    images.append(np.ascontiguousarray(synthetic_frame(240, seed=3)[:, :120]))  # 240 x 120
    ref = detector.predict(images, conf_thres=0.01, iou_thres=0.6)
    got = OnnxDetector(onnx_path).predict(images, conf_thres=0.01, iou_thres=0.6)
    for r, g in zip(ref, got, strict=True):
        assert_same_detections(r, g)


def test_export_from_checkpoint_path(parts, tmp_path):
    from lunarnav_ml.training.api import Detector

    ckpt = Detector(parts.model, 128, list(parts.class_names), "nano").save(tmp_path / "d.pt")
    out = export_onnx(ckpt, tmp_path / "d.onnx", img_size=96)
    det = OnnxDetector(out)
    assert det.img_size == (96, 96) and det.metadata.model == "nano"
    batch = np.random.default_rng(1).random((1, 3, 96, 96), dtype=np.float32)
    assert_decoded_close(det.forward(batch), torch_decoded(parts, batch))


def test_channels_last_model_exports_the_same_graph_values(parts, tmp_path):
    """A model trained on a GPU is channels-last (DetectorModule.channels_last): its export
    computes what the NCHW model's does."""
    model = copy.deepcopy(parts.model).to(memory_format=torch.channels_last)
    path = export_onnx(dataclasses.replace(parts, model=model), tmp_path / "cl.onnx")
    batch = np.random.default_rng(7).random((1, 3, 128, 128), dtype=np.float32)
    assert_decoded_close(OnnxDetector(path, img_size=128).forward(batch),
                         torch_decoded(parts, batch))


def test_four_anchors_per_level_save_load_and_export(parts, tmp_path):
    """A model given a fourth anchor per level (``model.reanchor``) round-trips through a
    slim file and exports with every anchor's boxes."""
    from lunarnav_ml.training.api import Detector, load_detector
    from lunarnav_ml.training.checkpoint import reanchor

    model = copy.deepcopy(parts.model)
    flat = torch.tensor([[[30.0, 3.0]], [[60.0, 5.0]], [[120.0, 8.0]]])
    reanchor(model, torch.cat([model.anchors, flat], dim=1))
    ckpt = Detector(model, 128, list(parts.class_names), "nano").save(tmp_path / "a4.pt")
    loaded = load_detector(ckpt)
    assert loaded.model.head.num_anchors == 4
    det = OnnxDetector(export_onnx(ckpt, tmp_path / "a4.onnx", img_size=128))
    batch = np.random.default_rng(4).random((1, 3, 128, 128), dtype=np.float32)
    with torch.no_grad():
        ref = decode(model(torch.from_numpy(batch)), model.anchors, model.strides,
                     model.scale_xy).numpy()
    got = det.forward(batch)
    assert got.shape == ref.shape == (1, 4 * 21 * 4 ** 2, 8)
    assert_decoded_close(got, ref)

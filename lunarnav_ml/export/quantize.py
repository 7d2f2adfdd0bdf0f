"""Static int8 quantization of an exported detector with onnxruntime's quantization tools.

QDQ format, activations uint8 (asymmetric, calibrated on images), weights int8 per output
channel: onnxruntime fuses each DequantizeLinear -> Conv -> QuantizeLinear into an integer
convolution (VNNI/AMX where the CPU has them). The box decoding, the NMS tail and the head's
last 1x1 convolutions stay fp32: they turn logits into pixel coordinates, where an int8 step
would move boxes by whole pixels, and they cost little. Mish activations stay fp32 too
(onnxruntime has no integer Mish; see :func:`mish_nodes`), and so does the input convolution
with its activation (:func:`input_conv_nodes`): with three input channels an integer kernel
is slower than the float one, and the image itself is the least quantizable tensor. A 6x6
stride-2 input convolution (the ``small-relu-s2`` stem) is first rewritten as a space-to-depth
of the image and a 3x3 convolution on its twelve channels, which is quantized with the rest.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import onnx
from google.protobuf.message import DecodeError
from onnxruntime.quantization import (
    CalibrationDataReader,
    CalibrationMethod,
    QuantFormat,
    QuantType,
    quantize_static,
)

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.export.graph_passes import space_to_depth_input_convs
from lunarnav_ml.export.onnx_meta import read_metadata, set_metadata
from lunarnav_ml.runtime import metadata as md
from lunarnav_ml.runtime.preprocess import prepare_batch
from lunarnav_ml.utils.atomic import write_bytes
from lunarnav_ml.utils.images import IMAGE_SUFFIXES, read_rgb

CALIBRATION_METHODS = {"minmax": CalibrationMethod.MinMax,
                       "percentile": CalibrationMethod.Percentile,
                       "entropy": CalibrationMethod.Entropy}


class ImageCalibrationReader(CalibrationDataReader):
    """Feeds letterboxed calibration images to onnxruntime's calibrator, one per call.

    Args:
        images: HxWx3 uint8 RGB images.
        meta: the model's metadata (input size, normalization, NMS inputs).
        size: (H, W) network input; default the metadata's.
    """

    def __init__(self, images: Sequence[np.ndarray], meta: md.ModelMetadata,
                 size: tuple[int, int] | None = None) -> None:
        self.images, self.meta = list(images), meta
        self.size = size or meta.input_size
        self._it: Iterator[np.ndarray] = iter(self.images)

    def get_next(self) -> dict[str, np.ndarray] | None:
        image = next(self._it, None)
        if image is None:
            return None
        batch, _ = prepare_batch([image], self.size, self.meta.pad_value, self.meta.mean,
                                 self.meta.std)
        feeds = {md.INPUT_NAME: batch}
        if self.meta.nms_in_graph:
            feeds.update({md.CONF_NAME: np.array([0.25], np.float32),
                          md.IOU_NAME: np.array([0.6], np.float32),
                          md.MAX_PER_CLASS_NAME: np.array([100], np.int64)})
        return feeds

    def rewind(self) -> None:
        self._it = iter(self.images)


def fp32_tail_nodes(graph: onnx.GraphProto) -> list[str]:
    """Names of the nodes kept fp32: every node with no Conv downstream (decode, NMS) and the
    last Conv of each head branch.

    Relies on ``graph.node`` being topologically sorted (an ONNX requirement).
    """
    consumers: dict[str, list[int]] = {}
    for i, node in enumerate(graph.node):
        for name in node.input:
            consumers.setdefault(name, []).append(i)
    conv_below = [False] * len(graph.node)
    for i in reversed(range(len(graph.node))):
        below = [j for out in graph.node[i].output for j in consumers.get(out, [])]
        conv_below[i] = any(graph.node[j].op_type == "Conv" or conv_below[j] for j in below)
    return [n.name for n, below in zip(graph.node, conv_below) if not below]


ACTIVATION_OPS = {"LeakyRelu", "Relu"}  # one-input activations after a conv (Mish: mish_nodes)


def input_conv_nodes(graph: onnx.GraphProto) -> list[str]:
    """Names of the Conv nodes that read a graph input and of the activation right after each
    (a node whose only input is that Conv's output)."""
    inputs = {i.name for i in graph.input}
    convs = [n for n in graph.node if n.op_type == "Conv" and n.input[0] in inputs]
    outs = {n.output[0] for n in convs}
    acts = [n for n in graph.node if n.op_type in ACTIVATION_OPS
            and n.input and all(i in outs for i in n.input)]
    return [n.name for n in convs + acts]


MISH_OPS = {"Clip", "Exp", "Add", "Mul", "Div"}  # the ops of ExportMish (export/onnx_export.py)


def mish_nodes(graph: onnx.GraphProto) -> list[str]:
    """Names of the nodes of each exported Mish (``x n / (n + 2)``, ``n = e^x (e^x + 2)``).

    They stay fp32 as one island per activation (dequantize, Mish, quantize): the
    intermediate ``n`` spans up to e^40, which a uint8 scale cannot hold. A Mish is found as
    the module scope (node name up to the last "/") of an Exp whose scope holds only Mish ops.
    """
    scopes: dict[str, list[onnx.NodeProto]] = {}
    for node in graph.node:
        scopes.setdefault(node.name.rsplit("/", 1)[0], []).append(node)
    return [n.name for nodes in scopes.values()
            if any(n.op_type == "Exp" for n in nodes)
            and {n.op_type for n in nodes} - {"Constant"} == MISH_OPS
            for n in nodes]


def _name_nodes(model: onnx.ModelProto) -> None:
    """Give every unnamed node a unique name (exclusion lists refer to nodes by name)."""
    for i, node in enumerate(model.graph.node):
        if not node.name:
            node.name = f"{node.op_type}_{i}"


def quantize_int8(fp32_path: str | os.PathLike, out_path: str | os.PathLike,
                  calibration_images: Sequence[np.ndarray], *, per_channel: bool = True,
                  method: str = "minmax") -> Path:
    """Quantize an fp32 lunarnav ONNX file to int8 (static, QDQ), atomically.

    Args:
        fp32_path: file written by :func:`lunarnav_ml.export.onnx_export.export_onnx`.
        out_path: destination ``.onnx``.
        calibration_images: HxWx3 uint8 RGB images (synthetic renders), letterboxed to the
            model's input size; a few dozen are enough.
        per_channel: per-output-channel weight scales.
        method: activation range calibration: "minmax", "percentile" or "entropy".

    Returns:
        ``out_path``; its metadata says ``precision: int8`` and how it was calibrated.
    """
    if method not in CALIBRATION_METHODS:
        raise ConfigError(f"method: expected one of {sorted(CALIBRATION_METHODS)}, got {method!r}")
    if len(calibration_images) == 0:
        raise InputError("calibration_images: expected at least one image, got none")
    model = _load_onnx(fp32_path)
    meta = read_metadata(model, str(fp32_path))
    if meta.precision != "fp32":
        raise InputError(f"{fp32_path}: expected an fp32 export, got precision {meta.precision}")
    space_to_depth_input_convs(model)  # a stride-2 stem (small-relu-s2) runs int8 this way
    _name_nodes(model)
    with tempfile.TemporaryDirectory(prefix="lunarnav_quant_") as tmp:
        src, dst = Path(tmp) / "fp32.onnx", Path(tmp) / "int8.onnx"
        onnx.save(model, src)
        quantize_static(
            src, dst, ImageCalibrationReader(calibration_images, meta),
            quant_format=QuantFormat.QDQ, activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8, per_channel=per_channel,
            nodes_to_exclude=(fp32_tail_nodes(model.graph) + mish_nodes(model.graph)
                              + input_conv_nodes(model.graph)),
            calibrate_method=CALIBRATION_METHODS[method],
            extra_options={"WeightSymmetric": True, "ActivationSymmetric": False})
        qmodel = onnx.load(dst)
    _set_int8_metadata(qmodel, meta, len(calibration_images), method, per_channel)
    onnx.checker.check_model(qmodel)
    return write_bytes(out_path, qmodel.SerializeToString())


def _set_int8_metadata(model: onnx.ModelProto, meta: md.ModelMetadata, n_images: int,
                       method: str, per_channel: bool) -> None:
    extra = {**meta.extra, "calibration": {"images": n_images, "method": method,
                                           "per_channel": per_channel, "format": "QDQ U8S8"}}
    fields = {**meta.__dict__, "precision": "int8", "extra": extra}
    set_metadata(model, md.ModelMetadata(**fields))


def _load_onnx(path: str | os.PathLike) -> onnx.ModelProto:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: ONNX file not found")
    try:
        return onnx.load(path)
    except DecodeError as err:
        raise InputError(f"{path}: not a readable ONNX file (truncated or corrupt): "
                         f"{type(err).__name__}") from None


def list_images(source: str | os.PathLike) -> list[Path]:
    """Image files of a dataset: ``annotations.json`` (its images' ``file_name``), a folder
    holding one, or any folder of image files (searched recursively, sorted)."""
    source = Path(source)
    ann = source / "annotations.json" if source.is_dir() else source
    if ann.is_file() and ann.suffix == ".json":
        try:
            records = json.loads(ann.read_text())["images"]
        except (json.JSONDecodeError, KeyError, TypeError) as err:
            raise InputError(f"{ann}: not a COCO file with an 'images' list ({err})") from None
        return [ann.parent / r["file_name"] for r in records]
    if not source.is_dir():
        raise InputError(f"{source}: expected a dataset folder, annotations.json or image folder")
    return sorted(p for p in source.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES)


def load_calibration_images(source: str | os.PathLike, n: int = 32) -> list[np.ndarray]:
    """Up to ``n`` images spread evenly over a dataset, as HxWx3 uint8 RGB."""
    paths = list_images(source)
    if not paths:
        raise InputError(f"{source}: no images found (expected .png/.jpg files)")
    picks = np.unique(np.linspace(0, len(paths) - 1, min(n, len(paths))).round().astype(int))
    return [read_rgb(paths[i]) for i in picks]

"""What a lunarnav ONNX file says about itself: the metadata written by the exporter.

Every exported file carries ``metadata_props`` under the ``lunarnav.`` prefix, each value a JSON
string, so a C/C++ consumer can read them with any JSON parser. The runtime refuses a file that
lacks them (a foreign ONNX file) or whose format version it does not read (an incompatible
exporter). This module imports only the standard library.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from lunarnav_ml.errors import InputError

PREFIX = "lunarnav."
# Bumped when the graph's inputs/outputs or the meaning of a metadata key change.
FORMAT_VERSION = 1
SUPPORTED_FORMAT_VERSIONS = (1,)

INPUT_NAME = "images"  # float32 (B, 3, H, W), RGB, normalized as the metadata says
DECODED_NAME = "decoded"  # float32 (B, N, 5 + C): cx, cy, w, h px, objectness, class probs
NMS_OUTPUTS = ("det_indices", "det_boxes", "det_scores")  # (K, 3) int64, (K, 4), (K,)
CONF_NAME, IOU_NAME, MAX_PER_CLASS_NAME = "conf_thres", "iou_thres", "max_per_class"


@dataclass(frozen=True)
class ModelMetadata:
    """Everything the runtime needs besides the graph.

    Attributes:
        class_names: category names; label ``k`` (1-based, COCO ids) is ``class_names[k - 1]``.
        input_size: (H, W) px the model was trained at (the default letterbox size).
        strides: pixels per cell of each head scale.
        anchors: per scale, per anchor, (w, h) px.
        scale_xy: grid-sensitivity factor per scale (decoding is in the graph; kept for
            consumers that decode raw maps themselves).
        mean, std: per-channel RGB normalization: ``x = (pixel / 255 - mean) / std``.
        pad_value: letterbox border gray level (0..255).
        dynamic_batch, dynamic_hw: whether the batch and the height/width axes are free.
        nms_in_graph: True when the file ends in ONNX NonMaxSuppression.
        model: model name (size preset).
        project_version: lunarnav_ml version that exported the file.
        format_version: layout version of inputs, outputs and metadata.
        opset: ONNX opset of the default domain.
        precision: "fp32" or "int8".
    """

    class_names: tuple[str, ...]
    input_size: tuple[int, int]
    strides: tuple[int, ...]
    anchors: tuple[tuple[tuple[float, float], ...], ...]
    scale_xy: tuple[float, ...]
    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)
    std: tuple[float, float, float] = (1.0, 1.0, 1.0)
    pad_value: int = 114
    dynamic_batch: bool = True
    dynamic_hw: bool = True
    nms_in_graph: bool = False
    model: str = "unknown"
    project_version: str = "unknown"
    format_version: int = FORMAT_VERSION
    opset: int = 17
    precision: str = "fp32"
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def num_classes(self) -> int:
        return len(self.class_names)

    @property
    def max_stride(self) -> int:
        return max(self.strides)

    def to_props(self) -> dict[str, str]:
        """Metadata as ``{"lunarnav.<key>": json}`` for ``ModelProto.metadata_props``."""
        values = {
            "format_version": self.format_version, "project_version": self.project_version,
            "model": self.model, "class_names": list(self.class_names),
            "input_size": list(self.input_size), "strides": list(self.strides),
            "anchors": [[list(a) for a in level] for level in self.anchors],
            "scale_xy": list(self.scale_xy), "mean": list(self.mean), "std": list(self.std),
            "pad_value": self.pad_value, "dynamic_batch": self.dynamic_batch,
            "dynamic_hw": self.dynamic_hw, "nms_in_graph": self.nms_in_graph,
            "opset": self.opset, "precision": self.precision, "extra": self.extra,
        }
        return {PREFIX + k: json.dumps(v) for k, v in values.items()}

    @classmethod
    def from_props(cls, props: Mapping[str, str], source: str) -> ModelMetadata:
        """Parse and check the metadata of the file ``source``.

        Raises:
            InputError: the file is not a lunarnav export, was written with a format version
                this runtime does not read, or a field is missing, malformed or impossible
                (an input size that is not a positive multiple of the largest stride, a std
                that is not positive, a NaN mean, no class names).
        """
        values = _decode_props(props, source)
        _check_format_version(values, source)
        try:
            meta = cls(
                class_names=tuple(str(n) for n in values["class_names"]),
                input_size=_int_pair(values["input_size"]),
                strides=tuple(int(s) for s in values["strides"]),
                anchors=tuple(tuple((float(w), float(h)) for w, h in lv)
                              for lv in values["anchors"]),
                scale_xy=tuple(float(s) for s in values["scale_xy"]),
                mean=_triple(values["mean"]), std=_triple(values["std"]),
                pad_value=int(values["pad_value"]),
                dynamic_batch=bool(values["dynamic_batch"]),
                dynamic_hw=bool(values["dynamic_hw"]),
                nms_in_graph=bool(values["nms_in_graph"]), model=str(values["model"]),
                project_version=str(values["project_version"]),
                format_version=int(values["format_version"]), opset=int(values["opset"]),
                precision=str(values["precision"]), extra=dict(values.get("extra", {})),
            )
        except KeyError as err:
            raise InputError(f"{source}: metadata key {PREFIX}{err.args[0]} is missing") from None
        except (TypeError, ValueError) as err:
            raise InputError(f"{source}: malformed lunarnav metadata ({err})") from None
        _check_values(meta, values, source)
        return meta


def _decode_props(props: Mapping[str, str], source: str) -> dict[str, Any]:
    values = {}
    for key, text in props.items():
        if not key.startswith(PREFIX):
            continue
        try:
            values[key[len(PREFIX):]] = json.loads(text)
        except json.JSONDecodeError:
            raise InputError(f"{source}: metadata {key} is not JSON: {text[:60]!r}") from None
    if "format_version" not in values:
        raise InputError(
            f"{source}: not a lunarnav export (no {PREFIX}format_version metadata); expected an "
            f"ONNX file written by `lunarnav export`")
    return values


def _check_format_version(values: Mapping[str, Any], source: str) -> None:
    version = values["format_version"]
    if version not in SUPPORTED_FORMAT_VERSIONS:
        raise InputError(
            f"{source}: exported with format version {version} by lunarnav_ml "
            f"{values.get('project_version', '?')}; this runtime reads format version(s) "
            f"{', '.join(map(str, SUPPORTED_FORMAT_VERSIONS))}: re-export the checkpoint")


def _check_values(meta: ModelMetadata, values: Mapping[str, Any], source: str) -> None:
    """Refuse values no exporter writes, naming the key: they would fail later as a NumPy or
    onnxruntime error (a negative size) or silently (a zero std makes every input NaN)."""
    def bad(key: str, expected: str) -> InputError:
        return InputError(f"{source}: metadata {PREFIX}{key} must be {expected}, "
                          f"got {values[key]!r}")

    if not meta.class_names:
        raise bad("class_names", "a non-empty list of class names")
    if not meta.strides or not all(_is_int(s) and s > 0 for s in values["strides"]):
        raise bad("strides", "a non-empty list of positive integers")
    if not all(_is_int(s) for s in values["input_size"]) or \
            any(s <= 0 or s % meta.max_stride for s in meta.input_size):
        raise bad("input_size", f"[H, W], positive multiples of the largest stride "
                                f"{meta.max_stride}")
    if len(meta.anchors) != len(meta.strides) or not all(
            lv and all(math.isfinite(v) and v > 0 for a in lv for v in a) for lv in meta.anchors):
        raise bad("anchors", f"{len(meta.strides)} levels (one per stride) of positive finite "
                             f"(w, h) pairs")
    if len(meta.scale_xy) != len(meta.strides) or not all(math.isfinite(v)
                                                           for v in meta.scale_xy):
        raise bad("scale_xy", f"{len(meta.strides)} finite numbers (one per stride)")
    if not all(math.isfinite(v) for v in meta.mean):
        raise bad("mean", "3 finite numbers")
    if not all(math.isfinite(v) and v > 0 for v in meta.std):
        raise bad("std", "3 finite numbers > 0")
    if not 0 <= meta.pad_value <= 255:
        raise bad("pad_value", "a gray level in 0..255")


def _is_int(value: Any) -> bool:
    if isinstance(value, bool):
        return False
    return isinstance(value, int) or (isinstance(value, float) and value.is_integer())


def _int_pair(value: Any) -> tuple[int, int]:
    h, w = value
    return int(h), int(w)


def _triple(value: Any) -> tuple[float, float, float]:
    a, b, c = value
    return float(a), float(b), float(c)

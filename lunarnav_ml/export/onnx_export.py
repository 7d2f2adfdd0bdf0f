"""Export a trained detector to ONNX: decoding in the graph, NMS optional, metadata inside.

The graph takes ``images`` (B, 3, H, W) float32 RGB in [0, 1] and returns ``decoded``
(B, N, 5 + C) rows ``(cx, cy, w, h, objectness, class probs...)`` in network pixels; with
``nms=True`` it also ends in ONNX NonMaxSuppression (:mod:`lunarnav_ml.export.graph_nms`).
The file's ``metadata_props`` (:mod:`lunarnav_ml.runtime.metadata`) say everything the runtime
needs: class names, input size, normalization, strides, anchors, model and project version.
"""

from __future__ import annotations

import copy
import io
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import onnx
import torch
from torch import nn

from lunarnav_ml import __version__
from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.export.graph_nms import append_nms
from lunarnav_ml.export.graph_passes import inline_shared_initializers, integer_ranges
from lunarnav_ml.export.onnx_meta import set_metadata
from lunarnav_ml.models.decode import decode
from lunarnav_ml.runtime import metadata as md
from lunarnav_ml.utils.atomic import write_bytes

DEFAULT_OPSET = 17
# Opsets the TorchScript exporter and onnxruntime 1.18+ both handle for this graph.
SUPPORTED_OPSETS = range(13, 21)


@dataclass
class DetectorParts:
    """What the exporter needs from a ``Detector`` (``lunarnav_ml.training.api``).

    Attributes:
        model: ``nn.Module`` returning raw head maps, one per stride.
        anchors: (L, A, 2) anchor (w, h) px per scale.
        strides: pixels per cell per scale.
        scale_xy: grid-sensitivity factor per scale.
        img_size: (H, W) training input size, px.
        class_names: category names (label k is ``class_names[k - 1]``).
        name: model name (size preset) written to the metadata.
    """

    model: nn.Module
    anchors: torch.Tensor
    strides: tuple[int, ...]
    scale_xy: tuple[float, ...]
    img_size: tuple[int, int]
    class_names: tuple[str, ...]
    name: str = "unknown"


class ExportMish(nn.Module):
    """Mish written as ``x n / (n + 2)`` with ``n = e^x (e^x + 2)``.

    The same function as ``x tanh(softplus(x))`` (``tanh(log(1 + e^x))`` simplifies to
    ``n / (n + 2)``), exported as Exp/Mul/Div, which onnxruntime vectorizes; its Softplus
    kernel is scalar and took 58% of the nano preset's time at 1024 px. The input is clamped
    at 20 before the exponential (where the factor is 1 to float precision) to avoid overflow.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        e = torch.exp(torch.clamp(x, max=20.0))
        n = e * (e + 2.0)
        return x * (n / (n + 2.0))


def replace_mish(module: nn.Module) -> int:
    """Swap every ``nn.Mish`` inside ``module`` for :class:`ExportMish`, in place.

    Returns:
        The number of modules replaced.
    """
    count = 0
    for name, child in module.named_children():
        if isinstance(child, nn.Mish):
            setattr(module, name, ExportMish())
            count += 1
        else:
            count += replace_mish(child)
    return count


class DecodedDetector(nn.Module):
    """The exported graph: the detector followed by box decoding.

    Shape:
        - Input: :math:`(B, 3, H, W)` float32 RGB in [0, 1], H and W multiples of the
          largest stride.
        - Output: :math:`(B, N, 5 + C)` decoded rows, network pixels.
    """

    def __init__(self, parts: DetectorParts) -> None:
        super().__init__()
        self.model = parts.model
        self.register_buffer("anchors", parts.anchors.detach().float().clone())
        self.strides = list(parts.strides)
        self.scale_xy = list(parts.scale_xy)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return decode(self.model(images), self.anchors, self.strides, self.scale_xy)


def _pair(value: Any, field_name: str) -> tuple[int, int]:
    size = (value, value) if isinstance(value, int) else tuple(int(v) for v in value)
    if len(size) != 2:
        raise ConfigError(f"{field_name}: expected an int or (H, W), got {value!r}")
    return size  # type: ignore[return-value]


def _scale_xy(detector: Any, levels: int) -> tuple[float, ...]:
    """The detector's per-scale grid-sensitivity factors (attribute on it or its model)."""
    for owner in (detector, getattr(detector, "model", None)):
        value = getattr(owner, "scale_xy", None)
        if value is not None:
            values = [float(value)] * levels if isinstance(value, (int, float)) else value
            return tuple(float(v) for v in values)
    raise InputError(f"{type(detector).__name__}: has no scale_xy (on itself or its .model); "
                     f"expected the decode factor per scale")


def detector_parts(detector: Any) -> DetectorParts:
    """Read the exported pieces off a ``Detector`` (attributes of the training API)."""
    if isinstance(detector, DetectorParts):
        return detector
    missing = [a for a in ("model", "anchors", "strides", "img_size", "class_names")
               if not hasattr(detector, a)]
    if missing:
        raise InputError(f"{type(detector).__name__}: expected a Detector with attribute(s) "
                         f"{', '.join(missing)}")
    anchors = torch.as_tensor(detector.anchors, dtype=torch.float32)
    strides = tuple(int(s) for s in detector.strides)
    if anchors.ndim != 3 or anchors.shape[0] != len(strides) or anchors.shape[2] != 2:
        raise InputError(f"detector.anchors: expected shape ({len(strides)}, A, 2), got "
                         f"{tuple(anchors.shape)}")
    name = getattr(detector, "preset", None) or getattr(detector.model, "preset", "unknown")
    return DetectorParts(detector.model, anchors, strides, _scale_xy(detector, len(strides)),
                         _pair(detector.img_size, "detector.img_size"),
                         tuple(str(c) for c in detector.class_names), str(name))


def load_parts(detector_or_checkpoint_path: Any) -> DetectorParts:
    """Parts from a ``Detector`` object or the path of a training checkpoint."""
    if isinstance(detector_or_checkpoint_path, (str, os.PathLike)):
        path = Path(detector_or_checkpoint_path)
        if not path.is_file():
            raise InputError(f"{path}: checkpoint not found")
        from lunarnav_ml.training.api import load_detector

        return detector_parts(load_detector(path))
    return detector_parts(detector_or_checkpoint_path)


def build_metadata(parts: DetectorParts, size: tuple[int, int], *, opset: int, nms: bool,
                   dynamic: bool) -> md.ModelMetadata:
    """The metadata written into the file."""
    return md.ModelMetadata(
        class_names=parts.class_names, input_size=size, strides=parts.strides,
        anchors=tuple(tuple((float(w), float(h)) for w, h in lv) for lv in parts.anchors.tolist()),
        scale_xy=parts.scale_xy, mean=(0.0, 0.0, 0.0), std=(1.0, 1.0, 1.0),
        dynamic_batch=dynamic, dynamic_hw=dynamic, nms_in_graph=nms, model=parts.name,
        project_version=__version__, opset=opset, precision="fp32",
    )


def trace_to_onnx(module: nn.Module, size: tuple[int, int], opset: int, dynamic: bool
                  ) -> onnx.ModelProto:
    """Trace ``module`` (input ``images``, output ``decoded``) to an ONNX model in memory."""
    axes = {md.INPUT_NAME: {0: "batch", 2: "height", 3: "width"},
            md.DECODED_NAME: {0: "batch", 1: "candidates"}} if dynamic else None
    return trace_module(module, torch.zeros(1, 3, *size), md.INPUT_NAME, md.DECODED_NAME,
                        axes, opset)


def trace_module(module: nn.Module, dummy: torch.Tensor, input_name: str,
                 output_name: str | Sequence[str], axes: dict[str, dict[int, str]] | None,
                 opset: int) -> onnx.ModelProto:
    """Trace a one-input ``module`` (one output, or a tuple named by ``output_name`` in order)
    on ``dummy`` to an ONNX model in memory (TorchScript exporter, constants folded; ``axes``:
    the dynamic axes by name)."""
    names = [output_name] if isinstance(output_name, str) else list(output_name)
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation/tracer notes
        torch.onnx.export(module, (dummy,), buf, opset_version=opset, dynamo=False,
                          input_names=[input_name], output_names=names,
                          dynamic_axes=axes, do_constant_folding=True)
    return onnx.load_from_string(buf.getvalue())


def _fix_decoded_width(model: onnx.ModelProto, width: int) -> None:
    """Write the known row width 5 + C into the ``decoded`` output's shape (tracing leaves it
    symbolic when the height and width are dynamic)."""
    out = next(o for o in model.graph.output if o.name == md.DECODED_NAME)
    dim = out.type.tensor_type.shape.dim[2]
    dim.Clear()
    dim.dim_value = width


def export_onnx(detector_or_checkpoint_path: Any, out_path: str | os.PathLike, *,
                opset: int = DEFAULT_OPSET, nms: bool = False, dynamic: bool = True,
                img_size: int | Sequence[int] | None = None) -> Path:
    """Export a detector (object or checkpoint path) to ONNX, atomically.

    Args:
        detector_or_checkpoint_path: a ``Detector`` or the path of a training checkpoint.
        out_path: destination ``.onnx`` file.
        opset: ONNX opset (pinned; default 17).
        nms: append ONNX NonMaxSuppression (thresholds become graph inputs).
        dynamic: free batch, height and width axes; False fixes (1, 3, H, W).
        img_size: input size recorded as the default (and traced with); default the
            detector's training size. Multiples of the largest stride.

    Returns:
        ``out_path``. The file passes ``onnx.checker`` (full check) before it is written.
    """
    if opset not in SUPPORTED_OPSETS:
        raise ConfigError(f"opset: expected {SUPPORTED_OPSETS.start}..{SUPPORTED_OPSETS.stop - 1},"
                          f" got {opset}")
    parts = load_parts(detector_or_checkpoint_path)
    size = parts.img_size if img_size is None else _pair(img_size, "img_size")
    if any(s <= 0 or s % max(parts.strides) for s in size):
        raise ConfigError(f"img_size: expected positive multiples of {max(parts.strides)}, "
                          f"got {size}")
    module = DecodedDetector(_cpu_eval_copy(parts))
    replace_mish(module)
    proto = trace_to_onnx(module, size, opset, dynamic)
    inline_shared_initializers(proto)
    integer_ranges(proto)
    _fix_decoded_width(proto, 5 + len(parts.class_names))
    if nms:
        proto = append_nms(proto, len(parts.class_names))
    set_metadata(proto, build_metadata(parts, size, opset=opset, nms=nms, dynamic=dynamic))
    onnx.checker.check_model(proto, full_check=True)
    return write_bytes(out_path, proto.SerializeToString())


def _cpu_eval_copy(parts: DetectorParts) -> DetectorParts:
    """A float32 CPU copy of the parts in eval mode (the caller's model is left untouched)."""
    clone = copy.deepcopy(parts.model).float().cpu().eval()
    return DetectorParts(clone, parts.anchors, parts.strides, parts.scale_xy, parts.img_size,
                         parts.class_names, parts.name)

"""Model size presets (depth and width multipliers, as in YOLOX) and ``build_model``.

Widths and depths scale the full YOLOv4 (CSPDarknet53: widths 32..1024, residual blocks
1, 2, 8, 8, 4; five-conv PAN stacks). Parameter counts (``count_parameters``):

| preset | depth | width | params, 3 classes | params, 80 classes | reference |
|---|---|---|---|---|---|
| nano   | 0.33 | 0.25 | 2.75 M | 2.85 M | |
| small  | 0.33 | 0.375 | 6.17 M | 6.33 M | |
| small-relu | 0.33 | 0.375 | 6.17 M | 6.33 M | small with ReLU for int8 |
| small-relu-s2 | 0.33 | 0.375 | 6.17 M | 6.33 M | small-relu, a stride-2 stem for int8 |
| medium | 0.67 | 0.75 | 28.48 M | 28.79 M | |
| yolov4 | 1.0  | 1.0  | 63.93 M | 64.34 M | darknet YOLOv4: 64.36 M |
| tiny   | two heads | 1.0 | 5.88 M | 6.06 M | darknet YOLOv4-tiny: 6.06 M |

The full model differs from darknet's by 0.03 %: its first CSP stage splits into halves like
the others, where darknet's keeps the full width in both branches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from lunarnav_ml.errors import ConfigError
from lunarnav_ml.models.darknet import CSPDarknet, TinyDarknet
from lunarnav_ml.models.pan import TinyFPN, YOLOv4PAN
from lunarnav_ml.models.yolo import YOLO
from lunarnav_ml.models.yolo_head import YOLOHead

# YOLOv4's COCO anchors (w, h) for a 608 px input, per stride 8 / 16 / 32.
YOLOV4_ANCHORS = (((12, 16), (19, 36), (40, 28)),
                  ((36, 75), (76, 55), (72, 146)),
                  ((142, 110), (192, 243), (459, 401)))
# YOLOv4-tiny's anchors for a 416 px input, per stride 16 / 32.
YOLOV4_TINY_ANCHORS = (((10, 14), (23, 27), (37, 58)),
                       ((81, 82), (135, 169), (344, 319)))
FULL_WIDTHS = (32, 64, 128, 256, 512, 1024)  # stem + five stages of CSPDarknet53
FULL_BLOCKS = (1, 2, 8, 8, 4)  # residual units per stage


@dataclass(frozen=True)
class Preset:
    """One model size."""

    depth: float  # multiplier of residual-block counts and neck conv pairs
    width: float  # multiplier of channel widths (rounded to multiples of 8)
    tiny: bool = False  # two-scale YOLOv4-tiny design instead of CSPDarknet53 + SPP + PAN
    backbone_act: str = "mish"  # YOLOv4's backbone activation
    neck_act: str = "leaky"  # YOLOv4's neck and head activation
    # grid sensitivity per scale (YOLOv4: 1.2 / 1.1 / 1.05); >= 2 lets the loss also train the
    # two neighbour cells nearest each box centre (YOLOv5's assignment, faster convergence)
    scale_xy: tuple[float, float, float] = (1.2, 1.1, 1.05)
    stem: str = "full"  # CSPDarknet's stem: "full" (YOLOv4's) or "s2" (see darknet.CSPDarknet)


PRESETS: dict[str, Preset] = {
    # nano is the CPU-first preset for minutes-long trainings: leaky ReLU throughout (Mish costs
    # ~1.6x the training step time on 2 CPU cores and has no int8 kernel in onnxruntime) and
    # three positive cells per box.
    "nano": Preset(depth=0.33, width=0.25, backbone_act="leaky", scale_xy=(2.0, 2.0, 2.0)),
    # small is the default CPU preset: the hour-long training budget and the shipped checkpoint
    # (12.3 MB in fp16, under 20 MB) set its width; leaky and three positives per box as nano.
    "small": Preset(depth=0.33, width=0.375, backbone_act="leaky", scale_xy=(2.0, 2.0, 2.0)),
    # small-relu is small with ReLU throughout, the onboard preset: onnxruntime folds a ReLU
    # into the integer convolution before it, where a leaky ReLU stays a separate quantized
    # operator, so its int8 model runs 2.6x faster than fp32 against 2.4x on a Zen 4 core (2.0-2.1x
    # on a Xeon with AMX, whose fp32 is faster; BENCHMARKS.md).
    "small-relu": Preset(depth=0.33, width=0.375, backbone_act="relu", neck_act="relu",
                         scale_xy=(2.0, 2.0, 2.0)),
    # small-relu-s2 is small-relu with a stride-2 stem in place of the full-resolution stem
    # and stage 0, whose thin layers onnxruntime's integer convolutions run no faster than
    # fp32: its int8 model runs 2.5-2.8x faster than fp32 on a Xeon with AMX (small-relu
    # 1.8-2.0x; BENCHMARKS.md). No weights are shipped for it yet (lunarnav distill-stem).
    "small-relu-s2": Preset(depth=0.33, width=0.375, backbone_act="relu", neck_act="relu",
                            scale_xy=(2.0, 2.0, 2.0), stem="s2"),
    "medium": Preset(depth=0.67, width=0.75),
    "yolov4": Preset(depth=1.0, width=1.0),
    "tiny": Preset(depth=1.0, width=1.0, tiny=True),
}


def _width(c: int, mult: float) -> int:
    return max(8, int(math.ceil(c * mult / 8) * 8))


def _depth(n: int, mult: float) -> int:
    return max(1, round(n * mult))


def get_preset(preset: str) -> Preset:
    """The :class:`Preset` of a name.

    Raises:
        ConfigError: not one of ``PRESETS``.
    """
    if not isinstance(preset, str) or preset not in PRESETS:
        raise ConfigError(f"preset: unknown model preset {preset!r} "
                          f"(known: {', '.join(PRESETS)})")
    return PRESETS[preset]


def default_anchors(preset: str) -> torch.Tensor:
    """The reference anchors of a preset, :math:`(L, 3, 2)` pixels."""
    return torch.tensor(YOLOV4_TINY_ANCHORS if get_preset(preset).tiny else YOLOV4_ANCHORS,
                        dtype=torch.float32)


def build_model(preset: str = "nano", num_classes: int = 3, anchors=None) -> YOLO:
    """Build a detector of a named size.

    Args:
        preset: one of ``PRESETS`` (``nano``, ``small``, ``small-relu``, ``medium``, ``yolov4``,
            ``tiny``).
        num_classes: number of classes K.
        anchors: :math:`(L, A, 2)` anchor (w, h) in input pixels (nested lists or tensor);
            default: the YOLOv4 (or YOLOv4-tiny) reference anchors.

    Returns:
        A :class:`YOLO` module.

    Raises:
        ConfigError: an unknown preset or ``num_classes`` < 1.
    """
    cfg = get_preset(preset)
    if isinstance(num_classes, bool) or not isinstance(num_classes, int) or num_classes < 1:
        raise ConfigError(f"num_classes: must be an integer >= 1, got {num_classes!r}")
    anchors = default_anchors(preset) if anchors is None else torch.as_tensor(
        anchors, dtype=torch.float32)
    if cfg.tiny:
        return _build_tiny(cfg, num_classes, anchors)
    widths = tuple(_width(c, cfg.width) for c in FULL_WIDTHS)
    blocks = tuple(_depth(n, cfg.depth) for n in FULL_BLOCKS)
    backbone = CSPDarknet(widths, blocks, act=cfg.backbone_act, stem=cfg.stem)
    neck = YOLOv4PAN(backbone.out_channels, pairs=_depth(2, cfg.depth), act=cfg.neck_act)
    strides = backbone.strides
    head = YOLOHead(neck.out_channels, anchors.shape[1], num_classes, strides, act=cfg.neck_act)
    return YOLO(backbone, neck, head, anchors, strides, cfg.scale_xy, num_classes)


def _build_tiny(cfg: Preset, num_classes: int, anchors: torch.Tensor) -> YOLO:
    width = _width(32, cfg.width)
    backbone = TinyDarknet(width, act="leaky")
    neck = TinyFPN(backbone.out_channels, act="leaky")
    strides = backbone.strides
    hidden = (8 * width, 16 * width)
    head = YOLOHead(neck.out_channels, anchors.shape[1], num_classes, strides, hidden, "leaky")
    return YOLO(backbone, neck, head, anchors, strides, (1.05, 1.05), num_classes)


def count_parameters(model: torch.nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)

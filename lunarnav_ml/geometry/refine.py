"""A learned refinement of SGBM's disparity around crater rims, run by onnxruntime (torch-free).

SGBM smears a depth edge over its block and interpolates subpixel disparities with a bias; at the
occluding near rim of a small, far crater both move the crest's disparity by a tenth of a pixel or
more, which is a range error of decimetres (docs/geometry.md). A small fully-convolutional net
trained on rendered pairs (:mod:`lunarnav_ml.training.refiner`) reads the left image, the right
image warped to the left by SGBM's disparity, their difference and SGBM's disparity, and returns a
per-pixel correction. Invalid pixels stay invalid: the lifter's rules for invalid runs (sky,
black shadow behind a crest) see the same mask.

Features (:func:`refiner_features`, shared with the training code): channels
``left - 0.5``, ``warped_right - 0.5`` (both scaled to [0, 1]), ``4 (left - warped_right)``,
``disparity / 32`` (0 where invalid) and the valid mask.

The ONNX file carries ``lunarnav.kind = disparity_refiner`` and ``lunarnav.receptive_px`` (the
radius in pixels beyond which an input pixel cannot change an output): refining only the
regions around crater boxes, each padded by that radius, gives the same values there as
refining the whole band. It may carry ``lunarnav.edge_offsets``, a JSON object of
:class:`~lunarnav_ml.geometry.lifter.LifterConfig` edge-offset terms calibrated on lifts from the
refined disparity (``benchmarks/calibrate_rim_offset.py``): the visible edge's offset in front
of the crest is partly the matcher's, so a refined map needs its own. Two more keys go with
those offsets, as they change the lifts they were fitted on: ``lunarnav.max_disparity_px``
(refine only the boxes whose SGBM disparity over the box's lower half has a median below it:
near craters, with 2-3x the far ones' disparity, are left to SGBM) and ``lunarnav.passes``
(refine the refined map again, the right image warped anew).
"""

from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from lunarnav_ml.errors import InputError
from lunarnav_ml.geometry.lifter import EDGE_OFFSET_TERMS, LifterConfig

FEATURES_NAME = "features"
DELTA_NAME = "delta"
KIND = "disparity_refiner"
N_FEATURES = 5
DISPARITY_SCALE = 32.0
DEFAULT_REFINER = Path(__file__).resolve().parents[1] / "weights" / "disparity_refiner.onnx"


def warp_right(right: np.ndarray, disparity: np.ndarray) -> np.ndarray:
    """The right image resampled at each left pixel's match, ``right(u - d, v)`` (bilinear; 0
    disparity where invalid), so that it lines up with the left image where ``d`` is right.

    Shape:
        right: (H, W) uint8; disparity: (H, W) px, NaN invalid. Returns (H, W) uint8.
    """
    h, w = right.shape
    d = np.where(np.isfinite(disparity), disparity, 0.0).astype(np.float32)
    map_x = np.arange(w, dtype=np.float32)[None, :] - d
    map_y = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w))
    return cv2.remap(right, map_x, np.ascontiguousarray(map_y), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


def refiner_features(left: np.ndarray, warped: np.ndarray, disparity: np.ndarray) -> np.ndarray:
    """The refiner's input channels for a batch of crops.

    Shape:
        left, warped: (B, H, W) uint8; disparity: (B, H, W) px, NaN invalid.
        Returns (B, 5, H, W) float32.
    """
    lf = np.asarray(left, dtype=np.float32) / 255.0
    rf = np.asarray(warped, dtype=np.float32) / 255.0
    valid = np.isfinite(disparity)
    d = np.where(valid, disparity, 0.0).astype(np.float32)
    return np.stack([lf - 0.5, rf - 0.5, 4.0 * (lf - rf), d / DISPARITY_SCALE,
                     valid.astype(np.float32)], axis=1)


def refine_regions(boxes_xywh: np.ndarray, shape: tuple[int, int]) -> list[tuple[int, ...]]:
    """Rows and columns [r0, r1) x [c0, c1) refined around each crater box: the box with the
    rows above it that an ellipse fit and a crest search reach (a quarter of its height + 16)
    and the flank rows below its near rim the lifter reads (28), 8 columns either side.

    Shape:
        boxes_xywh: (K, 4) px.
    """
    h, w = shape
    out = []
    for x, y, bw, bh in np.asarray(boxes_xywh, dtype=np.float64).reshape(-1, 4):
        r0, r1 = max(int(y - 0.25 * bh - 16), 0), min(int(y + bh + 28), h)
        c0, c1 = max(int(x - 8), 0), min(int(x + bw + 9), w)
        if r1 > r0 and c1 > c0:
            out.append((r0, r1, c0, c1))
    return out


def _edge_offsets(text: str | None, path: Path) -> dict[str, float]:
    """The ``lunarnav.edge_offsets`` terms of a refiner file ({} without them)."""
    if text is None:
        return {}
    try:
        terms = json.loads(text)
    except json.JSONDecodeError:
        terms = None
    names = {k for keys in EDGE_OFFSET_TERMS.values() for k in keys}
    if not isinstance(terms, dict) or not all(
            k in names and isinstance(v, int | float) and not isinstance(v, bool)
            and np.isfinite(v) for k, v in terms.items()):
        raise InputError(f"{path}: metadata lunarnav.edge_offsets: expected a JSON object of "
                         f"finite numbers named among {sorted(names)}, got {text[:80]!r}")
    return {k: float(v) for k, v in terms.items()}


def _gate_setting(text: str | None, path: Path) -> float | None:
    """The ``lunarnav.max_disparity_px`` of a refiner file (None: absent or "none")."""
    if text is None or text == "none":
        return None
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (np.isfinite(value) and value > 0):
        raise InputError(f"{path}: metadata lunarnav.max_disparity_px: expected a positive "
                         f"number or 'none', got {text[:80]!r}")
    return value


def gate_metadata(max_disparity_px: float | None) -> dict[str, str]:
    """The ``lunarnav.max_disparity_px`` entry a refiner file carries for this gate (read back
    by :class:`DisparityRefiner`)."""
    text = "none" if max_disparity_px is None else repr(float(max_disparity_px))
    return {"lunarnav.max_disparity_px": text}


def _passes_setting(text: str | None, path: Path) -> int:
    """The ``lunarnav.passes`` of a refiner file (1 when absent)."""
    if text is None:
        return 1
    if not text.isdigit() or int(text) < 1:
        raise InputError(f"{path}: metadata lunarnav.passes: expected a positive integer, "
                         f"got {text[:80]!r}")
    return int(text)


def check_settings(max_disparity_px: float | None, passes: int) -> None:
    """Raise :class:`InputError` for a gate that is not a positive number (or None) or a pass
    count that is not a positive integer."""
    if max_disparity_px is not None and not (
            isinstance(max_disparity_px, int | float) and not isinstance(max_disparity_px, bool)
            and np.isfinite(max_disparity_px) and max_disparity_px > 0):
        raise InputError(f"max_disparity_px: expected a positive number or None, got "
                         f"{max_disparity_px!r}")
    if not isinstance(passes, int) or isinstance(passes, bool) or passes < 1:
        raise InputError(f"passes: expected a positive integer, got {passes!r}")


def gated_boxes(disparity: np.ndarray, boxes_xywh: np.ndarray,
                max_disparity_px: float | None) -> np.ndarray:
    """Which boxes a refiner with this gate refines: those whose valid disparity over the box's
    lower half (the near rim and the floor) has a median below ``max_disparity_px``, and those
    with no valid pixel there (the gate cannot tell); all of them without a gate.

    Shape:
        disparity: (H, W) px, NaN invalid; boxes_xywh: (K, 4) px. Returns (K,) bool.
    """
    boxes = np.asarray(boxes_xywh, dtype=np.float64).reshape(-1, 4)
    if max_disparity_px is None:
        return np.ones(len(boxes), bool)
    h, w = disparity.shape
    keep = np.ones(len(boxes), bool)
    for k, (x, y, bw, bh) in enumerate(boxes):
        r0, r1 = max(int(y + 0.5 * bh), 0), min(int(y + bh) + 1, h)
        c0, c1 = max(int(x), 0), min(int(x + bw) + 1, w)
        patch = disparity[r0:r1, c0:c1]
        patch = patch[np.isfinite(patch)]
        if patch.size:
            keep[k] = float(np.median(patch)) < max_disparity_px
    return keep


def default_lifter(refiner: DisparityRefiner | None) -> LifterConfig:
    """The lifter settings to use with ``refiner``'s disparity: :class:`LifterConfig` with the
    refiner's edge offsets (the defaults without a refiner)."""
    return refiner.lifter_config() if refiner is not None else LifterConfig()


class DisparityRefiner:
    """Refine SGBM's disparity with an exported refiner (``lunarnav train-refiner``).

    Args:
        path: the ONNX file (default: the shipped ``lunarnav_ml/weights/disparity_refiner.onnx``).
        threads: onnxruntime intra-op threads.
        max_disparity_px: refine only the boxes :func:`gated_boxes` passes (None: every box);
            default: the file's ``lunarnav.max_disparity_px`` (none when absent).
        passes: times the map is refined, the right image warped anew by the last map each
            time; default: the file's ``lunarnav.passes`` (1 when absent).
        Set either one apart from the file only to calibrate new edge offsets for it
        (``benchmarks/calibrate_rim_offset.py``): the file's offsets were fitted with its own.

    Raises:
        InputError: missing, corrupt or foreign file (no ``lunarnav.kind = disparity_refiner``),
            inputs / outputs other than the ones the trainer exports, or bad settings.
    """

    def __init__(self, path: str | os.PathLike | None = None, threads: int = 1, *,
                 max_disparity_px: float | None | str = "file",
                 passes: int | None = None) -> None:
        from lunarnav_ml.runtime.session import load_tool_session

        self.path = Path(path) if path is not None else DEFAULT_REFINER
        self.session, props = load_tool_session(self.path, threads, KIND, "disparity refiner",
                                                "`lunarnav train-refiner`")
        try:
            self.receptive_px = int(props["lunarnav.receptive_px"])
        except (KeyError, ValueError):
            raise InputError(f"{self.path}: metadata lunarnav.receptive_px missing or not an "
                             "integer") from None
        self.edge_offsets = _edge_offsets(props.get("lunarnav.edge_offsets"), self.path)
        file_gate = _gate_setting(props.get("lunarnav.max_disparity_px"), self.path)
        file_passes = _passes_setting(props.get("lunarnav.passes"), self.path)
        self.max_disparity_px = file_gate if max_disparity_px == "file" else max_disparity_px
        self.passes = file_passes if passes is None else passes
        check_settings(self.max_disparity_px, self.passes)
        ins = {i.name: i.shape for i in self.session.get_inputs()}
        outs = {o.name for o in self.session.get_outputs()}
        if FEATURES_NAME not in ins or len(ins[FEATURES_NAME]) != 4 or DELTA_NAME not in outs:
            raise InputError(f"{self.path}: expected input '{FEATURES_NAME}' (B, {N_FEATURES}, "
                             f"H, W) and output '{DELTA_NAME}', got inputs {ins}, outputs "
                             f"{sorted(outs)}")

    def lifter_config(self, base: LifterConfig | None = None) -> LifterConfig:
        """``base`` (default :class:`LifterConfig`) with the edge offsets calibrated for this
        refiner's disparity, where the file carries them."""
        return replace(base if base is not None else LifterConfig(), **self.edge_offsets)

    def correction(self, left: np.ndarray, warped: np.ndarray, disparity: np.ndarray
                   ) -> np.ndarray:
        """The net's per-pixel correction, px, for one (H, W) crop (NaN where ``disparity`` is)."""
        feats = refiner_features(left[None], warped[None], disparity[None])
        delta = self.session.run([DELTA_NAME], {FEATURES_NAME: feats})[0][0]
        return np.where(np.isfinite(disparity), delta, np.nan).astype(np.float32)

    def refine(self, left: np.ndarray, right: np.ndarray, disparity: np.ndarray,
               boxes_xywh: np.ndarray | None = None) -> np.ndarray:
        """SGBM's disparity with the net's correction added, invalid pixels left invalid.

        Args:
            left, right: the rectified pair, (H, W) uint8 gray.
            disparity: left-reference disparity, px; NaN invalid (SGBM's band: rows outside it
                are NaN and stay NaN).
            boxes_xywh: crater boxes, px: as :meth:`refine_boxes`. None: every row that holds
                a valid pixel.

        Raises:
            InputError: images that are not (H, W) uint8 of the disparity's shape.

        Shape:
            disparity: (H, W); boxes_xywh: (K, 4). Returns (H, W) float32.
        """
        if boxes_xywh is not None:
            return self.refine_boxes(left, right, disparity, boxes_xywh)[0]
        return self._refine(left, right, self._checked(left, right, disparity), None)

    def refine_boxes(self, left: np.ndarray, right: np.ndarray, disparity: np.ndarray,
                     boxes_xywh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`refine` around crater boxes: only their regions (:func:`refine_regions`) are
        refined, the rest of the map is returned as it was, and with a gate only the regions
        of the boxes :func:`gated_boxes` passes on SGBM's ``disparity``.

        Returns:
            The refined (H, W) float32 map and (K,) bool: which boxes were refined.
        """
        disp = self._checked(left, right, disparity)
        boxes = np.asarray(boxes_xywh, dtype=np.float64).reshape(-1, 4)
        refined = gated_boxes(disp, boxes, self.max_disparity_px)
        return self._refine(left, right, disp, refine_regions(boxes[refined], disp.shape)), refined

    @staticmethod
    def _checked(left: np.ndarray, right: np.ndarray, disparity: np.ndarray) -> np.ndarray:
        """``disparity`` as float32, once ``left`` and ``right`` are uint8 gray of its shape."""
        disp = np.asarray(disparity, dtype=np.float32)
        for name, img in (("left", left), ("right", right)):
            if img.ndim != 2 or img.dtype != np.uint8 or img.shape != disp.shape:
                raise InputError(f"{name}: expected a uint8 gray image of shape {disp.shape}, "
                                 f"got {img.dtype} {img.shape}")
        return disp

    def _refine(self, left: np.ndarray, right: np.ndarray, disp: np.ndarray,
                regions: list[tuple[int, ...]] | None) -> np.ndarray:
        """``disp`` refined in ``regions`` (None: its whole band), ``passes`` times, each region
        read with the receptive radius around it."""
        out = disp.copy()
        rows = np.flatnonzero(np.isfinite(disp).any(axis=1))
        if not len(rows) or regions == []:  # nothing to refine (the gate passed no box)
            return out
        a, b = int(rows[0]), int(rows[-1]) + 1
        if regions is None:
            regions = [(a, b, 0, disp.shape[1])]
        m, w = self.receptive_px, disp.shape[1]
        for _ in range(self.passes):
            src = out.copy()
            warped = warp_right(right, src)
            for r0, r1, c0, c1 in regions:
                r0, r1 = max(r0, a), min(r1, b)
                if r1 <= r0:
                    continue
                pr0, pr1 = max(r0 - m, a), min(r1 + m, b)
                pc0, pc1 = max(c0 - m, 0), min(c1 + m, w)
                delta = self.correction(left[pr0:pr1, pc0:pc1], warped[pr0:pr1, pc0:pc1],
                                        src[pr0:pr1, pc0:pc1])
                inner = (slice(r0 - pr0, r1 - pr0), slice(c0 - pc0, c1 - pc0))
                out[r0:r1, c0:c1] = src[r0:r1, c0:c1] + delta[inner]
        return out

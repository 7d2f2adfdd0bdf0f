"""A second, larger read of a frame's small boxes, merged into the detector's own read.

A detector trained at 384 px reads a 1024 px frame shrunk 2.7 times: on the paper's monocular
grid a key crater 15-20 m ahead is about 17 px high in the frame and 6 px at the 384 px read,
where the network finds it poorly. :class:`SmallBoxReadPredictor` reads the frame a second time
at a larger side and keeps from that read only the boxes that are small at the model's own
side (under ``below_px`` high in its input, 15 px by default); they join the first read's boxes
and per-class NMS takes out the repeats. Big boxes come from the first read only, where the
detector sees them as it was trained.

On the paper-mono grid (1024 px frames, `small.pt` at 384 with a 640 px second read, through
the box refiner) crater AP50 rose 0.477 -> 0.650 on the test quarter (validation 0.463 ->
0.639), key-crater Pd stayed 0.827 -> 0.824, and end to end on the paper-stereo evaluation half
the 5 m craters at 15-20 m were placed within 3σ 1.45 m, sized within 1.91 m (one read: 1.75 /
2.30 m). On the 384 px default renders and the 432 px real frames it lowered both figures, so
it is a read for large frames of the renders' kind, off by default; it costs about 3.4 times
the first read (BENCHMARKS.md, issue 4, "A second, larger read of the small boxes"). The cut
of 15 px was chosen against 9 px and no cut on the validation quarter, by key-crater Pd.
With it, ``--box-rescorer`` takes the shipped trees fitted on this read's boxes (test quarter:
AP50 0.677, key-crater Pd 0.849, Pd 0.77-0.86 at every sun zenith).

``band`` reads only a band of rows, through a rectangular input. On the paper's camera the rows
0.15-0.6 with the rescorer found what the whole frame finds on the validation quarter (0.674 /
0.901) and read the test quarter at AP50 0.676, key-crater Pd 0.858, every sun zenith at 0.75 or
more (the whole test grid, four quarters: 0.677 / 0.855, every bin 0.755 or more; two quarters
alone each have one bin under 0.75), for 0.66 of the whole second read's time; the narrower
0.27-0.56 misses craters near the horizon (validation AP50 0.629 against 0.639 without the
rescorer). ``small_grid.pt``, trained on the paper's grid at both read scales, with the band
and its own rescorer read the whole test grid at 0.703 / 0.879 (BENCHMARKS.md, issue 4, "A
model trained on the paper's grid"). ``horizon`` gives the band as angles over and under the
camera's horizon instead, for any camera pitch: :meth:`SmallBoxReadConfig.at_camera` turns it
into rows once the camera is known (the ``--camera`` record of ``lunarnav localize`` and
``lunarnav detect``; each image's own record in ``lunarnav eval``, through
:attr:`SmallBoxReadPredictor.camera`).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from lunarnav_ml.errors import ConfigError
from lunarnav_ml.eval.tta import max_stride, square_side
from lunarnav_ml.runtime.nms import batched_nms

DEFAULT_BELOW_PX = 15.0


@dataclass(frozen=True)
class SmallBoxReadConfig:
    """The second read.

    Attributes:
        side: the second read's network input side, px (a multiple of the model's largest
            stride, larger than the model's own side).
        below_px: a box of the second read is kept when it is under this many px high at the
            model's own side (its height in the frame x own side / the frame's longer side).
        band: ``(top, bottom)``, fractions of the frame's height: the second read covers these
            rows only, at the scale the whole frame would have had (a rectangular input, so
            it costs about ``bottom - top`` of a whole second read); None: the whole frame.
        horizon: ``(above_deg, below_deg)``: the band as the rows from ``above_deg`` over the
            camera's horizon down to ``below_deg`` under it (not with ``band``; the read needs
            :meth:`at_camera` first). The paper's camera (pitch 20 deg, 90 deg field of view)
            puts rows 0.15-0.6 at 15.0 over and 31.3 under.
    """

    side: int
    below_px: float = DEFAULT_BELOW_PX
    band: tuple[float, float] | None = None
    horizon: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if isinstance(self.side, bool) or not isinstance(self.side, int) or self.side <= 0:
            raise ConfigError(f"--small-read: expected a positive side in px, got {self.side!r}")
        if not (np.isfinite(self.below_px) and self.below_px > 0):
            raise ConfigError(f"--small-read-below: expected a positive height in px, "
                              f"got {self.below_px}")
        if self.band is not None:
            band = tuple(float(v) for v in self.band)
            if len(band) != 2 or not (0.0 <= band[0] < band[1] <= 1.0):  # NaN fails too
                raise ConfigError(f"--small-read-band: expected TOP BOTTOM with 0 <= TOP < "
                                  f"BOTTOM <= 1 (fractions of the frame's height), got "
                                  f"{list(self.band)}")
            object.__setattr__(self, "band", band)
        if self.horizon is not None:
            angles = tuple(float(v) for v in self.horizon)
            if self.band is not None:
                raise ConfigError("--small-read-band and --small-read-horizon: choose one")
            if len(angles) != 2 or not all(-90.0 < v < 90.0 for v in angles) \
                    or not angles[0] + angles[1] > 0:  # NaN fails too
                raise ConfigError(f"--small-read-horizon: expected ABOVE BELOW in degrees over "
                                  f"and under the horizon (each in (-90, 90), ABOVE + BELOW > "
                                  f"0), got {list(self.horizon)}")
            object.__setattr__(self, "horizon", angles)

    def at_camera(self, camera: Mapping[str, float], height: int) -> SmallBoxReadConfig:
        """This read for one camera: ``horizon`` turned into a ``band`` of the rows of a frame
        ``height`` px high, from the camera's ``pitch_deg`` (optical axis below the horizon),
        ``fy`` and ``cy`` (px; roll is left out); itself without ``horizon``.

        Raises:
            ConfigError: the band lies wholly outside the frame for this camera.
        """
        if self.horizon is None:
            return self
        above, below = self.horizon

        def row(elevation_deg: float) -> float:  # the frame row of a ray at this elevation
            tilt = elevation_deg + camera["pitch_deg"]  # over the optical axis, deg
            if abs(tilt) >= 90.0:
                return 0.0 if tilt > 0 else float(height)
            return camera["cy"] - camera["fy"] * math.tan(math.radians(tilt))

        top, bottom = (min(max(row(e) / height, 0.0), 1.0) for e in (above, -below))
        if bottom <= top:
            raise ConfigError(f"--small-read-horizon {above:g} {below:g}: no row of the frame "
                              f"lies in the band for a camera pitched "
                              f"{camera['pitch_deg']:g} deg down (fy {camera['fy']:g}, cy "
                              f"{camera['cy']:g} px)")
        return dataclasses.replace(self, band=(top, bottom), horizon=None)

    def record(self) -> dict[str, float]:
        """What a box rescorer fitted on this read's boxes records of it: the side and the cut
        (a band reads the same boxes where it reads)."""
        return {"side": self.side, "below_px": float(self.below_px)}

    def describe(self) -> str:
        """One line for report titles."""
        rows = "" if self.band is None else f" (rows {self.band[0]:.3g}-{self.band[1]:.3g})"
        if self.horizon is not None:
            rows = f" ({self.horizon[0]:g} deg over to {self.horizon[1]:g} under the horizon)"
        return f"boxes under {self.below_px:g} px high read again at {self.side} px{rows}"


def _up(px: float, stride: int) -> int:
    """``px`` rounded up to a multiple of ``stride`` (at least one)."""
    return max(stride, int(np.ceil(px / stride - 1e-9)) * stride)


class SmallBoxReadPredictor:
    """Wraps a predictor with ``img_size`` and ``set_img_size(side)`` (the torch ``Detector``,
    an onnxruntime ``OnnxDetector`` exported with a dynamic input); ``predict`` has the wrapped
    predictor's signature and output, and other attributes are the wrapped predictor's."""

    def __init__(self, predictor: Any, config: SmallBoxReadConfig,
                 camera: Mapping[str, float] | None = None) -> None:
        self.predictor, self.config = predictor, config
        self.camera = camera  # what a ``horizon`` is read against; set per frame group
        self.base_side = square_side(predictor, "--small-read")
        self.stride = max_stride(predictor)
        if config.side <= self.base_side:
            raise ConfigError(f"--small-read: {config.side} px is not larger than the model's "
                              f"own side, {self.base_side} px")
        try:  # a model that cannot run at the side says so now, not halfway through a set
            predictor.set_img_size(config.side)
        finally:
            predictor.set_img_size(self.base_side)

    def __getattr__(self, name: str) -> Any:  # class_names, strides, ...
        if name in ("predictor", "config"):  # not set yet (copy, unpickling): no recursion
            raise AttributeError(name)
        return getattr(self.predictor, name)

    def describe(self) -> str:
        """One line for report titles."""
        return self.config.describe()

    def predict(self, images: list[np.ndarray], conf_thres: float = 0.001,
                iou_thres: float = 0.6, max_det: int = 300) -> list[dict[str, np.ndarray]]:
        """Per image ``{"boxes" (N, 4) xyxy px, "scores", "labels"}``: the model's own read
        and the larger read's small boxes, per-class NMS at ``iou_thres``, highest score
        first, at most ``max_det``."""
        if not images:
            return []
        bands = [self.band_for(image.shape[0]) for image in images]  # a camera missing: now
        own = self.predictor.predict(images, conf_thres, iou_thres, max_det)
        try:
            if all(band is None for band in bands):
                self.predictor.set_img_size(self.config.side)
                larger = self.predictor.predict(images, conf_thres, iou_thres, max_det)
            else:
                larger = [self.read_band(image, conf_thres, iou_thres, max_det, band)
                          for image, band in zip(images, bands, strict=True)]
        finally:
            self.predictor.set_img_size(self.base_side)
        return [self.merge(a, b, image.shape, iou_thres, max_det)
                for a, b, image in zip(own, larger, images, strict=True)]

    def band_for(self, height: int) -> tuple[float, float] | None:
        """The rows a frame ``height`` px high is read again in: the config's ``band``, or its
        ``horizon`` at :attr:`camera`; None: the whole frame.

        Raises:
            ConfigError: a ``horizon`` and no camera to read it against, or a band outside the
                frame for this camera.
        """
        if self.config.horizon is None:
            return self.config.band
        if self.camera is None:
            raise ConfigError("--small-read-horizon needs the camera's pitch: give the rows as "
                              "--small-read-band TOP BOTTOM, or a camera record (lunarnav "
                              "detect --camera, localize --camera; eval reads each image's)")
        return self.config.at_camera(self.camera, height).band

    def read_band(self, image: np.ndarray, conf_thres: float, iou_thres: float, max_det: int,
                  band: tuple[float, float]) -> dict[str, np.ndarray]:
        """The second read of one frame's ``band`` of rows (:meth:`band_for`'s), at the scale
        ``side`` gives the whole frame, through an input just large enough for the band; boxes
        in frame pixels."""
        h, w = image.shape[:2]
        top, bottom = band
        y0, y1 = int(np.floor(top * h)), max(int(np.ceil(bottom * h)), int(np.floor(top * h)) + 1)
        scale = self.config.side / max(h, w)
        self.predictor.set_img_size((_up((y1 - y0) * scale, self.stride),
                                     _up(w * scale, self.stride)))
        (pred,) = self.predictor.predict([np.ascontiguousarray(image[y0:y1])], conf_thres,
                                         iou_thres, max_det)
        boxes = np.asarray(pred["boxes"], np.float32).reshape(-1, 4).copy()
        boxes[:, [1, 3]] += y0
        return {**pred, "boxes": boxes}

    def merge(self, own: dict[str, np.ndarray], larger: dict[str, np.ndarray],
              shape: tuple[int, ...], iou_thres: float = 0.6, max_det: int = 300
              ) -> dict[str, np.ndarray]:
        """One frame's two reads merged: ``larger``'s boxes under ``below_px`` high at the
        model's own side join ``own``'s; per-class NMS; by score, at most ``max_det``."""
        scale = self.base_side / max(shape[:2])  # the letterbox's, at the model's own side
        lb = np.asarray(larger["boxes"], np.float32).reshape(-1, 4)
        small = (lb[:, 3] - lb[:, 1]) * scale < self.config.below_px
        boxes = np.concatenate([np.asarray(own["boxes"], np.float32).reshape(-1, 4), lb[small]])
        scores = np.concatenate([np.asarray(own["scores"], np.float32).reshape(-1),
                                 np.asarray(larger["scores"], np.float32).reshape(-1)[small]])
        labels = np.concatenate([np.asarray(own["labels"], np.int64).reshape(-1),
                                 np.asarray(larger["labels"], np.int64).reshape(-1)[small]])
        keep = batched_nms(boxes, scores, labels, iou_thres)[:max_det]
        return {"boxes": boxes[keep], "scores": scores[keep], "labels": labels[keep]}


def small_reader(predictor: Any) -> SmallBoxReadPredictor | None:
    """The :class:`SmallBoxReadPredictor` in a chain of wrappers, each holding the next as its
    own attribute ``predictor`` (a ``BoxRefinedDetector`` around it), or None."""
    for _ in range(8):  # wrappers are few; a cycle would be a bug
        if isinstance(predictor, SmallBoxReadPredictor):
            return predictor
        predictor = vars(predictor).get("predictor") if hasattr(predictor, "__dict__") else None
        if predictor is None:
            return None
    return None


def add_small_read_arguments(parser: argparse.ArgumentParser, horizon: bool = False) -> None:
    """``--small-read SIDE``, ``--small-read-below PX`` and ``--small-read-band TOP BOTTOM`` for a
    command that runs a detector; ``horizon``: also ``--small-read-horizon ABOVE BELOW``, for a
    command that knows its camera (a ``--camera`` record, or each image's)."""
    parser.add_argument("--small-read", type=int, default=None, metavar="SIDE",
                        help="read each frame a second time at this network side (px) and add "
                             "the boxes that are small at the model's own side: for frames much "
                             "larger than the model's input, such as the paper's 1024 px "
                             "renders (640 there; slower by the second read; not with --tta)")
    parser.add_argument("--small-read-below", type=float, default=DEFAULT_BELOW_PX, metavar="PX",
                        help="(--small-read) keep the second read's boxes under this many px "
                             "high at the model's own side; default %(default)s")
    parser.add_argument("--small-read-band", type=float, nargs=2, default=None,
                        metavar=("TOP", "BOTTOM"),
                        help="(--small-read) read again only these rows, as fractions of the "
                             "frame's height (the far ground below the horizon, where the small "
                             "craters are): about BOTTOM - TOP of the second read's cost, but "
                             "the network needs some sky and near ground around them (the "
                             "paper's camera: 0.15 0.6 found as much as the whole frame for 0.66 "
                             "of its time, 0.27 0.56 fewer); default the whole frame")
    if horizon:
        parser.add_argument("--small-read-horizon", type=float, nargs=2, default=None,
                            metavar=("ABOVE", "BELOW"),
                            help="(--small-read) read again only the rows from ABOVE degrees "
                                 "over the camera's horizon to BELOW degrees under it, from the "
                                 "camera record's pitch_deg, fy and cy (--camera's; eval: each "
                                 "image's): the band for any pitch (the paper's camera: 15 31.3 "
                                 "are its rows 0.15-0.6); not with --small-read-band")


def small_read_config(args: argparse.Namespace) -> SmallBoxReadConfig | None:
    """The :class:`SmallBoxReadConfig` the arguments ask for, or None without
    ``--small-read``.

    Raises:
        ConfigError: a band of rows given without ``--small-read`` (it would read nothing).
    """
    side = getattr(args, "small_read", None)
    band, horizon = (getattr(args, f"small_read_{k}", None) for k in ("band", "horizon"))
    if side is None:
        if band is not None or horizon is not None:
            option = "--small-read-band" if band is not None else "--small-read-horizon"
            raise ConfigError(f"{option} chooses the rows of the second read: give "
                              f"--small-read SIDE too (640 for 1024 px frames)")
        return None
    return SmallBoxReadConfig(side=side, below_px=args.small_read_below,
                              band=None if band is None else tuple(band),
                              horizon=None if horizon is None else tuple(horizon))

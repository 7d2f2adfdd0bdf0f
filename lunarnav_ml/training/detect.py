"""Detection on image files: COCO results JSON plus overlay images (``lunarnav detect``)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.eval.predict import Predictor, coco_results
from lunarnav_ml.utils import atomic
from lunarnav_ml.utils.images import IMAGE_SUFFIXES, caption_tile, contact_sheet, read_rgb

CLASS_COLORS_BGR = ((0, 200, 255), (255, 160, 0), (60, 60, 255))  # crater, rock, artifact
DETECT_OUTPUTS = ("overlays", "results.json", "images.json", "gallery.png")  # what --out holds


def list_images(sources: Path | str | Sequence[Path | str]) -> list[Path]:
    """Image files named directly or held by folders (each folder's sorted, not recursive), in
    the order given; a file named twice is kept once."""
    if isinstance(sources, (str, Path)):
        sources = [sources]
    files, seen = [], set()
    for source in map(Path, sources):
        if source.is_file():
            found = [source]
        elif source.is_dir():
            found = sorted(p for p in source.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not found:
                raise InputError(f"{source}: the folder holds no images "
                                 f"({', '.join(IMAGE_SUFFIXES)})")
        else:
            raise InputError(f"{source}: no such image or folder")
        for f in found:
            key = f.resolve()
            if key not in seen:
                seen.add(key)
                files.append(f)
    return files


def overlay_names(files: Sequence[Path]) -> list[str]:
    """One overlay file name per input, ``<stem>.jpg``; a stem met again (``a.png`` beside
    ``a.jpg``, or two folders' ``000001.png``) gets ``<stem>-2.jpg``, ``<stem>-3.jpg``, ..."""
    names: list[str] = []
    taken: set[str] = set()  # membership in O(1): a rover log holds thousands of frames
    for f in files:
        stem, k = Path(f).stem, 1
        name = f"{stem}.jpg"
        while name in taken:
            k += 1
            name = f"{stem}-{k}.jpg"
        names.append(name)
        taken.add(name)
    return names


def draw_overlay(image: np.ndarray, pred: dict[str, np.ndarray], class_names: list[str],
                 min_score: float) -> np.ndarray:
    """Boxes with class and score drawn on a copy of an RGB image; returns BGR for writing."""
    out = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    for box, score, label in zip(pred["boxes"], pred["scores"], pred["labels"]):
        if score < min_score:
            continue
        color = CLASS_COLORS_BGR[(int(label) - 1) % len(CLASS_COLORS_BGR)]
        x0, y0, x1, y1 = (round(float(v)) for v in box)
        cv2.rectangle(out, (x0, y0), (x1, y1), color, 1)
        name = class_names[int(label) - 1] if 0 < int(label) <= len(class_names) else str(label)
        cv2.putText(out, f"{name} {score:.2f}", (x0, max(8, y0 - 2)), cv2.FONT_HERSHEY_SIMPLEX,
                    0.35, color, 1, cv2.LINE_AA)
    return out


def gallery_indices(n_files: int, n: int) -> set[int]:
    """``n`` indices spread evenly over ``n_files`` files (all of them when there are fewer)."""
    if n <= 0 or n_files == 0:
        return set()
    return {int(i) for i in np.linspace(0, n_files - 1, min(n, n_files)).round()}


def check_out_dir(out_dir: Path, files: list[Path]) -> None:
    """ConfigError when replacing ``out_dir`` with a new detection output would lose files:
    a plain file, a folder holding the input images, or one holding what detect does not write.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: --out exists and is not a folder")
    resolved = out.resolve()
    for f in files:
        if resolved in Path(f).resolve().parents:
            raise ConfigError(f"{out}: --out holds the input image {f}; choose another folder")
    if out.is_dir():
        foreign = sorted(p.name for p in out.iterdir() if p.name not in DETECT_OUTPUTS)
        if foreign:
            raise ConfigError(f"{out}: --out holds files detect did not write ({foreign[0]}); "
                              "give a new or empty folder, or an earlier detect output")


def detect_files(detector: Predictor, files: list[Path], out_dir: Path, *, conf_thres: float,
                 iou_thres: float, overlay_thres: float, batch: int = 8, progress: bool = True,
                 gallery: int = 12) -> dict[str, Any]:
    """Detect on image files; write ``results.json`` (COCO results), ``images.json`` (ids to
    files and overlays), ``overlays/<stem>.jpg`` (named by ``overlay_names``) and, when
    ``gallery`` > 0, ``gallery.png`` (a contact sheet of up to ``gallery`` overlays spread over
    the files) under ``out_dir``.

    The folder is built under a temporary name and replaces ``out_dir`` (an earlier detect
    output) only when every image was read: a failure leaves ``out_dir`` as it was.

    Args:
        detector: the torch ``Detector``, the onboard runtime's ``OnnxDetector``, or either
            wrapped in test-time augmentation (``predict`` and ``class_names``).

    Returns:
        ``{"images": [...], "results": [...]}`` as written.
    """
    check_out_dir(out_dir, files)
    images_meta, results = [], []
    in_gallery, tiles = gallery_indices(len(files), gallery), []
    names = overlay_names(files)
    bar = tqdm(total=len(files), desc="detect", unit="img", disable=not progress)
    with atomic.atomic_dir(out_dir) as work:
        for start in range(0, len(files), batch):
            chunk = files[start:start + batch]
            rgb = [read_rgb(f) for f in chunk]
            preds = detector.predict(rgb, conf_thres=conf_thres, iou_thres=iou_thres)
            ids = list(range(start + 1, start + 1 + len(chunk)))
            results += coco_results(preds, ids)
            for image_id, path, image, pred in zip(ids, chunk, rgb, preds):
                name = names[image_id - 1]
                images_meta.append({"id": image_id, "file_name": str(path),
                                    "width": image.shape[1], "height": image.shape[0],
                                    "overlay": f"overlays/{name}"})
                overlay = draw_overlay(image, pred, detector.class_names, overlay_thres)
                atomic.write_image(work / "overlays" / name, overlay)
                if image_id - 1 in in_gallery:
                    tiles.append(caption_tile(overlay, 320, path.name[:48]))
            bar.update(len(chunk))
        bar.close()
        if tiles:
            atomic.write_image(work / "gallery.png", contact_sheet(tiles))
        atomic.write_json(work / "results.json", results, indent=None)
        atomic.write_json(work / "images.json", images_meta)
    return {"images": images_meta, "results": results}

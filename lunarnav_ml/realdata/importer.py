"""Import a real labelled set (COCO / Roboflow COCO, or YOLO txt) into our COCO convention.

Output folder::

    <out>/<split>/annotations.json   our COCO (categories 1 crater, 2 rock, 3 artifact);
                                     file_name points at the original image (nothing copied)
    <out>/import_report.json         counts: mapped, dropped, skipped, cameras, leakage
    <out>/import_report.md           the same, short

Splits are the source's split folders (``train``, ``valid``, ``test``...), or the source
folder itself when it holds one split. Copies of one source frame must not be in two splits.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from lunarnav_ml.errors import InputError
from lunarnav_ml.realdata.category_map import load_category_map
from lunarnav_ml.realdata.coco_source import find_annotation_file, read_coco_split
from lunarnav_ml.realdata.convert import SplitLabels
from lunarnav_ml.realdata.import_report import render_markdown, split_summary
from lunarnav_ml.realdata.sources import check_leakage
from lunarnav_ml.realdata.yolo_source import is_yolo_split, read_class_names, read_yolo_split
from lunarnav_ml.utils import atomic

FORMATS = ("coco", "yolo")
SPLIT_ORDER = ("train", "valid", "val", "test")  # later splits are the more held-out ones
REPORT_JSON, REPORT_MD = "import_report.json", "import_report.md"


def import_real(src: str | Path, out: str | Path, *, map_file: str | Path | None = None,
                fmt: str | None = None, splits: Sequence[str] | None = None,
                skip_bad: bool = False) -> dict[str, Any]:
    """Import every split of ``src`` into ``out`` and write the report.

    Args:
        src: dataset folder (split folders inside) or one split folder.
        out: output folder; replaced if it holds an earlier import, refused if it holds
            anything else or overlaps ``src``.
        map_file: category-map YAML (default: the built-in map, the same as
            ``configs/realdata/category_map.yaml``).
        fmt: ``"coco"`` or ``"yolo"``; ``None`` detects it.
        splits: split folder names to import (default: all found).
        skip_bad: skip and count bad items instead of raising ``InputError``.

    Returns:
        The report (also written as ``import_report.json``).
    """
    src, out = Path(src), Path(out)
    if not src.is_dir():
        raise InputError(f"{src}: source folder not found")
    _check_out(src, out)
    cmap = load_category_map(map_file)
    fmt = fmt or detect_format(src)
    if fmt not in FORMATS:
        raise InputError(f"format must be one of {FORMATS}, got {fmt!r}")
    folders = find_splits(src, fmt, splits)
    if fmt == "coco":
        converted = [read_coco_split(find_annotation_file(f), n, cmap, skip_bad)
                     for n, f in folders.items()]
    else:
        names = read_class_names([src, *folders.values()])
        converted = [read_yolo_split(f, n, names, cmap, skip_bad) for n, f in folders.items()]
    leaks = resolve_leakage(converted, skip_bad)
    report = {"source": str(src), "format": fmt, "category_map": cmap.to_dict(),
              "skip_bad": skip_bad, "leakage_found": {k: len(v) for k, v in leaks.items()},
              "splits": {s.name: split_summary(s) for s in converted}}
    with atomic.atomic_dir(out) as work:
        work.chmod(0o755)  # a temporary folder is private; the output need not be
        for split in converted:
            atomic.write_json(work / split.name / "annotations.json",
                              split.to_coco(out / split.name), indent=None)
        atomic.write_json(work / REPORT_JSON, report)
        atomic.write_text(work / REPORT_MD, render_markdown(report))
    return report


def detect_format(src: Path) -> str:
    """``"coco"`` when a COCO file is in ``src`` or a subfolder, ``"yolo"`` for label folders."""
    folders = [src, *sorted(p for p in src.iterdir() if p.is_dir())]
    if any(find_annotation_file(f) for f in folders):
        return "coco"
    if any(is_yolo_split(f) for f in folders):
        return "yolo"
    raise InputError(f"{src}: found neither a COCO file (_annotations.coco.json, "
                     "annotations.json) nor YOLO labels; give --format")


def find_splits(src: Path, fmt: str, wanted: Sequence[str] | None = None) -> dict[str, Path]:
    """Split name -> folder, train first and the held-out splits last.

    The split folders are ``src``'s subfolders that hold labels, or ``src`` itself when none do.

    Raises:
        InputError: no split found, or a wanted split missing.
    """
    is_split = (lambda f: find_annotation_file(f) is not None) if fmt == "coco" else is_yolo_split
    found = {p.name: p for p in src.iterdir() if p.is_dir() and is_split(p)}
    if not found and is_split(src):
        found = {src.name: src}
    if not found:
        raise InputError(f"{src}: no {fmt} split folders found")
    if wanted:
        missing = [w for w in wanted if w not in found]
        if missing:
            raise InputError(f"{src}: no split {', '.join(missing)} (found: {', '.join(found)})")
        found = {w: found[w] for w in wanted}
    return dict(sorted(found.items(), key=lambda kv: _split_rank(kv[0])))


def _split_rank(name: str) -> tuple[float, str]:
    """Sort key: train, valid, val, other names, test."""
    return (SPLIT_ORDER.index(name) if name in SPLIT_ORDER else len(SPLIT_ORDER) - 1.5, name)


def resolve_leakage(splits: list[SplitLabels], skip_bad: bool) -> dict[str, list[str]]:
    """Find source frames shared between splits.

    Without ``skip_bad`` a leak raises ``InputError``; with it, the shared frames' images are
    removed from the less held-out split of each pair (train before valid before test) and
    counted as ``leaked_source_image``.

    Returns:
        The leaks found (``check_leakage``'s answer), before any removal.
    """
    leaks = check_leakage({s.name: [img["source_name"] for img in s.images] for s in splits})
    by_name = {s.name: s for s in splits}
    for pair, shared in leaks.items():
        a, b = pair.split("/")
        loser = by_name[min(a, b, key=_split_rank)]
        if not skip_bad:
            raise InputError(f"splits {a} and {b} share {len(shared)} source frame(s), e.g. "
                             f"{', '.join(shared[:3])}: re-split by source frame, or pass "
                             f"--skip-bad to drop them from {loser.name}")
        drop = {img["id"] for img in loser.images if img["source_name"] in set(shared)}
        loser.drop_images(drop, "leaked_source_image")
    return leaks


def _check_out(src: Path, out: Path) -> None:
    s, o = src.resolve(), out.resolve()
    if o == s or s in o.parents or o in s.parents:
        raise InputError(f"{out}: the output folder must not overlap the source folder {src}")
    if o.exists() and not o.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    if o.is_dir() and any(o.iterdir()) and not (o / REPORT_JSON).is_file():
        raise InputError(f"{out}: not empty and not an earlier import-real output "
                         f"(no {REPORT_JSON}); choose a new folder")

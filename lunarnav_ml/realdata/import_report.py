"""The import report: what was mapped, dropped and skipped, per split and camera."""

from __future__ import annotations

from collections import Counter, defaultdict
from typing import Any

from lunarnav_ml.data.coco import CLASS_NAMES
from lunarnav_ml.realdata.convert import SplitLabels


def split_summary(split: SplitLabels) -> dict[str, Any]:
    """Counts of one converted split (after any leakage removal)."""
    anns = split.annotations
    copies = Counter(img["source_name"] for img in split.images)
    return {
        "images_in": split.images_in,
        "images_out": len(split.images),
        "annotations_in": split.annotations_in,
        "annotations_out": len(anns),
        "per_class": {name: sum(a["category_id"] == k for a in anns)
                      for k, name in enumerate(CLASS_NAMES, start=1)},
        "ignored": sum(bool(a["ignore"]) for a in anns),
        "mapped": dict(sorted(Counter(f"{a['source_category']} -> "
                                      f"{CLASS_NAMES[a['category_id'] - 1]}" for a in anns).items())),
        "dropped": dict(sorted(split.dropped.items())),
        "skipped": dict(sorted(split.skipped.items())),
        "source_frames": len(copies),
        "max_copies_per_source": max(copies.values(), default=0),
        "cameras": _cameras(split),
        "skipped_examples": list(split.examples),
    }


def _cameras(split: SplitLabels) -> dict[str, dict[str, int]]:
    images: Counter = Counter()
    sources: dict[str, set[str]] = defaultdict(set)
    boxes: Counter = Counter()
    camera_of = {}
    for img in split.images:
        images[img["camera_name"]] += 1
        sources[img["camera_name"]].add(img["source_name"])
        camera_of[img["id"]] = img["camera_name"]
    for ann in split.annotations:
        boxes[camera_of[ann["image_id"]]] += 1
    return {cam: {"images": images[cam], "source_frames": len(sources[cam]),
                  "annotations": boxes[cam]} for cam in sorted(images)}


def render_markdown(report: dict[str, Any]) -> str:
    """A short markdown version of the import report."""
    cmap_file = report["category_map"]["file"] or "built-in"
    intro = (f"Format {report['format']}; category map {cmap_file}; skip_bad "
             f"{report['skip_bad']}. Images are referenced in place, not copied.")
    head = ("| split | images in | images out | source frames | boxes in | boxes out | crater | "
            "rock | artifact | ignored | dropped | skipped |")
    lines = [f"# Import report: {report['source']}", "", intro, "", head, "|---" * 12 + "|"]
    for name, s in report["splits"].items():
        c = s["per_class"]
        lines.append(f"| {name} | {s['images_in']} | {s['images_out']} | {s['source_frames']} | "
                     f"{s['annotations_in']} | {s['annotations_out']} | {c['crater']} | "
                     f"{c['rock']} | {c['artifact']} | {s['ignored']} | "
                     f"{sum(s['dropped'].values())} | {sum(s['skipped'].values())} |")
    for name, s in report["splits"].items():
        lines += ["", f"## {name}", "",
                  f"- mapped: {_pairs(s['mapped'])}",
                  f"- dropped by the map: {_pairs(s['dropped'])}",
                  f"- skipped (bad input): {_pairs(s['skipped'])}",
                  "- cameras (images / source frames / boxes): " + ", ".join(
                      f"{cam} {v['images']}/{v['source_frames']}/{v['annotations']}"
                      for cam, v in s["cameras"].items())]
        lines += [f"  - {m}" for m in s["skipped_examples"]]
    leaks = report["leakage_found"]
    lines += ["", "## Source-frame leakage between splits", "",
              "none" if not leaks else "; ".join(f"{pair}: {n} shared source frame(s)"
                                                  for pair, n in leaks.items())]
    return "\n".join(lines) + "\n"


def _pairs(counts: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in counts.items()) or "none"

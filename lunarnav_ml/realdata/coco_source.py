"""Read a COCO split (Roboflow ``<split>/_annotations.coco.json`` included) into our convention.

Roboflow exports carry instance-segmentation polygons (kept as ``segmentation``), a category 0
supercategory that no box uses, image ids from 0 (renumbered from 1 here), and the original
frame name in ``images[*].extra.name`` (kept as ``source_name``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lunarnav_ml.data.coco import read_json
from lunarnav_ml.errors import InputError
from lunarnav_ml.realdata.category_map import CategoryMap
from lunarnav_ml.realdata.convert import SplitLabels, image_size
from lunarnav_ml.realdata.sources import source_name

ANNOTATION_FILES = ("_annotations.coco.json", "annotations.json")  # Roboflow's, then ours


def find_annotation_file(folder: Path) -> Path | None:
    """The COCO file of a split folder, or ``None``."""
    for name in ANNOTATION_FILES:
        if (Path(folder) / name).is_file():
            return Path(folder) / name
    return None


def read_coco_split(ann_file: Path, name: str, cmap: CategoryMap, skip_bad: bool = False
                    ) -> SplitLabels:
    """Convert one COCO file; image ``file_name`` entries are relative to its folder.

    Raises:
        InputError: (without ``skip_bad``) an image file missing or unreadable or not the size
            the file says, an annotation naming an unknown image or category, a bad box.
    """
    ann_file = Path(ann_file)
    data = read_json(ann_file)
    split = SplitLabels(name, cmap, skip_bad)
    categories = _categories(ann_file, data["categories"])
    by_id: dict[Any, dict[str, Any] | None] = {}
    for k, img in enumerate(data["images"]):
        split.images_in += 1
        key = img.get("id") if isinstance(img, dict) else None
        if not _hashable(key):
            split.problem("bad_image_entry", f"{ann_file}: images[{k}]: 'id' must be a number "
                          f"or a string, got {key!r}")
            continue
        if key in by_id:
            split.problem("duplicate_image_id", f"{ann_file}: images[{k}] repeats image id {key}")
            continue
        by_id[key] = _image(split, ann_file, k, img)
    for k, ann in enumerate(data["annotations"]):
        split.annotations_in += 1
        _annotation(split, ann_file, k, ann, by_id, categories)
    return split


def _categories(ann_file: Path, categories: list) -> dict[Any, str]:
    table = {}
    for k, cat in enumerate(categories):
        if not isinstance(cat, dict) or "id" not in cat or "name" not in cat:
            raise InputError(f"{ann_file}: categories[{k}] needs 'id' and 'name', got {cat!r}")
        key = cat["id"]
        if isinstance(key, bool) or not isinstance(key, (int, str)):
            raise InputError(f"{ann_file}: categories[{k}] ({cat['name']!r}): 'id' must be an "
                             f"integer, got {key!r}")
        if table.get(key, str(cat["name"])) != str(cat["name"]):
            raise InputError(f"{ann_file}: categories[{k}] ({cat['name']!r}) reuses the id "
                             f"{key!r} of {table[key]!r}")
        table[key] = str(cat["name"])
    return table


def _hashable(value: Any) -> bool:
    """Whether ``value`` can be an id (a JSON list or object cannot)."""
    return not isinstance(value, (list, dict))


def _image(split: SplitLabels, ann_file: Path, k: int, img: Any) -> dict[str, Any] | None:
    """Check one image entry against its file; ``None`` when it is skipped."""
    if not isinstance(img, dict) or "file_name" not in img:
        split.problem("bad_image_entry", f"{ann_file}: images[{k}] needs 'id' and 'file_name'")
        return None
    where = f"{ann_file}: images[{k}] (id {img.get('id')}, {img['file_name']})"
    path = ann_file.parent / str(img["file_name"])
    if not path.is_file():
        split.problem("missing_image", f"{where}: image file {path} not found")
        return None
    size = image_size(path)
    if size is None:
        split.problem("unreadable_image", f"{where}: {path} is not a readable image")
        return None
    if (img.get("width"), img.get("height")) != size:
        split.problem("size_mismatch", f"{where}: the file is {size[0]}x{size[1]} px but the "
                      f"labels say {img.get('width')}x{img.get('height')}")
        return None
    return split.add_image(path, *size, source=source_name(img), source_file=img["file_name"])


def _annotation(split: SplitLabels, ann_file: Path, k: int, ann: Any,
                by_id: dict[Any, dict[str, Any] | None], categories: dict[Any, str]) -> None:
    if not isinstance(ann, dict):
        split.problem("bad_annotation", f"{ann_file}: annotations[{k}] is not an object")
        return
    where = f"{ann_file}: annotations[{k}] (id {ann.get('id')})"
    image_id = ann.get("image_id")
    if not _hashable(image_id) or image_id not in by_id:
        split.problem("unknown_image_id", f"{where}: unknown image_id {image_id!r}")
        return
    image = by_id[image_id]
    if image is None:  # its image was skipped (and counted) already
        split.skipped["annotation_of_skipped_image"] += 1
        return
    if not _hashable(ann.get("category_id")) or ann.get("category_id") not in categories:
        split.problem("unknown_category", f"{where}: unknown category_id "
                      f"{ann.get('category_id')!r} (categories: {sorted(categories)})")
        return
    polygons = ann.get("segmentation")
    split.add_box(image, categories[ann["category_id"]], ann.get("bbox"), where,
                  iscrowd=bool(ann.get("iscrowd", 0)) or bool(ann.get("ignore", False)),
                  segmentation=polygons if isinstance(polygons, list) else None)

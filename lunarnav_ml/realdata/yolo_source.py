"""Read a YOLO-txt split into our convention.

Layout: ``<split>/images/*.jpg`` with ``<split>/labels/<stem>.txt`` (or both in one folder);
class names from ``data.yaml`` (``names`` list or ``{index: name}``), ``classes.txt`` or
``obj.names`` in the dataset or split folder. A label line is ``class cx cy w h`` or a polygon
``class x1 y1 x2 y2 ...`` (YOLO segmentation), normalised to [0, 1]. An image without a
label file has no objects.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from lunarnav_ml.errors import InputError, one_line
from lunarnav_ml.realdata.category_map import CategoryMap
from lunarnav_ml.realdata.convert import SplitLabels, image_size
from lunarnav_ml.realdata.sources import original_name
from lunarnav_ml.utils.images import IMAGE_SUFFIXES

NAME_FILES = ("data.yaml", "data.yml", "classes.txt", "obj.names")


def is_yolo_split(folder: Path) -> bool:
    """A folder with a ``labels/`` subfolder, or with ``.txt`` labels beside its images."""
    folder = Path(folder)
    if (folder / "labels").is_dir():
        return True
    if not folder.is_dir():
        return False
    suffixes = {p.suffix.lower() for p in folder.iterdir() if p.name not in NAME_FILES}
    return ".txt" in suffixes and bool(suffixes & set(IMAGE_SUFFIXES))


def read_class_names(folders: list[Path]) -> dict[int, str]:
    """Class index -> name from the first ``data.yaml`` / ``classes.txt`` / ``obj.names`` found.

    Raises:
        InputError: none found, or the file holds no names.
    """
    for folder in folders:
        for name in NAME_FILES:
            path = Path(folder) / name
            if path.is_file():
                return _names_from(path)
    raise InputError(f"{folders[0]}: no class names for the YOLO labels (looked for "
                     f"{', '.join(NAME_FILES)})")


def _names_from(path: Path) -> dict[int, str]:
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a class names file (not UTF-8 text)") from None
    if path.suffix in (".yaml", ".yml"):
        try:
            names = (yaml.safe_load(text) or {}).get("names")
        except (yaml.YAMLError, AttributeError) as err:
            raise InputError(f"{path}: not a YAML mapping with a 'names' entry "
                             f"({one_line(err)})") from None
        if isinstance(names, list):
            return {i: str(n) for i, n in enumerate(names)}
        if isinstance(names, dict) and all(isinstance(i, int) for i in names):
            return {i: str(n) for i, n in names.items()}
        raise InputError(f"{path}: 'names' must be a list or an {{index: name}} mapping")
    names = [line.strip() for line in text.splitlines() if line.strip()]
    if not names:
        raise InputError(f"{path}: no class names in the file")
    return dict(enumerate(names))


def read_yolo_split(folder: Path, name: str, class_names: dict[int, str], cmap: CategoryMap,
                    skip_bad: bool = False) -> SplitLabels:
    """Convert one YOLO-txt split folder.

    Raises:
        InputError: (without ``skip_bad``) a label file without its image, an unreadable image,
            a malformed line, a class index without a name, a box outside its image.
    """
    folder = Path(folder)
    images_dir = folder / "images" if (folder / "images").is_dir() else folder
    labels_dir = folder / "labels" if (folder / "labels").is_dir() else folder
    images = {p.stem: p for p in sorted(images_dir.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES}
    labels = {p.stem: p for p in sorted(labels_dir.glob("*.txt")) if p.name not in NAME_FILES}
    split = SplitLabels(name, cmap, skip_bad)
    for stem in sorted(set(labels) - set(images)):
        split.annotations_in += _count_lines(labels[stem])
        split.problem("missing_image", f"{labels[stem]}: labels an image {stem}.* that is not "
                      f"in {images_dir}")
    for stem, path in images.items():
        split.images_in += 1
        size = image_size(path)
        if size is None:
            split.problem("unreadable_image", f"{path}: not a readable image")
            continue
        text = _label_text(split, labels[stem]) if stem in labels else ""
        if text is None:  # skipped (and counted) with its unreadable label file
            continue
        image = split.add_image(path, *size, source=original_name(path.name),
                                source_file=path.name)
        if stem in labels:
            _read_labels(split, labels[stem], text, image, class_names)
    return split


def _count_lines(path: Path) -> int:
    """Non-blank lines, counted on the bytes (a file that is not text still has lines)."""
    return sum(1 for line in path.read_bytes().splitlines() if line.strip())


def _label_text(split: SplitLabels, path: Path) -> str | None:
    """A label file's text; ``None`` (counted) when it is not UTF-8 text."""
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        split.annotations_in += _count_lines(path)
        split.problem("unreadable_labels", f"{path}: not a YOLO label file (not UTF-8 text: "
                      f"byte {err.object[err.start]:#04x} at offset {err.start})")
        return None


def _read_labels(split: SplitLabels, path: Path, text: str, image: dict[str, Any],
                 class_names: dict[int, str]) -> None:
    for n, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        split.annotations_in += 1
        where = f"{path}:{n}"
        parsed = _parse_line(line)
        if parsed is None:
            split.problem("bad_line", f"{where}: expected 'class cx cy w h' or 'class x1 y1 x2 "
                          f"y2 ...' (normalised), got {line.strip()!r}")
            continue
        cls, values = parsed
        if cls not in class_names:
            split.problem("unknown_category", f"{where}: class {cls} has no name "
                          f"(names: {class_names})")
            continue
        bbox, polygon = _to_pixels(values, image["width"], image["height"])
        split.add_box(image, class_names[cls], bbox, where, segmentation=polygon)


def _parse_line(line: str) -> tuple[int, list[float]] | None:
    parts = line.split()
    try:
        cls, values = int(parts[0]), [float(v) for v in parts[1:]]
    except (ValueError, IndexError):
        return None
    if len(values) == 4 or (len(values) >= 6 and len(values) % 2 == 0):
        return cls, values
    return None


def _to_pixels(values: list[float], width: int, height: int
               ) -> tuple[list[float], list[list[float]] | None]:
    """Normalised box or polygon -> ([x, y, w, h] px, polygon px or ``None``)."""
    if len(values) == 4:
        cx, cy, w, h = values
        return [(cx - w / 2) * width, (cy - h / 2) * height, w * width, h * height], None
    xs = [v * width for v in values[0::2]]
    ys = [v * height for v in values[1::2]]
    polygon = [round(c, 3) for xy in zip(xs, ys) for c in xy]
    return [min(xs), min(ys), max(xs) - min(xs), max(ys) - min(ys)], [polygon]

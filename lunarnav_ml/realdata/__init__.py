"""Real labelled sets: importers (COCO / Roboflow, YOLO txt) into our COCO convention,
source-frame de-duplication and camera assignment, and the transfer evaluation."""

from lunarnav_ml.realdata.category_map import CategoryMap, load_category_map
from lunarnav_ml.realdata.importer import import_real
from lunarnav_ml.realdata.sources import (
    CAMERA_PREFIXES,
    camera_for,
    check_leakage,
    group_by_source,
    original_name,
    source_name,
    split_by_source,
)

__all__ = [
    "CAMERA_PREFIXES", "CategoryMap", "camera_for", "check_leakage", "group_by_source",
    "import_real", "load_category_map", "original_name", "source_name", "split_by_source",
]

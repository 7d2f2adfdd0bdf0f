"""Small COCO label fixtures shared by the tests of the evaluation scripts."""

CATEGORIES = [{"id": 1, "name": "crater"}, {"id": 2, "name": "rock"}, {"id": 3, "name": "artifact"}]


def ann(ann_id: int, image_id: int, bbox: list[float], category: int = 1, **kw) -> dict:
    """One COCO annotation (``bbox`` x, y, w, h px); ``kw`` adds fields such as ``ignore``."""
    return {"id": ann_id, "image_id": image_id, "category_id": category, "bbox": bbox,
            "area": bbox[2] * bbox[3], "iscrowd": 0, **kw}

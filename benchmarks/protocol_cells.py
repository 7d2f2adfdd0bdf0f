"""Write the frames of chosen cells of a protocol grid (target diameter x near-rim range) as
another annotations file, to weigh those cells up in training.

Each protocol frame records its grid item (``protocol_item``: the target's diameter and near-rim
range, the sun). Session 82 weighed up the cells the whole paper-mono test grid still missed
most (D 15-20 m at 13-19 m) in a training mix:

    .venv/bin/python benchmarks/protocol_cells.py \\
        data/protocol8/mono_train1024/annotations.json --diameters 15 17 20 \\
        --ranges 11 21 --out data/protocol8/mono_train1024/big_near.json

The file names the same image files, so it sits beside the set it came from.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lunarnav_ml.errors import InputError, LunarNavError
from lunarnav_ml.utils.atomic import write_json
from lunarnav_ml.utils.jsonfile import read_json_file


def select_cells(coco: dict, diameters: list[float], ranges: tuple[float, float],
                 source: str = "annotations") -> dict:
    """The COCO set holding only the frames whose target diameter is one of ``diameters`` (m)
    and whose near-rim range lies in ``ranges`` (m, both ends kept)."""
    keep = set()
    for im in coco["images"]:
        item = im.get("protocol_item")
        if not isinstance(item, dict) or "diameter_m" not in item or "near_rim_range_m" not in item:
            raise InputError(f"{source}: image {im.get('id')} has no protocol_item with "
                             "diameter_m and near_rim_range_m (not a protocol render)")
        d, r = float(item["diameter_m"]), float(item["near_rim_range_m"])
        if any(abs(d - x) < 1e-6 for x in diameters) and ranges[0] <= r <= ranges[1]:
            keep.add(im["id"])
    return {**coco, "images": [im for im in coco["images"] if im["id"] in keep],
            "annotations": [a for a in coco["annotations"] if a["image_id"] in keep]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("annotations", type=Path, help="a protocol set's COCO annotations")
    p.add_argument("--diameters", type=float, nargs="+", required=True,
                   help="target diameters to keep, m (the grid's: 5 7 10 12 15 17 20)")
    p.add_argument("--ranges", type=float, nargs=2, required=True, metavar=("NEAR", "FAR"),
                   help="near-rim ranges to keep, m, both ends included")
    p.add_argument("--out", type=Path, required=True, help="annotations file to write")
    args = p.parse_args(argv)
    try:
        coco = read_json_file(args.annotations, "COCO annotations", expect=dict)
        out = select_cells(coco, args.diameters, tuple(args.ranges), str(args.annotations))
        if not out["images"]:
            raise InputError(f"{args.annotations}: no frame in those cells")
        path = write_json(args.out, out, indent=None)
    except LunarNavError as err:
        print(f"protocol_cells: error: {err}", file=sys.stderr)
        return 2
    print(f"{path}: {len(out['images'])} of {len(coco['images'])} images")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Write a balanced half of a rendered protocol set as another annotations file beside it.

The paper-stereo grid is ordered (diameter, approach, near-rim range, sun zenith), zenith
fastest. The half keeps grid item k when ``(k // 4 + k) % 2 == 0``: per (diameter, approach,
range) two of the four sun zeniths, alternating with the range, so every diameter, approach,
range and zenith keeps exactly half of its items. Evaluations that take minutes per hundred
pairs (SGBM at 1024 px) run on it in half the time:

    .venv/bin/python benchmarks/protocol_subset.py /tmp/ps1024
    .venv/bin/lunarnav eval --task geometry --gt /tmp/ps1024/half_annotations.json --out ...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from lunarnav_ml.utils.atomic import write_json


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("root", type=Path, help="protocol set folder holding annotations.json")
    args = p.parse_args(argv)
    coco = json.loads((args.root / "annotations.json").read_text())
    keep = {im["id"] for k, im in enumerate(coco["images"]) if (k // 4 + k) % 2 == 0}
    out = {**coco, "images": [im for im in coco["images"] if im["id"] in keep],
           "annotations": [a for a in coco["annotations"] if a["image_id"] in keep]}
    path = write_json(args.root / "half_annotations.json", out, indent=None)
    print(f"{path}: {len(out['images'])} of {len(coco['images'])} images")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

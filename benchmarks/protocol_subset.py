"""Write a balanced half of a protocol set as another annotations file beside it.

The paper-stereo grid is ordered (diameter, approach, near-rim range, sun zenith), zenith
fastest. The half keeps grid item k when ``(k // 4 + k) % 2 == 0``: per (diameter, approach,
range) two of the four sun zeniths, alternating with the range, so every diameter, approach,
range and zenith keeps exactly half of its items. Evaluations that take minutes per hundred
pairs (SGBM at 1024 px) run on it in half the time:

    .venv/bin/python benchmarks/protocol_subset.py /tmp/ps1024
    .venv/bin/lunarnav eval --task geometry --gt /tmp/ps1024/half_annotations.json --out ...

With ``--render`` only the half's items are rendered first (the same bytes as in a full
render with that seed; 896 pairs at 1024 px take about 25 min on 2 cores):

    .venv/bin/python benchmarks/protocol_subset.py /tmp/ps1024 --render --size 1024

``--config`` renders with other scene settings (e.g. ``configs/synth/legacy_crest.yaml``, the
renders before session 47).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lunarnav_ml.errors import LunarNavError
from lunarnav_ml.utils.atomic import write_json
from lunarnav_ml.utils.jsonfile import read_json_file


def in_half(k: int) -> bool:
    """Whether grid item ``k`` belongs to the balanced half."""
    return (k // 4 + k) % 2 == 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("root", type=Path, help="protocol set folder (holding annotations.json "
                   "unless --render)")
    p.add_argument("--render", action="store_true", help="render the half's items first")
    p.add_argument("--protocol", default="paper-stereo", help="with --render: the grid")
    p.add_argument("--size", type=int, default=1024, help="with --render: image side, px")
    p.add_argument("--seed", type=int, default=0, help="with --render: master seed")
    p.add_argument("--workers", type=int, default=2, help="with --render: processes")
    p.add_argument("--config", type=Path, default=None,
                   help="with --render: scene settings YAML (default: the defaults)")
    args = p.parse_args(argv)
    try:
        if args.render:
            from lunarnav_ml.synth.config import SynthConfig
            from lunarnav_ml.synth.generate import generate_dataset
            from lunarnav_ml.synth.protocols import grid

            cfg = SynthConfig.from_yaml(args.config) if args.config else None
            path = generate_dataset(args.root, seed=args.seed, image_size=args.size, config=cfg,
                                    protocol=args.protocol, workers=args.workers,
                                    items=[k for k in range(len(grid(args.protocol))) if in_half(k)])
        else:
            path = args.root / "annotations.json"
        coco = read_json_file(path, "COCO annotations")
    except LunarNavError as err:
        print(f"protocol_subset: error: {err}", file=sys.stderr)
        return 2
    # image id = grid index + 1 (synth.generate.write_item)
    keep = {im["id"] for im in coco["images"] if in_half(im["id"] - 1)}
    out = {**coco, "images": [im for im in coco["images"] if im["id"] in keep],
           "annotations": [a for a in coco["annotations"] if a["image_id"] in keep]}
    path = write_json(args.root / "half_annotations.json", out, indent=None)
    print(f"{path}: {len(out['images'])} of {len(coco['images'])} images")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

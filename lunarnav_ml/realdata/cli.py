"""``lunarnav import-real``: a real labelled set (COCO / Roboflow COCO, YOLO txt) into our
COCO convention, with an import report. Images are referenced in place, never copied.

Example::

    lunarnav import-real /work/shared/data/real/chandai_lunar_scene_v5 --out data/real/chandai_v5 \\
        --map configs/realdata/category_map.yaml --splits train valid
"""

from __future__ import annotations

import argparse
from pathlib import Path

from lunarnav_ml.realdata.importer import FORMATS, REPORT_MD


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``lunarnav import-real``."""
    p = subparsers.add_parser("import-real", help="import a real labelled set (COCO, YOLO txt)",
                              description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("src", type=Path, help="dataset folder (split folders inside) or one split")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder: <split>/annotations.json and import_report.{json,md}")
    p.add_argument("--map", dest="map_file", type=Path, default=None,
                   help="category-map YAML (default: built-in, as "
                        "configs/realdata/category_map.yaml)")
    p.add_argument("--format", dest="fmt", choices=FORMATS, default=None,
                   help="source format (default: detected)")
    p.add_argument("--splits", nargs="+", default=None,
                   help="split folders to import (default: every split found)")
    p.add_argument("--skip-bad", action="store_true",
                   help="skip and count bad labels (missing images, boxes outside the image, "
                        "unknown categories, leaked source frames) instead of stopping")
    p.set_defaults(func=run_import)


def run_import(args: argparse.Namespace) -> int:
    """Run the import and print one line per split."""
    from lunarnav_ml.realdata.importer import import_real

    report = import_real(args.src, args.out, map_file=args.map_file, fmt=args.fmt,
                         splits=args.splits, skip_bad=args.skip_bad)
    for name, s in report["splits"].items():
        print(f"{name}: {s['images_out']}/{s['images_in']} images ({s['source_frames']} source "
              f"frames), {s['annotations_out']}/{s['annotations_in']} boxes {s['per_class']}, "
              f"dropped {sum(s['dropped'].values())}, skipped {sum(s['skipped'].values())}")
    print(f"-> {args.out} (report: {args.out / REPORT_MD})")
    return 0

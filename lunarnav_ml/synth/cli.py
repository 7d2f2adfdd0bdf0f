"""``lunarnav synth``: render a synthetic dataset (stereo, lidar, COCO labels)."""

from __future__ import annotations

import argparse
from pathlib import Path

from lunarnav_ml.errors import InputError

PROTOCOLS = ("paper-mono", "paper-stereo", "paper-lidar")


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``synth`` subcommand."""
    p = subparsers.add_parser(
        "synth", help="render a synthetic lunar dataset (stereo, lidar, COCO labels)",
        description="Render domain-randomized lunar scenes (or one of the paper's protocol "
                    "grids) into a dataset folder: left/right PNGs, depth, disparity, lidar "
                    "scans and annotations.json. Re-running skips finished items.")
    p.add_argument("out", type=Path, help="dataset folder to write")
    p.add_argument("--n", type=int, default=None,
                   help="number of scenes (default 200; with --protocol: first N grid items)")
    p.add_argument("--seed", type=int, default=0, help="master seed (same seed, same bytes)")
    p.add_argument("--config", type=Path, default=None, help="synth YAML (configs/synth/)")
    p.add_argument("--size", type=int, default=512, help="image side, px (default 512)")
    p.add_argument("--protocol", choices=PROTOCOLS, default=None, help="the paper's grids")
    p.add_argument("--shard", default="0/1", help="render items with index %% n == k (k/n)")
    p.add_argument("--lidar", action="store_true", help="also write 360 deg lidar scans")
    p.add_argument("--no-stereo", action="store_true", help="left images only")
    p.add_argument("--gallery", type=Path, default=None,
                   help="also write a labelled gallery PNG of examples across sun angles")
    p.add_argument("--merge", action="store_true",
                   help="only merge finished shards into annotations.json")
    p.add_argument("--workers", type=int, default=None,
                   help="rendering processes (default: 2 when there are >= 32 items, else 1)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``lunarnav synth``; returns the exit code."""
    from lunarnav_ml.synth import SynthConfig, generate_dataset, merge_annotations
    from lunarnav_ml.synth.generate import parse_shard

    if args.merge:
        print(merge_annotations(args.out))
        return 0
    if args.n is not None and args.n < 0:
        raise InputError(f"--n: must be >= 0, got {args.n}")
    from lunarnav_ml.utils.atomic import check_destination, check_image_destination

    check_destination(args.out, folder=True)  # bad paths found now, not after rendering
    if args.gallery is not None:
        check_image_destination(args.gallery)
    cfg = SynthConfig.from_yaml(args.config) if args.config else SynthConfig()
    ann = generate_dataset(args.out, n_images=args.n, seed=args.seed, config=cfg,
                           image_size=args.size, protocol=args.protocol,
                           shard=parse_shard(args.shard), stereo=not args.no_stereo,
                           lidar=args.lidar, progress=not args.quiet, workers=args.workers)
    print(ann)
    if args.gallery is not None:
        from lunarnav_ml.synth.gallery import write_gallery

        print(write_gallery(args.gallery, config=cfg, seed=args.seed, image_size=args.size))
    return 0

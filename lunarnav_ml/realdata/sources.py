"""Source frames and cameras of real images: de-duplication of augmented copies.

Roboflow exports name each image ``<origname>_<ext>.rf.<hash>.jpg`` and keep the original name
in the COCO image's ``extra.name``; its augmentations make several images of one source frame.
All copies of a frame must stay in one split, or a model is evaluated on frames it trained on.
"""

from __future__ import annotations

import itertools
import re
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from pathlib import PurePath
from typing import Any

import numpy as np

# Original-name prefix -> camera (see shared/data/real/*/SOURCE.md).
CAMERA_PREFIXES: dict[str, str] = {
    "PCAML-C-": "pcam_colour",  # Chang'e 3 Yutu Panoramic Camera, left eye, colour
    "PCAML-Q-": "pcam_pan",  # Chang'e 3 Yutu Panoramic Camera, left eye, panchromatic
    "C3_TCAM_": "ce3_tcam",  # Chang'e 3 lander Terrain Camera
    "chang4_": "ce4",  # Chang'e 4 surface image (probably lander TCAM)
}
UNKNOWN_CAMERA = "unknown"
_ROBOFLOW_NAME = re.compile(r"^(?P<stem>.+)_(?P<ext>[A-Za-z0-9]+)\.rf\.[0-9a-fA-F]+\.[A-Za-z0-9]+$")


def original_name(file_name: str) -> str:
    """The source frame's file name behind a Roboflow export name.

    ``C3_TCAM_2_2C_011_png.rf.90ed....jpg`` -> ``C3_TCAM_2_2C_011.png``; any other name is
    returned unchanged (without its folder).
    """
    name = PurePath(file_name).name
    match = _ROBOFLOW_NAME.match(name)
    return f"{match['stem']}.{match['ext']}" if match else name


def source_name(image: Mapping[str, Any]) -> str:
    """The source frame of a COCO image: ``extra.name`` when the export kept it, else the
    original name parsed from ``file_name``."""
    extra = image.get("extra")
    if isinstance(extra, Mapping) and isinstance(extra.get("name"), str) and extra["name"]:
        return PurePath(extra["name"]).name
    return original_name(str(image["file_name"]))


def camera_for(name: str, prefixes: Mapping[str, str] = CAMERA_PREFIXES) -> str:
    """The camera of a source frame from its original name's prefix (``"unknown"`` if none).

    Examples: ``PCAML-C-012_...png`` -> ``pcam_colour``, ``chang4_2019...png`` -> ``ce4``.
    """
    base = PurePath(name).name
    for prefix, camera in prefixes.items():
        if base.startswith(prefix):
            return camera
    return UNKNOWN_CAMERA


def group_by_source(names: Iterable[str]) -> dict[str, list[int]]:
    """Indices of the images of each source frame, in first-seen order."""
    groups: dict[str, list[int]] = defaultdict(list)
    for i, name in enumerate(names):
        groups[name].append(i)
    return dict(groups)


def check_leakage(splits: Mapping[str, Iterable[str]]) -> dict[str, list[str]]:
    """Source frames shared between splits.

    Args:
        splits: split name -> source names of its images (repeats allowed).

    Returns:
        ``{"train/valid": [shared names, sorted], ...}`` for every pair of splits that share a
        source; empty when the splits are clean.
    """
    sets = {split: set(names) for split, names in splits.items()}
    leaks = {}
    for a, b in itertools.combinations(sets, 2):
        shared = sorted(sets[a] & sets[b])
        if shared:
            leaks[f"{a}/{b}"] = shared
    return leaks


def split_by_source(names: Sequence[str], fractions: Mapping[str, float],
                    seed: int | np.random.Generator = 0) -> dict[str, list[int]]:
    """Split images into named parts by source frame, so no source lands in two parts.

    Args:
        names: source name of each image.
        fractions: part name -> fraction of the *source frames* it gets (normalised to sum 1).
        seed: seed or generator for the shuffle of source frames.

    Returns:
        Part name -> sorted image indices.
    """
    if not fractions or any(f < 0 for f in fractions.values()) or sum(fractions.values()) <= 0:
        raise ValueError(f"fractions must be >= 0 with a positive sum, got {dict(fractions)}")
    groups = group_by_source(names)
    order = list(groups)
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    order = [order[i] for i in rng.permutation(len(order))]
    total = sum(fractions.values())
    bounds = np.round(np.cumsum([f / total for f in fractions.values()]) * len(order)).astype(int)
    parts, start = {}, 0
    for part, stop in zip(fractions, bounds):
        parts[part] = sorted(i for src in order[start:stop] for i in groups[src])
        start = stop
    return parts

"""Category mapping of real labelled sets onto ours (DESIGN.md: 1 crater, 2 rock, 3 artifact).

The mapping file is YAML (``configs/realdata/category_map.yaml``)::

    map:                      # source name -> crater | rock | artifact | null (drop)
      crater: crater
      boulder: rock
    unmapped: drop            # a name the map does not list: drop, or error
    ignore_height_below_px: 6 # shorter boxes become ignore regions

Source names are matched case-insensitively with surrounding spaces removed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lunarnav_ml.data.coco import CLASS_NAMES
from lunarnav_ml.errors import ConfigError
from lunarnav_ml.utils.yamlfile import read_yaml

# Built-in default; configs/realdata/category_map.yaml holds the same (a test checks it).
DEFAULT_MAPPING: dict[str, str | None] = {
    "crater": "crater", "rock": "rock", "boulder": "rock", "artifact": "artifact",
    "rocky region": None, "rover path": None, "objects": None,
}
UNMAPPED_POLICIES = ("drop", "error")
_KEYS = ("map", "unmapped", "ignore_height_below_px")


def normalize_name(name: Any) -> str:
    """The form names are compared in: lower case, surrounding spaces removed."""
    return str(name).strip().lower()


@dataclass(frozen=True)
class CategoryMap:
    """How source category names become our category ids.

    Attributes:
        mapping: normalized source name -> our category name (``CLASS_NAMES``) or ``None``
            (dropped on purpose).
        unmapped: ``"drop"`` or ``"error"``: what to do with a name ``mapping`` lacks.
        ignore_height_below_px: boxes shorter than this (px) are marked ``ignore``.
        source: the file the map was read from (``None``: built-in default).
    """

    mapping: dict[str, str | None] = field(default_factory=lambda: dict(DEFAULT_MAPPING))
    unmapped: str = "drop"
    ignore_height_below_px: float = 6.0
    source: Path | None = None

    def target_id(self, name: str) -> int | None:
        """Our category id (1..3) for a source name, or ``None`` when it is dropped.

        Raises:
            KeyError: the name is not in the map and the policy is ``"error"``.
        """
        key = normalize_name(name)
        if key not in self.mapping:
            if self.unmapped == "error":
                raise KeyError(key)
            return None
        target = self.mapping[key]
        return None if target is None else CLASS_NAMES.index(target) + 1

    def to_dict(self) -> dict[str, Any]:
        """The map as written in reports."""
        return {"file": None if self.source is None else str(self.source),
                "map": dict(self.mapping), "unmapped": self.unmapped,
                "ignore_height_below_px": self.ignore_height_below_px}


def load_category_map(path: str | Path | None = None) -> CategoryMap:
    """Read a mapping file; ``None`` gives the built-in default.

    Raises:
        ConfigError: missing or malformed file, unknown key, or a target that is not one of
            ``crater``, ``rock``, ``artifact`` or ``null``.
    """
    if path is None:
        return CategoryMap()
    path = Path(path)
    data = read_yaml(path, "category map file")
    if not isinstance(data, dict) or not isinstance(data.get("map"), dict):
        raise ConfigError(f"{path}: expected a mapping with a 'map' table of name -> category")
    unknown = sorted(set(data) - set(_KEYS))
    if unknown:
        raise ConfigError(f"{path}: unknown key(s) {unknown} (known: {list(_KEYS)})")
    unmapped = data.get("unmapped", "drop")
    if unmapped not in UNMAPPED_POLICIES:
        raise ConfigError(f"{path}: 'unmapped' must be one of {UNMAPPED_POLICIES}, got {unmapped!r}")
    min_h = data.get("ignore_height_below_px", 6.0)
    if not isinstance(min_h, (int, float)) or isinstance(min_h, bool) \
            or not math.isfinite(min_h) or min_h < 0:
        raise ConfigError(f"{path}: 'ignore_height_below_px' must be a finite number >= 0, "
                          f"got {min_h!r}")
    return CategoryMap(_mapping(path, data["map"]), unmapped, float(min_h), path)


def _mapping(path: Path, table: dict) -> dict[str, str | None]:
    mapping: dict[str, str | None] = {}
    for name, target in table.items():
        key = normalize_name(name)
        if target is not None and target not in CLASS_NAMES:
            raise ConfigError(f"{path}: map[{name!r}] = {target!r}: the target must be one of "
                              f"{list(CLASS_NAMES)} or null (drop)")
        if key in mapping:
            raise ConfigError(f"{path}: map lists {name!r} twice (names ignore case and spaces)")
        mapping[key] = target
    return mapping

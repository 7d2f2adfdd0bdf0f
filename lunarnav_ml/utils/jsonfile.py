"""Reading JSON files with errors that name the file."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from lunarnav_ml.errors import InputError


def read_json_file(path: str | Path, what: str = "JSON", expect: type | None = None) -> Any:
    """Parse a JSON file; ``InputError`` naming the file when it is missing, not valid JSON,
    or (with ``expect``) not that type at the top level (``dict`` for a COCO file, ``list``
    for COCO results)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} file not found")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise InputError(f"{path}: {what} is not valid JSON ({err})") from err
    if expect is not None and not isinstance(data, expect):
        kind = {dict: "an object", list: "a list"}.get(expect, expect.__name__)
        raise InputError(f"{path}: {what} must hold {kind} at the top level, "
                         f"got {type(data).__name__}")
    return data

"""Reading YAML configuration files with errors that name the file."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lunarnav_ml.errors import ConfigError, one_line


def read_yaml(path: str | Path, what: str = "YAML file") -> Any:
    """Parse a YAML file; ``ConfigError`` naming the file when it is missing or malformed."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: {what} not found")
    try:
        return yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML ({one_line(err)})") from None

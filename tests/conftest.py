"""Shared fixtures: a tiny synthetic COCO dataset drawn at test time (see detector_fixtures)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.detector_fixtures import make_coco


@pytest.fixture(scope="session")
def tiny_coco(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Train (16 images) and validation (8 images) splits, 96 px, with ignore regions."""
    root = tmp_path_factory.mktemp("tiny_coco")
    return {"train": make_coco(root / "train", 16, 96, seed=1),
            "val": make_coco(root / "val", 8, 96, seed=2)}

"""The weights shipped in the package load and run, within the size limit (issue 4: <= 20 MB)."""

from pathlib import Path

import numpy as np
import pytest
import torch

from lunarnav_ml.training.api import load_detector
from lunarnav_ml.training.cli import DEFAULT_WEIGHTS

WEIGHTS = Path(__file__).parents[2] / "lunarnav_ml" / "weights"


@pytest.mark.parametrize(("name", "preset", "size"), [("small.pt", "small-relu", 384),
                                                      ("small_fullres.pt", "small-relu", 384),
                                                      ("small_s2.pt", "small-relu-s2", 384),
                                                      ("nano.pt", "nano", 320)])
def test_shipped_weights_load_and_detect(name, preset, size):
    path = WEIGHTS / name
    assert path.stat().st_size <= 20e6
    det = load_detector(path)
    assert (det.preset, det.img_size) == (preset, size)
    assert det.class_names == ["crater", "rock", "artifact"]
    assert all(p.dtype == torch.float32 and torch.isfinite(p).all()
               for p in det.model.parameters())
    image = np.random.default_rng(0).integers(0, 255, (300, 400, 3), dtype=np.uint8)
    pred = det.predict([image], conf_thres=0.0)[0]
    assert len(pred["scores"]) > 0 and np.isfinite(pred["boxes"]).all()


def test_detect_defaults_to_the_small_model():
    assert DEFAULT_WEIGHTS == WEIGHTS / "small.pt" and DEFAULT_WEIGHTS.is_file()

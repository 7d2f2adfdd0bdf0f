"""A detector trained once per session on the tiny fixture dataset (two short epochs)."""

import pytest

from lunarnav_ml.training.api import fit_detector


@pytest.fixture(scope="session")
def trained(tiny_coco, tmp_path_factory):
    """(best checkpoint, run folder) of a 2-epoch nano run at 64 px."""
    out = tmp_path_factory.mktemp("run")
    best = fit_detector(tiny_coco["train"], tiny_coco["val"], out, preset="nano", img_size=64,
                        max_minutes=2.0, max_epochs=2, batch_size=8, progress=False,
                        log_every_n_steps=1)
    return best, out

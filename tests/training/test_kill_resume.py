"""A run killed with SIGKILL mid-training resumes from its last step checkpoint."""

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from lunarnav_ml.training.api import fit_detector

SCRIPT = """
import sys
from lunarnav_ml.training.api import fit_detector
fit_detector(sys.argv[1], sys.argv[2], sys.argv[3], img_size=64, batch_size=4, max_epochs=50,
             max_minutes=5, progress=False, checkpoint_every_n_steps=2)
"""


@pytest.mark.slow
def test_sigkill_loses_at_most_one_checkpoint_interval(tiny_coco, tmp_path):
    last = tmp_path / "checkpoints" / "last.ckpt"
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT, str(tiny_coco["train"]),
                             str(tiny_coco["val"]), str(tmp_path)])
    try:
        deadline = time.time() + 240
        while time.time() < deadline and not _step_at_least(last, 6):
            time.sleep(1.0)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    saved = torch.load(last, map_location="cpu", weights_only=False)["global_step"]
    assert saved >= 6

    fit_detector(tiny_coco["train"], tiny_coco["val"], tmp_path, img_size=64, batch_size=4,
                 max_epochs=saved // 4 + 2, max_minutes=5, progress=False, resume=True,
                 checkpoint_every_n_steps=2)
    steps = _logged_steps(tmp_path / "csv" / "version_1" / "metrics.csv")
    assert min(steps) >= saved  # training went on from the checkpoint, not from step 0
    assert torch.load(last, map_location="cpu", weights_only=False)["global_step"] > saved


def _step_at_least(path: Path, step: int) -> bool:
    try:
        return torch.load(path, map_location="cpu", weights_only=False)["global_step"] >= step
    except Exception:  # noqa: BLE001 - absent or being written
        return False


def _logged_steps(path: Path) -> list[int]:
    with open(path) as f:
        return [int(row["step"]) for row in csv.DictReader(f) if row.get("step")]

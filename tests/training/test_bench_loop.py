"""benchmarks/bench_loop.py: the loader is timed across epochs; the step rates are real."""

import math

import torch

from lunarnav_ml.data.datamodule import DetectionDataModule
from lunarnav_ml.training.module import DetectorModule
from tests.bench_scripts import load_script

bench_loop = load_script("bench_loop")


def test_loader_rate_runs_past_an_epoch_and_steps_train(tiny_coco):
    dm = DetectionDataModule(tiny_coco["train"], tiny_coco["val"], img_size=64, batch_size=4)
    dm.setup("fit")
    loader = dm.train_dataloader()
    assert len(loader) == 4
    assert bench_loop.loader_rate(loader, 10) > 0  # 10 batches: two and a half epochs

    module = DetectorModule("nano", img_size=64)
    batches = [next(iter(loader)) for _ in range(2)]
    before = [p.detach().clone() for p in module.model.parameters()]
    rate = bench_loop.step_rate(module, batches, 2, torch.device("cpu"), "32",
                                channels_last=False, ema=True, copy=True)
    assert math.isfinite(rate) and rate > 0
    assert any(not torch.equal(a, p) for a, p in zip(before, module.model.parameters()))
    assert int(module.ema.updates) == 5  # three warm-up steps and two timed ones
    rate = bench_loop.step_rate(module, batches, 2, torch.device("cpu"), "32",
                                channels_last=False, ema=True, copy=True, host_targets=True)
    assert math.isfinite(rate) and rate > 0 and int(module.ema.updates) == 10

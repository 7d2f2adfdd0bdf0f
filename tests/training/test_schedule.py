from types import SimpleNamespace

import torch
from lightning.pytorch.callbacks import Timer

from lunarnav_ml.training.callbacks import TimeBudgetSchedule
from lunarnav_ml.training.schedule import WarmupCosine


class _Clock(Timer):
    """A Timer whose elapsed and remaining training time are set by the test."""

    def __init__(self) -> None:
        super().__init__(duration="00:01:00:00")
        self.elapsed, self.remaining = 0.0, 3600.0

    def time_elapsed(self, stage: str = "train") -> float:
        return self.elapsed

    def time_remaining(self, stage: str = "train") -> float:
        return self.remaining


def _run(steps: int, clock: _Clock, sched: WarmupCosine, cb: TimeBudgetSchedule) -> None:
    trainer = SimpleNamespace(callbacks=[clock], global_step=steps,
                              lr_scheduler_configs=[SimpleNamespace(scheduler=sched)])
    cb.on_train_epoch_end(trainer, SimpleNamespace(log=lambda *a, **k: None))


def test_time_budget_plan_follows_the_pace_both_ways_under_the_configured_length():
    opt = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0)
    sched = WarmupCosine(opt, total_steps=100_000, warmup_steps=10)
    cb, clock = TimeBudgetSchedule(margin=0.0), _Clock()
    clock.elapsed, clock.remaining = 600.0, 3000.0  # a slow first epoch: 1 step/s
    _run(600, clock, sched, cb)
    assert sched.total_steps == 600 + 3000
    clock.elapsed, clock.remaining = 1200.0, 2400.0  # now 3 steps/s on average since the start
    _run(1200 + 2400, clock, sched, cb)  # (0.33 s/step overall)
    assert sched.total_steps == 3600 + 7200  # raised again: the plan was not stuck at its lowest
    clock.elapsed, clock.remaining = 1200.0, 1e9
    _run(3600, clock, sched, cb)
    assert sched.total_steps == 100_000  # never beyond the configured length
    assert sched.state_dict()["max_steps"] == 100_000  # kept for a resumed run


def test_training_rate_counts_images_over_the_window_without_validation(monkeypatch):
    import pytest

    from lunarnav_ml.errors import ConfigError
    from lunarnav_ml.training import callbacks
    from lunarnav_ml.training.callbacks import TrainingRate
    now = [0.0]
    monkeypatch.setattr(callbacks.time, "perf_counter", lambda: now[0])
    logged = {}
    module = SimpleNamespace(log=lambda name, value, **k: logged.__setitem__(name, value))
    cb, trainer, batch = TrainingRate(window=2), SimpleNamespace(global_step=0), (torch.zeros(4),)

    def step(t: float) -> None:
        now[0] = t
        trainer.global_step += 1
        cb.on_train_batch_end(trainer, module, None, batch, 0)

    step(100.0)  # the first batch (start-up) starts the first window
    step(101.0)
    assert logged == {}
    cb.on_validation_start(trainer, module)
    now[0] = 111.0  # ten seconds of validation, not counted
    cb.on_validation_end(trainer, module)
    step(112.0)  # two steps of 4 images in 2 s of training
    assert logged["train/images_per_s"] == pytest.approx(4.0)
    step(112.5)
    step(113.0)  # 8 images in 1 s
    assert logged["train/images_per_s"] == pytest.approx(8.0)
    with pytest.raises(ConfigError, match="window must be >= 1"):
        TrainingRate(window=0)

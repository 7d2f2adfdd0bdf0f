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

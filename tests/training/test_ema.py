"""Weight EMA: each update moves every float tensor by the current decay; counters are copied."""

import math

import torch

from lunarnav_ml.models import build_model
from lunarnav_ml.training.ema import ModelEMA


def test_update_is_the_decayed_average_and_copies_integer_buffers():
    model = build_model("nano")
    ema = ModelEMA(model, decay=0.9, tau=2.0)
    before = {k: v.clone() for k, v in ema.module.state_dict().items()}
    with torch.no_grad():
        for p in model.parameters():
            p.add_(1.0)
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_var.mul_(3.0)
                m.num_batches_tracked += 5
    d = 0.9 * (1 - math.exp(-1 / 2.0))  # the first update's decay
    ema.update(model)
    src = model.state_dict()
    for key, value in ema.module.state_dict().items():
        if value.dtype.is_floating_point:
            torch.testing.assert_close(value, d * before[key] + (1 - d) * src[key])
        else:
            assert torch.equal(value, src[key])
    assert ema.updates == 1


def test_update_count_follows_a_loaded_checkpoint():
    model = build_model("nano")
    ema = ModelEMA(model, decay=0.9, tau=2.0)
    for _ in range(3):
        ema.update(model)
    saved = {k: v.clone() for k, v in ema.state_dict().items()}
    assert int(saved["updates"]) == 3
    resumed = ModelEMA(model, decay=0.9, tau=2.0)
    resumed.update(model)  # its host count is 1 now; the checkpoint says 3
    holder = torch.nn.Module()
    holder.ema = resumed
    holder.load_state_dict({f"ema.{k}": v for k, v in saved.items()})  # as a parent module loads
    assert resumed.current_decay() == ema.current_decay()
    resumed.update(model)
    ema.update(model)
    assert resumed.updates == ema.updates == 4

"""Resuming restores step, optimizer state, LR schedule and EMA; fine-tuning loads weights."""

import lightning as L
import pytest
import torch
from lightning.pytorch.loggers import CSVLogger

from lunarnav_ml.data.datamodule import DetectionDataModule
from lunarnav_ml.errors import InputError
from lunarnav_ml.training.module import DetectorModule
from lunarnav_ml.training.trainer import build_callbacks


class _Record(L.Callback):
    """Snapshot of the training state when (re)starting."""

    def on_train_start(self, trainer, pl_module):
        opt = trainer.optimizers[0]
        first = opt.param_groups[0]["params"][0]
        self.step = trainer.global_step
        self.lr = opt.param_groups[0]["lr"]
        self.exp_avg = opt.state[first]["exp_avg"].clone() if first in opt.state else None
        self.ema_updates = int(pl_module.ema.updates)
        self.anchors = pl_module.model.anchors.clone()


def _trainer(out, max_steps, record):
    return L.Trainer(default_root_dir=out, max_steps=max_steps, accelerator="cpu",
                     callbacks=[*build_callbacks(out / "ckpt", every_n_steps=2), record],
                     logger=CSVLogger(out), enable_progress_bar=False, enable_model_summary=False,
                     num_sanity_val_steps=0, limit_val_batches=1, val_check_interval=2)


def _parts(coco, **kw):
    L.seed_everything(0, workers=True)
    dm = DetectionDataModule(coco["train"], coco["val"], img_size=64, batch_size=4)
    return DetectorModule(img_size=64, warmup_steps=2, **kw), dm


def test_resume_continues_step_optimizer_and_lr(tiny_coco, tmp_path):
    module, dm = _parts(tiny_coco)
    _trainer(tmp_path, 3, _Record()).fit(module, dm)  # stops at step 3, last.ckpt at step 2
    ckpt_path = tmp_path / "ckpt" / "last.ckpt"
    saved = torch.load(ckpt_path, map_location="cpu", weights_only=False)
    assert saved["global_step"] == 2

    record = _Record()
    module, dm = _parts(tiny_coco)
    _trainer(tmp_path, 5, record).fit(module, dm, ckpt_path=str(ckpt_path))
    opt_state = saved["optimizer_states"][0]
    assert record.step == 2
    assert record.lr == pytest.approx(opt_state["param_groups"][0]["lr"])
    assert saved["lr_schedulers"][0]["last_epoch"] == 2
    torch.testing.assert_close(record.exp_avg, opt_state["state"][0]["exp_avg"])
    assert record.ema_updates == 2
    torch.testing.assert_close(record.anchors, saved["state_dict"]["model.anchors"])


def test_finetune_from_checkpoint_with_frozen_backbone(tiny_coco, tmp_path):
    module, dm = _parts(tiny_coco)
    _trainer(tmp_path / "a", 2, _Record()).fit(module, dm)
    source = tmp_path / "a" / "ckpt" / "last.ckpt"
    weights = torch.load(source, map_location="cpu", weights_only=False)["state_dict"]

    record = _Record()
    module, dm = _parts(tiny_coco, init_from=str(source), freeze_backbone=True)
    _trainer(tmp_path / "b", 2, record).fit(module, dm)
    assert record.step == 0  # a new run, not a resume
    torch.testing.assert_close(record.anchors, weights["ema.module.anchors"])
    backbone = {k: v for k, v in module.model.state_dict().items() if k.startswith("backbone")}
    for key, value in backbone.items():  # frozen: weights and BatchNorm statistics unchanged
        torch.testing.assert_close(value, weights["ema.module." + key])
    head = "head.preds.0.weight"
    assert not torch.equal(module.model.state_dict()[head], weights["ema.module." + head])


def test_finetune_rejects_other_preset(tiny_coco, tmp_path, trained):
    other, dm = _parts(tiny_coco, preset="tiny", init_from=str(trained[0]))
    with pytest.raises(InputError, match="weights do not fit this model"):
        _trainer(tmp_path / "b", 1, _Record()).fit(other, dm)


def test_init_from_another_preset_with_the_same_tensors_warns(tmp_path):
    import warnings

    from lunarnav_ml.models import build_model
    from lunarnav_ml.training.checkpoint import load_weights, save_slim

    path = save_slim(tmp_path / "small.pt", {"preset": "small", "num_classes": 3},
                     build_model("small"))
    with pytest.warns(UserWarning, match="preset 'small' start a 'small-relu' model"):
        load_weights(build_model("small-relu"), path, "small-relu")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_weights(build_model("small"), path, "small")


class _FirstLoss(_Record):
    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if batch_idx == 0:
            self.first_loss = float(outputs["loss"])


def test_channels_last_trains_like_the_default_layout(tiny_coco, tmp_path):
    losses = {}
    for flag in (False, True):
        module, dm = _parts(tiny_coco, channels_last=flag)
        record = _FirstLoss()
        _trainer(tmp_path / str(flag), 2, record).fit(module, dm)
        for model in (module.model, module.ema.module):
            conv = next(m for m in model.modules() if isinstance(m, torch.nn.Conv2d))
            assert conv.weight.is_contiguous(memory_format=torch.channels_last) == flag
        losses[flag] = record.first_loss
    assert losses[True] == pytest.approx(losses[False], rel=1e-4)  # same batch, same weights


def test_compiled_training_matches_eager_and_keeps_checkpoint_keys(tiny_coco, tmp_path):
    # aot_eager: the compile path without inductor's code generation (a minute on 2 cores)
    losses, keys = {}, {}
    for flag in (False, True):
        module, dm = _parts(tiny_coco, compile="aot_eager" if flag else False)
        record = _FirstLoss()
        _trainer(tmp_path / str(flag), 2, record).fit(module, dm)
        assert (module.model._compiled_call_impl is not None) == flag
        losses[flag] = record.first_loss
        saved = torch.load(tmp_path / str(flag) / "ckpt" / "last.ckpt", map_location="cpu",
                           weights_only=False)
        keys[flag] = sorted(saved["state_dict"])
    assert losses[True] == pytest.approx(losses[False], rel=1e-4)  # same batch, same weights
    assert keys[True] == keys[False]  # a compiled run's checkpoint loads anywhere


class _HostPrepared(DetectorModule):
    """Keeps each training batch as the loader gave it, and the RNG state before the hook."""

    def on_before_batch_transfer(self, batch, dataloader_idx):
        if self.trainer.training:
            self.raw_batch, self.rng = batch, torch.get_rng_state()
        return super().on_before_batch_transfer(batch, dataloader_idx)


class _CompareLosses(L.Callback):
    """The step's loss from the host-prepared batch against the loss from the plain one."""

    def __init__(self):
        self.pairs, self.sides = [], []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        from lunarnav_ml.losses.yolo_loss import PreparedTargets
        assert len(batch) == 4 and isinstance(batch[1], PreparedTargets)
        with torch.no_grad():
            new = pl_module._losses(pl_module.model, *pl_module._prepare(batch, True))
            state = torch.get_rng_state()
            torch.set_rng_state(pl_module.rng)  # the same multi-scale draw
            old = pl_module._losses(pl_module.model, *pl_module._prepare(pl_module.raw_batch, True))
            torch.set_rng_state(state)
        self.pairs.append((float(new["loss"]), float(old["loss"])))
        self.sides.append(batch[3])


def test_targets_prepared_on_the_host_give_the_device_path_loss(tiny_coco, tmp_path):
    L.seed_everything(0, workers=True)
    dm = DetectionDataModule(tiny_coco["train"], tiny_coco["val"], img_size=64, batch_size=4)
    module = _HostPrepared(img_size=64, warmup_steps=2, multiscale=(32, 96))
    record = _CompareLosses()
    _trainer(tmp_path, 4, record).fit(module, dm)
    assert len(record.pairs) == 4 and set(record.sides) <= {32, 64, 96}
    assert len(set(record.sides)) > 1  # the multi-scale draw moved with the preparation
    for new, old in record.pairs:
        assert new == old


def test_accumulated_batches_step_ema_and_schedule_once_per_optimizer_step(tiny_coco, tmp_path):
    """``--trainer.accumulate_grad_batches 8`` emulates a GPU's batch on a CPU (configs/
    small_relu_acc.yaml): the EMA and the LR schedule move once per optimizer step, not per
    micro-batch, so their constants (``ema_tau``, ``warmup_steps``) keep their meaning."""
    module, dm = _parts(tiny_coco)
    trainer = L.Trainer(default_root_dir=tmp_path, max_epochs=1, limit_train_batches=4,
                        accumulate_grad_batches=2, accelerator="cpu", logger=False,
                        enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, limit_val_batches=0)
    trainer.fit(module, dm)
    assert trainer.global_step == 2 and int(module.ema.updates) == 2
    assert trainer.lr_scheduler_configs[0].scheduler.last_epoch == 2


def test_reanchor_keeps_the_boxes_and_changes_the_shapes():
    from lunarnav_ml.errors import ConfigError
    from lunarnav_ml.models import build_model
    from lunarnav_ml.models.decode import decode
    from lunarnav_ml.training.checkpoint import reanchor

    torch.manual_seed(0)
    model = build_model("nano").eval()
    x = torch.rand(1, 3, 128, 128)
    with torch.no_grad():
        before = decode(model(x), model.anchors, model.strides, model.scale_xy)
    new = model.anchors.clone()
    new[1, 1] = torch.tensor([160.0, 8.0])  # a flat anchor in place of the middle one
    assert reanchor(model, new.tolist()) == [(1, 1)]
    torch.testing.assert_close(model.anchors, new)
    with torch.no_grad():
        after = decode(model(x), model.anchors, model.strides, model.scale_xy)
    torch.testing.assert_close(after, before, rtol=1e-4, atol=1e-3)  # the same boxes
    assert reanchor(model, new) == []  # nothing changed, nothing moved
    for bad in (new[:2], torch.full_like(new, float("nan")), -new, "flat"):
        with pytest.raises(ConfigError, match="reanchor"):
            reanchor(model, bad)


def test_reanchor_adds_anchors_as_copies_of_the_nearest():
    from lunarnav_ml.errors import ConfigError
    from lunarnav_ml.models import build_model
    from lunarnav_ml.models.decode import decode, split_raw
    from lunarnav_ml.training.checkpoint import reanchor

    torch.manual_seed(0)
    model = build_model("nano").eval()
    x = torch.rand(1, 3, 128, 128)
    with torch.no_grad():
        before = [split_raw(r, 3) for r in model(x)]
    old = model.anchors.clone()
    flat = torch.tensor([[40.0, 4.0], [160.0, 8.0], [320.0, 12.0]])
    new = torch.cat([old, flat[:, None]], dim=1)  # a fourth, flat anchor per level
    assert reanchor(model, new.tolist()) == [(0, 3), (1, 3), (2, 3)]
    assert model.head.num_anchors == 4 and model.anchors.shape == (3, 4, 2)
    with torch.no_grad():
        raw = model(x)
        boxes = decode(raw, model.anchors, model.strides, model.scale_xy)
    for level, r in enumerate(raw):
        p = split_raw(r, 4)
        torch.testing.assert_close(p[:, :3], before[level])  # the old slots as they were
        src = int((old[level].log() - flat[level].log()).square().sum(-1).argmin())
        torch.testing.assert_close(p[:, 3, ..., 4:], before[level][:, src, ..., 4:])
    # the added slot's boxes are its source anchor's: same centres and sizes
    per_level = [r.shape[2] * r.shape[3] for r in raw]
    start = 0
    for level, n in enumerate(per_level):
        b = boxes[:, start:start + 4 * n, :4].reshape(1, 4, n, 4)
        src = int((old[level].log() - flat[level].log()).square().sum(-1).argmin())
        torch.testing.assert_close(b[:, 3], b[:, src], rtol=1e-4, atol=1e-3)
        start += 4 * n
    with pytest.raises(ConfigError, match="reanchor"):
        reanchor(model, old)  # fewer anchors than the model has


def test_reanchor_needs_init_from_and_is_applied_on_it(tiny_coco, tmp_path, trained):
    from lunarnav_ml.errors import ConfigError

    with pytest.raises(ConfigError, match="reanchor"):
        _parts(tiny_coco, reanchor=[[[10, 7]] * 3] * 3)
    source = torch.load(trained[0], map_location="cpu", weights_only=False)["state_dict"]
    new = source["ema.module.anchors"].clone()
    new[2, 0] = torch.tensor([90.0, 6.0])
    record = _Record()
    module, dm = _parts(tiny_coco, init_from=str(trained[0]), reanchor=new.tolist())
    _trainer(tmp_path / "b", 1, record).fit(module, dm)
    torch.testing.assert_close(record.anchors, new)


def test_reanchor_with_an_added_anchor_trains_resumes_and_loads(tiny_coco, tmp_path, trained):
    from lunarnav_ml.training.api import load_detector

    source = torch.load(trained[0], map_location="cpu", weights_only=False)["state_dict"]
    old = source["ema.module.anchors"]
    new = torch.cat([old, torch.tensor([[24.0, 3.0], [48.0, 4.0], [96.0, 6.0]])[:, None]], 1)
    module, dm = _parts(tiny_coco, init_from=str(trained[0]), reanchor=new.tolist())
    _trainer(tmp_path, 3, _Record()).fit(module, dm)  # last.ckpt at step 2
    ckpt_path = tmp_path / "ckpt" / "last.ckpt"
    record = _Record()
    module, dm = _parts(tiny_coco, init_from=str(trained[0]), reanchor=new.tolist())
    _trainer(tmp_path, 4, record).fit(module, dm, ckpt_path=str(ckpt_path))
    assert record.step == 2 and record.ema_updates == 2
    torch.testing.assert_close(record.anchors, new)
    detector = load_detector(ckpt_path)
    assert detector.model.head.num_anchors == 4
    torch.testing.assert_close(detector.model.anchors, new)
    saved = torch.load(ckpt_path, map_location="cpu", weights_only=False)["state_dict"]
    torch.testing.assert_close(detector.model.head.preds[1].weight,
                               saved["ema.module.head.preds.1.weight"])

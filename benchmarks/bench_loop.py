"""Which side holds a training run: the loader, the step, or what lies between them.

    python3 benchmarks/bench_loop.py --train data/gpu/train/annotations.json --device cuda \
        --workers 14 --batch 64 --precision bf16 --init-from lunarnav_ml/weights/small.pt

Prints images/s for each part of a training step on real batches of a COCO dataset:

- ``loader``: the training DataLoader alone (workers decode, augment and collate; this
  process only receives the batches, pinned when a GPU is used);
- ``step``: forward, loss, backward and AdamW on a few of those batches kept on the device
  (``bench_train.py``'s figure, with real targets);
- ``step+ema``: the same with the weight EMA's update after each step;
- ``step+ema+copy``: the same, each batch copied from pinned host memory first (targets too);
- the ``host targets`` rows: the same with the loss's targets prepared on the host before the
  copy (``YOLOLoss.prepare``, what a Lightning run does since session 39), so that the step
  waits on nothing on the device.

A Lightning run's steps/s set against these tells where its time goes (BENCHMARKS.md, issue 4).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from typing import Any

import torch
from bench_train import time_steps
from torch.utils.data import DataLoader

from lunarnav_ml.data.datamodule import DetectionDataModule
from lunarnav_ml.errors import LunarNavError
from lunarnav_ml.losses.yolo_loss import PreparedTargets
from lunarnav_ml.training.module import DetectorModule


def _to(batch: tuple, device: torch.device, channels_last: bool,
        prepare: Callable[[list, int], PreparedTargets] | None = None) -> tuple[torch.Tensor, Any]:
    """A batch on ``device``: the network input, and its targets, prepared on the host first
    when ``prepare`` is given."""
    images, targets, _ = batch
    x = images.to(device, non_blocking=True).float() / 255.0
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    if prepare is not None:
        return x, prepare(targets, len(images)).to(device)
    return x, [{k: v.to(device, non_blocking=True) for k, v in t.items()} for t in targets]


def _endless(loader):
    """The loader's batches epoch after epoch."""
    while True:
        yield from loader


def loader_rate(loader, batches: int) -> float:
    """Images/s the loader keeps up, timed after the batches its workers made side by side
    when they started (``prefetch_factor`` each; timed from the first batch, as before
    session 39, the figure included that head start)."""
    it = _endless(loader)
    burst = 1 + (loader.prefetch_factor or 0) * loader.num_workers
    for _ in range(burst):
        next(it)
    n, start = 0, time.perf_counter()
    for _ in range(batches):
        n += len(next(it)[0])
    return n / (time.perf_counter() - start)


def step_rate(module: DetectorModule, batches: list, steps: int, device: torch.device,
              precision: str, channels_last: bool, ema: bool, copy: bool,
              host_targets: bool = False) -> float:
    """Images/s of training steps cycling over ``batches`` (host batches if ``copy``, their
    targets prepared on the host each time if ``host_targets``), after three untimed steps."""
    model = module.model
    prepare = None
    if host_targets:
        side, pin = batches[0][0].shape[-1], device.type == "cuda"

        def prepare(targets: list, n: int) -> PreparedTargets:
            return module.host_targets(targets, n, side, pin)

    ready = [_to(b, device, channels_last, prepare) for b in batches] if not copy else None

    def batch_at(i: int) -> tuple[torch.Tensor, Any]:
        if copy:
            return _to(batches[i % len(batches)], device, channels_last, prepare)
        return ready[i % len(ready)]

    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    step_s = time_steps(model, module.loss, opt, batch_at, steps, 3, device, precision,
                        (lambda: module.ema.update(model)) if ema else None)
    return len(batches[0][0]) / step_s


def _loader(train: str, size: int, batch: int, workers: int) -> DataLoader:
    """The training DataLoader of a DetectionDataModule (its cache filled at setup)."""
    dm = DetectionDataModule(train, train, img_size=size, batch_size=batch, num_workers=workers)
    dm.setup("fit")
    return dm.train_dataloader()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train", required=True, help="training annotations.json")
    parser.add_argument("--preset", default="small-relu")
    parser.add_argument("--init-from", help="weights to start from (anchors come with them)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--size", type=int, default=384, help="input side, px")
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--workers", type=int, nargs="+", default=[2],
                        help="loader workers; the loader is timed for each, the steps use the "
                             "first")
    parser.add_argument("--loader-batches", type=int, default=30)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--precision", choices=("32", "bf16"), default="bf16")
    parser.add_argument("--channels-last", choices=("auto", "on", "off"), default="auto",
                        help="auto: on a GPU only, as DetectorModule(channels_last=None)")
    args = parser.parse_args()
    device = torch.device(args.device)
    channels_last = {"auto": device.type == "cuda", "on": True, "off": False}[args.channels_last]

    print(f"torch {torch.__version__}, {device}, batch {args.batch}, {args.size} px, "
          f"{args.precision}, channels-last {channels_last}")
    try:
        module = DetectorModule(args.preset, init_from=args.init_from, img_size=args.size)
        module.setup("fit")
        loaders = [(w, _loader(args.train, args.size, args.batch, w))
                   for w in reversed(args.workers)]
    except LunarNavError as err:
        print(f"bench_loop: error: {err}", file=sys.stderr)
        return 2
    for workers, loader in loaders:
        n = args.loader_batches if workers else max(2, args.loader_batches // 6)
        print(f"loader, {workers:2d} workers {loader_rate(loader, n):7.1f} img/s"
              + (" (pinned)" if loader.pin_memory else ""))
        if loader.pin_memory:
            unpinned = DataLoader(loader.dataset, loader.batch_size, sampler=loader.sampler,
                                  num_workers=workers, collate_fn=loader.collate_fn,
                                  drop_last=loader.drop_last)
            print(f"loader, {workers:2d} workers "
                  f"{loader_rate(unpinned, n):7.1f} img/s (not pinned)")

    it = _endless(loader)
    batches = [next(it) for _ in range(4)]
    if device.type == "cuda":
        batches = [(b[0].pin_memory(), [{k: v.pin_memory() for k, v in t.items()} for t in b[1]],
                    b[2]) for b in batches]
    module.to(device).train()
    if channels_last:
        module.model.to(memory_format=torch.channels_last)
        module.ema.to(memory_format=torch.channels_last)
    for name, ema, copy, host in (
            ("step", False, False, False), ("step+ema", True, False, False),
            ("step+ema+copy", True, True, False), ("step, host targets", False, False, True),
            ("step+ema+copy, host targets", True, True, True)):
        rate = step_rate(module, batches, args.steps, device, args.precision, channels_last,
                         ema, copy, host)
        print(f"{name:28s} {rate:7.1f} img/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

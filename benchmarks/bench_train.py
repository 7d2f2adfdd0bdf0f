"""Training throughput per preset (images/s of forward + loss + backward + AdamW step).

    .venv/bin/python benchmarks/bench_train.py --presets nano tiny small --size 320 --batch 8
    .venv/bin/python benchmarks/bench_train.py --presets small --size 384 --precision 32 bf16
    python3 benchmarks/bench_train.py --device cuda --presets small-relu --size 384 --batch 64 \
        --precision bf16 --steps 30 --warmup 5

``--precision bf16`` runs forward and loss under autocast in bfloat16 (Lightning's
``trainer.precision: bf16-mixed``); on CPU it pays off with AVX512-BF16 or AMX. On a GPU the
figure has no data loading in it: set it against a training run's steps/s to see whether the
loader or the model holds the run.

Random images with a few random boxes each; prints one line per preset.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable

import torch

from lunarnav_ml.losses import YOLOLoss
from lunarnav_ml.models import build_model, count_parameters


def _targets(batch: int, size: int, gen: torch.Generator) -> list[dict[str, torch.Tensor]]:
    out = []
    for _ in range(batch):
        xy = torch.rand(6, 2, generator=gen) * size * 0.7
        wh = 8 + torch.rand(6, 2, generator=gen) * size * 0.25
        out.append({"boxes": torch.cat([xy, xy + wh], 1).clamp(max=size),
                    "labels": torch.randint(1, 4, (6,), generator=gen)})
    return out


def time_steps(model: torch.nn.Module, loss_fn: YOLOLoss, opt: torch.optim.Optimizer,
               batch_at: Callable[[int], tuple[torch.Tensor, list[dict]]], steps: int,
               warmup: int, device: torch.device, precision: str = "32",
               after_step: Callable[[], None] | None = None) -> float:
    """Seconds per training step (forward and loss, under bf16 autocast if asked; backward;
    optimizer step; then ``after_step``) on ``batch_at(i)``, after ``warmup`` untimed steps."""
    autocast = torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bf16")
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    for i in range(warmup + steps):
        if i == warmup:
            sync()
            start = time.perf_counter()
        x, targets = batch_at(i)
        with autocast:
            loss = loss_fn(model(x), targets, model.anchors, model.strides, model.scale_xy)["loss"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if after_step is not None:
            after_step()
    sync()
    return (time.perf_counter() - start) / steps


def bench(preset: str, size: int, batch: int, steps: int, warmup: int,
          precision: str = "32", device: str = "cpu",
          channels_last: bool = False) -> dict[str, float]:
    """Seconds per training step and images per second for one preset."""
    dev = torch.device(device)
    autocast = torch.autocast(dev.type, dtype=torch.bfloat16, enabled=precision == "bf16")
    gen = torch.Generator().manual_seed(0)
    model = build_model(preset).train().to(dev)
    loss_fn = YOLOLoss(model.num_classes)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3)
    x = torch.rand(batch, 3, size, size, generator=gen).to(dev)
    if channels_last:
        model, x = model.to(memory_format=torch.channels_last), x.contiguous(
            memory_format=torch.channels_last)
    targets = [{k: v.to(dev) for k, v in t.items()} for t in _targets(batch, size, gen)]
    cuda = dev.type == "cuda"
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    if cuda:
        torch.cuda.reset_peak_memory_stats(dev)
    step = time_steps(model, loss_fn, opt, lambda i: (x, targets), steps, warmup, dev, precision)
    model.eval()
    with torch.no_grad(), autocast:
        model(x)
        sync()
        t0 = time.perf_counter()
        model(x)
        sync()
        infer = time.perf_counter() - t0
    peak = torch.cuda.max_memory_allocated(dev) / 2**30 if cuda else float("nan")
    return {"params_m": count_parameters(model) / 1e6, "step_s": step,
            "train_img_s": batch / step, "infer_img_s": batch / infer, "peak_gib": peak}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["nano", "tiny", "small"])
    parser.add_argument("--size", type=int, default=320, help="input side, px")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:1, ...")
    parser.add_argument("--precision", nargs="+", choices=("32", "bf16"), default=["32"],
                        help="float32 and/or bfloat16 autocast")
    parser.add_argument("--channels-last", action="store_true",
                        help="model and batches in channels-last (NHWC) memory format")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {args.device}, {torch.get_num_threads()} threads, "
          f"input {args.size} px, batch {args.batch}")
    for preset in args.presets:
        for precision in args.precision:
            r = bench(preset, args.size, args.batch, args.steps, args.warmup, precision,
                      args.device, args.channels_last)
            print(f"{preset:8s} {precision:>4s} {r['params_m']:6.2f} M params  train "
                  f"{r['train_img_s']:6.1f} img/s "
                  f"({r['step_s']:.2f} s/step)  inference {r['infer_img_s']:6.1f} img/s"
                  + (f"  peak {r['peak_gib']:.1f} GiB" if math.isfinite(r["peak_gib"]) else ""))


if __name__ == "__main__":
    main()

"""Synthetic stereo rendering speed and memory: pairs per second at 512 and 1024 px, peak RSS.

Usage: .venv/bin/python benchmarks/bench_synth.py [--n 6] [--threads 2] [--config PATH]
Renders complete items (terrain, left + right images, depth, disparity, labels) into a
temporary folder, after one warm-up item (numba cache load), and prints one line per size.
CPU-seconds per pair (all threads) are printed too: on a shared machine they stay meaningful
when wall-clock rates are depressed by other load (check ``uptime`` before recording).
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path


def _cpu() -> float:
    """CPU seconds of this process and its finished children."""
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; prints results, returns 0."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=6, help="pairs per size")
    ap.add_argument("--threads", type=int, default=2, help="numba / BLAS threads")
    ap.add_argument("--sizes", type=int, nargs="+", default=[512, 1024])
    ap.add_argument("--config", type=Path, default=None)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2],
                    help="rendering processes to compare (1 = numba threads in one process)")
    args = ap.parse_args(argv)
    for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(args.threads)
    import cv2
    import numba

    from lunarnav_ml.synth import SynthConfig, generate_dataset

    numba.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    cfg = SynthConfig.from_yaml(args.config) if args.config else SynthConfig()
    with tempfile.TemporaryDirectory() as tmp:
        generate_dataset(Path(tmp) / "warm", n_images=1, seed=99, config=cfg, image_size=128,
                         progress=False)
        print(f"bench_synth: {args.threads} threads, {args.n} stereo pairs per size, "
              f"config {args.config or 'default'}")
        for size in args.sizes:
            for workers in args.workers:
                t0, c0 = time.perf_counter(), _cpu()
                generate_dataset(Path(tmp) / f"s{size}w{workers}", n_images=args.n, seed=1,
                                 config=cfg, image_size=size, progress=False, workers=workers)
                dt, cpu = time.perf_counter() - t0, _cpu() - c0
                note = " incl. worker start-up" if workers > 1 else ""
                print(f"  {size}x{size}, {workers} worker(s): {args.n / dt:.2f} pairs/s "
                      f"({dt / args.n:.2f} s/pair wall, {cpu / args.n:.2f} CPU-s/pair{note})")
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024**2
    print(f"  peak RSS: {own:.2f} GiB (main process), {kids:.2f} GiB (largest worker); "
          f"total with 2 workers <= {own + 2 * kids:.2f} GiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Dataset generation: items -> files (atomic), sharding, resume, COCO merge.

Layout (docs/ARCHITECTURE.md): ``annotations.json``, ``images/left|right/<stem>.png``,
``depth/<stem>.npy``, ``disparity/<stem>.npy``, ``lidar/<stem>.npz``. Each finished item also
leaves ``items/<stem>.json`` (its image entry and annotations), written last: an item whose
record exists is complete and is skipped on resume. Item i belongs to shard k of n when
i % n == k; every item's randomness comes from (seed, i) alone, so shards and resumed runs
produce the same bytes as one uninterrupted run.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.synth.config import SynthConfig
from lunarnav_ml.synth.pipeline import Rendered, TerrainCache, render_item
from lunarnav_ml.synth.scene import SceneSpec, sample_scene
from lunarnav_ml.utils import atomic
from lunarnav_ml.utils.jsonfile import read_json_file

CATEGORIES = [{"id": 1, "name": "crater"}, {"id": 2, "name": "rock"},
              {"id": 3, "name": "artifact"}]
DEFAULT_N = 200


def item_seed(seed: int, index: int) -> np.random.Generator:
    """Generator for item ``index`` of a run with ``seed`` (independent of sharding)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]))


def plan_items(cfg: SynthConfig, seed: int, n_images: int | None, protocol: str | None
               ) -> tuple[SynthConfig, list[Callable[[], SceneSpec]]]:
    """The config to render with and one zero-argument spec factory per item."""
    if protocol is None:
        n = DEFAULT_N if n_images is None else n_images
        return cfg, [(lambda i=i: sample_scene(cfg, item_seed(seed, i))) for i in range(n)]
    from lunarnav_ml.synth.protocols import protocol_config, protocol_specs

    specs = protocol_specs(protocol, cfg, seed)
    if n_images is not None:
        specs = specs[:n_images]
    return protocol_config(cfg), [(lambda s=s: s) for s in specs]


def parse_shard(text: str) -> tuple[int, int]:
    """'k/n' -> (k, n) with 0 <= k < n; InputError otherwise."""
    try:
        k, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise InputError(f"--shard: expected k/n such as 0/4, got {text!r}") from None
    check_shard((k, n))
    return k, n


def check_shard(shard: Sequence[int]) -> tuple[int, int]:
    """Validate a (k, n) shard."""
    if len(shard) != 2 or not 0 <= shard[0] < shard[1]:
        raise InputError(f"shard: need 0 <= k < n, got {tuple(shard)}")
    return int(shard[0]), int(shard[1])


def generate_dataset(out_dir: str | Path, n_images: int | None = None, seed: int = 0,
                     config: SynthConfig | None = None, image_size: int = 512,
                     protocol: str | None = None, shard: Sequence[int] = (0, 1),
                     stereo: bool = True, lidar: bool = False, progress: bool = True,
                     workers: int | None = None, items: Sequence[int] | None = None) -> Path:
    """Render a dataset folder and return the path of its annotations.

    Args:
        out_dir: dataset root (created). n_images: number of random scenes (default 200); with
            a protocol, None renders the whole grid and a number keeps its first n items.
        seed: master seed; same seed, same bytes. config: SynthConfig (default settings).
        image_size: square image side, px. protocol: None, 'paper-mono', 'paper-stereo' or
            'paper-lidar'. shard: (k, n), render items with index % n == k.
        stereo: also render the right image. lidar: also write lidar scans.
        progress: tqdm bar on stderr.
        workers: rendering processes (each single-threaded). None: 1 for fewer than 32 items,
            else min(2, CPU count). Output bytes do not depend on it.
        items: render only these item indices (of this shard; e.g. a balanced subset of a
            protocol grid); None: all. An item's bytes do not depend on which others exist.

    Returns:
        ``annotations.json`` once every item of the run exists (always for shard 0/1),
        otherwise this shard's ``annotations.shard-k-of-n.json``. A sharded run writes its
        shard's file even when it finishes the set, so that each shard can be read alone.
    """
    cfg = config if config is not None else SynthConfig()
    if not isinstance(cfg, SynthConfig):
        raise ConfigError(f"config: expected SynthConfig, got {type(cfg).__name__}")
    if not isinstance(image_size, int) or not 16 <= image_size <= 8192:
        raise InputError(f"image_size: must be an integer in 16..8192, got {image_size!r}")
    if n_images is not None and (not isinstance(n_images, int) or n_images < 0):
        raise InputError(f"n_images: must be a non-negative integer, got {n_images!r}")
    if workers is not None and (not isinstance(workers, int) or workers < 1):
        raise InputError(f"workers: must be a positive integer, got {workers!r}")
    k, n = check_shard(shard)
    job = Job(str(Path(out_dir)), int(seed), json.dumps(cfg.to_dict()), image_size, protocol,
              n_images, stereo, lidar or protocol == "paper-lidar")
    used_cfg, plan = _plan(job)
    root = Path(out_dir)
    _write_manifest(root, seed, used_cfg, image_size, protocol, len(plan), job.stereo, job.lidar)
    mine = [i for i in range(len(plan)) if i % n == k]
    if items is not None:
        wanted = {int(i) for i in items}
        bad = sorted(i for i in wanted if not 0 <= i < len(plan))
        if bad:
            raise InputError(f"items: indices must be in 0..{len(plan) - 1}, got {bad[0]}")
        mine = [i for i in mine if i in wanted]
    todo = [i for i in mine if not (root / "items" / f"{i:06d}.json").exists()]
    if workers is None:
        workers = 1 if len(todo) < 32 else max(1, min(2, os.cpu_count() or 1))
    bar = _progress(len(mine), progress)
    bar.update(bar.total - len(todo))
    if workers == 1 or len(todo) < 2:
        render_items(job, todo, bar.update)
    else:
        _render_parallel(job, todo, workers, bar.update)
    bar.close()
    return _finish(root, len(plan), k, n)


@dataclasses.dataclass(frozen=True)
class Job:
    """Everything a worker process needs to render items of a run (picklable)."""

    root: str
    seed: int
    cfg_json: str
    image_size: int
    protocol: str | None
    n_images: int | None
    stereo: bool
    lidar: bool


@functools.lru_cache(maxsize=2)
def _plan(job: Job) -> tuple[SynthConfig, list[Callable[[], SceneSpec]]]:
    """The render config and spec factories of a run (cached per process)."""
    return plan_items(SynthConfig.from_dict(json.loads(job.cfg_json)), job.seed, job.n_images,
                      job.protocol)


def render_items(job: Job, indices: Sequence[int],
                 done: Callable[[int], Any] | None = None) -> int:
    """Render and write the items ``indices`` of ``job`` in order; returns how many."""
    cfg, plan = _plan(job)
    cache = TerrainCache()
    for i in indices:
        spec = plan[i]()
        out = render_item(spec, cfg, job.image_size, stereo=job.stereo, lidar=job.lidar,
                          cache=cache)
        write_item(Path(job.root), i, job.seed, spec, out)
        if done is not None:
            done(1)
    return len(indices)


def _worker_init(parent: int) -> None:
    """Worker processes run single-threaded (the pool provides the parallelism) and exit when
    the process that started them is gone: a killed run must not leave idle workers behind."""
    import numba

    numba.set_num_threads(1)
    threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True).start()


def _exit_with_parent(parent: int, poll_s: float = 1.0) -> None:
    """Exit this process once ``parent`` is no longer its parent (it died; we were adopted)."""
    while os.getppid() == parent:
        time.sleep(poll_s)
    os._exit(1)


def _render_parallel(job: Job, todo: list[int], workers: int,
                     done: Callable[[int], Any]) -> None:
    """Render ``todo`` in ``workers`` spawned processes, in chunks of consecutive items
    (protocol items that share terrain stay together)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    size = 16 if job.protocol else 1
    chunks = [todo[c: c + size] for c in range(0, len(todo), size)]
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_init,
                             initargs=(os.getpid(),)) as pool:
        futures = [pool.submit(render_items, job, chunk) for chunk in chunks]
        for fut in as_completed(futures):
            done(fut.result())


def _progress(total: int, enabled: bool) -> Any:
    from tqdm import tqdm

    return tqdm(total=total, desc="synth", unit="img", file=sys.stderr, disable=not enabled)


def _write_manifest(root: Path, seed: int, cfg: SynthConfig, size: int, protocol: str | None,
                    total: int, stereo: bool, lidar: bool) -> None:
    """Record the run settings; a resumed run must match them."""
    manifest = {"seed": seed, "image_size": size, "protocol": protocol, "n_items": total,
                "stereo": stereo, "lidar": lidar, "config": cfg.to_dict()}
    path = root / "synth_manifest.json"
    if path.exists():
        old = read_json_file(path, "synth manifest", expect=dict)
        if old != json.loads(json.dumps(manifest)):
            diff = sorted(k for k in manifest if old.get(k) != json.loads(json.dumps(manifest[k])))
            raise InputError(f"{path}: {root} holds a run with other settings ({', '.join(diff)});"
                             " use a new folder")
        return
    atomic.write_json(path, manifest)


def write_item(root: Path, index: int, seed: int, spec: SceneSpec, out: Rendered) -> None:
    """Write one item's files, then its record ``items/<stem>.json`` (the completion mark)."""
    stem = f"{index:06d}"
    image: dict[str, Any] = {"id": index + 1, "file_name": f"images/left/{stem}.png",
                             "width": out.left.shape[1], "height": out.left.shape[0]}
    atomic.write_image(root / image["file_name"], out.left)
    if out.right is not None:
        image["right_file"] = f"images/right/{stem}.png"
        atomic.write_image(root / image["right_file"], out.right)
    image["depth_file"] = f"depth/{stem}.npy"
    atomic.write_npy(root / image["depth_file"], out.depth)
    image["disparity_file"] = f"disparity/{stem}.npy"
    atomic.write_npy(root / image["disparity_file"], out.disparity)
    if out.lidar is not None:
        image["lidar_file"] = f"lidar/{stem}.npz"
        atomic.write_npz(root / image["lidar_file"], **out.lidar)
    image.update(out.image_info)
    image["seed"] = [int(seed), index]
    atomic.write_json(root / "items" / f"{stem}.json",
                      {"image": image, "annotations": out.annotations}, indent=None)


def _finish(root: Path, total: int, k: int, n: int) -> Path:
    """Write the shard's COCO file (a sharded run's, or a run of some items), and
    annotations.json when all items are present; the latter's path then, else the shard's."""
    done = [i for i in range(total) if (root / "items" / f"{i:06d}.json").exists()]
    shard_file = None
    if n > 1 or len(done) < total:  # the last shard to finish still reads as one shard
        shard_file = atomic.write_json(root / f"annotations.shard-{k}-of-{n}.json",
                                       _coco(root, [i for i in done if i % n == k]),
                                       indent=None)
    if len(done) == total:
        return merge_annotations(root, total)
    return shard_file


def merge_annotations(root: str | Path, total: int | None = None) -> Path:
    """Collect every item record into ``annotations.json`` (annotation ids in item order)."""
    root = Path(root)
    if total is None:
        manifest = root / "synth_manifest.json"
        if not manifest.exists():
            raise InputError(f"{manifest}: not a synth dataset folder")
        total = _manifest_items(manifest)
    missing = [i for i in range(total) if not (root / "items" / f"{i:06d}.json").exists()]
    if missing:
        raise InputError(f"{root}: {len(missing)} of {total} items are not rendered yet "
                         f"(first missing: {missing[0]:06d})")
    return atomic.write_json(root / "annotations.json", _coco(root, list(range(total))),
                             indent=None)


def _manifest_items(path: Path) -> int:
    """``n_items`` of a synth manifest; ``InputError`` naming the file when it is corrupt."""
    manifest = read_json_file(path, "synth manifest", expect=dict)
    n = manifest.get("n_items")
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise InputError(f"{path}: corrupt manifest: n_items must be an integer >= 0, got {n!r}")
    return n


def _coco(root: Path, indices: list[int]) -> dict[str, Any]:
    images, anns = [], []
    for i in indices:
        path = root / "items" / f"{i:06d}.json"
        try:
            rec = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise InputError(f"{path}: corrupt item record ({err}); delete it to re-render") from None
        if (not isinstance(rec, dict) or not isinstance(rec.get("image"), dict)
                or "id" not in rec["image"] or not isinstance(rec.get("annotations"), list)
                or not all(isinstance(a, dict) for a in rec["annotations"])):
            raise InputError(f"{path}: corrupt item record (needs an 'image' object with an 'id' "
                             "and an 'annotations' list of objects); delete it to re-render")
        images.append(rec["image"])
        for a in rec["annotations"]:
            anns.append({"id": len(anns) + 1, "image_id": rec["image"]["id"], **a})
    return {"info": {"description": "lunarnav_ml synthetic lunar scenes"},
            "images": images, "annotations": anns, "categories": CATEGORIES}

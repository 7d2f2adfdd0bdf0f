"""Lightning DataModule: one or several COCO training sources mixed by weight, a COCO
validation set."""

from __future__ import annotations

from pathlib import Path

import cv2
import lightning as L
import numpy as np
import torch
from torch.utils.data import ConcatDataset, DataLoader, WeightedRandomSampler

from lunarnav_ml.data.anchors import anchors_for_levels, box_sizes
from lunarnav_ml.data.dataset import CocoDetection, collate
from lunarnav_ml.errors import ConfigError


def mixing_weights(sizes: list[int], weights: list[float]) -> torch.Tensor:
    """Per-sample weights so that source ``k`` is drawn with probability
    ``weights[k] / sum(weights)`` whatever its size.

    Shape:
        - Output: :math:`(\\sum_k sizes_k,)`
    """
    if len(sizes) != len(weights):
        raise ConfigError(f"{len(weights)} sampling weights for {len(sizes)} training sources")
    if any(w < 0 for w in weights) or sum(weights) <= 0:
        raise ConfigError(f"sampling weights must be >= 0 with a positive sum, got {weights}")
    total = float(sum(weights))
    return torch.cat([torch.full((n,), w / total / n, dtype=torch.float64)
                      for n, w in zip(sizes, weights)])


def _is_int(x: object) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def check_loader_settings(img_size: int, batch_size: int, num_workers: int) -> None:
    """ConfigError naming the ``data.*`` setting that no loader can run with."""
    if not _is_int(img_size) or img_size <= 0 or img_size % 32:
        raise ConfigError(f"data.img_size: must be a positive multiple of 32, got {img_size!r}")
    if not _is_int(batch_size) or batch_size < 1:
        raise ConfigError(f"data.batch_size: must be an integer >= 1, got {batch_size!r}")
    if not _is_int(num_workers) or num_workers < 0:
        raise ConfigError(f"data.num_workers: must be an integer >= 0, got {num_workers!r}")


class DetectionDataModule(L.LightningDataModule):
    """Training and validation loaders over COCO datasets.

    Args:
        train: training ``annotations.json`` path(s); several are mixed.
        val: validation ``annotations.json`` path.
        weights: sampling weight per training source (default: proportional to size).
        img_size: network input side, px.
        batch_size: images per batch (per device).
        num_workers: loader worker processes.
        mosaic_prob: probability of a 4-image mosaic per training sample.
        augment: box-aware photometric/geometric augmentation of training samples.
        cache: keep decoded images in memory. With loader workers, every image is decoded
            once at setup (threaded) and the forked workers share them.
        num_classes: category ids 1..num_classes.
        read_sizes: per training source, the long side its frames are read at before a
            random ``img_size`` crop (:class:`CocoDetection` ``read_size``); None or a None
            entry letterboxes that source's whole frames.
    """

    def __init__(self, train: str | list[str], val: str, weights: list[float] | None = None,
                 img_size: int = 320, batch_size: int = 16, num_workers: int = 0,
                 mosaic_prob: float = 0.0, augment: bool = True, cache: bool = True,
                 num_classes: int = 3, read_sizes: list[int | None] | None = None) -> None:
        super().__init__()
        check_loader_settings(img_size, batch_size, num_workers)
        self.train_files = [train] if isinstance(train, (str, Path)) else list(train)
        if not self.train_files:
            raise ConfigError("data.train: give at least one annotations.json")
        self.read_sizes = read_sizes
        self.val_file = val
        self.weights = weights
        self.img_size, self.batch_size, self.num_workers = img_size, batch_size, num_workers
        self.mosaic_prob, self.augment, self.cache = mosaic_prob, augment, cache
        self.num_classes = num_classes
        self.train_sets: list[CocoDetection] = []
        self.val_set: CocoDetection | None = None

    def setup(self, stage: str | None = None) -> None:
        if not self.train_sets:
            reads = self.read_sizes or [None] * len(self.train_files)
            if len(reads) != len(self.train_files):  # checked here, like the weights: a
                # command line may replace data.train after the config set read_sizes
                raise ConfigError(f"data.read_sizes: {len(reads)} entries for "
                                  f"{len(self.train_files)} training sources")
            self.train_sets = [CocoDetection(f, self.img_size, self.augment, self.mosaic_prob,
                                             self.cache, self.num_classes, read)
                               for f, read in zip(self.train_files, reads)]
        if self.val_set is None:
            self.val_set = CocoDetection(self.val_file, self.img_size, False, 0.0, self.cache,
                                         self.num_classes)
            if self.cache and self.num_workers > 0:
                for ds in [*self.train_sets, self.val_set]:
                    ds.preload(self.num_workers)

    def kmeans_anchors(self, levels: int, per_level: int = 3, seed: int = 0) -> np.ndarray:
        """Anchors from k-means on all training boxes, :math:`(levels, per_level, 2)` px."""
        self.setup("fit")
        sizes = np.concatenate([box_sizes(ds.records, ds.read_size) for ds in self.train_sets])
        return anchors_for_levels(sizes, levels, per_level, seed)

    def train_dataloader(self) -> DataLoader:
        if self.num_workers > 0:
            # one OpenCV thread in each worker (their samples run side by side already): set
            # here, before the workers fork, since setting it inside a forked worker deadlocks
            # once this process has used OpenCV's thread pool. This process keeps the setting.
            cv2.setNumThreads(1)
        data = ConcatDataset(self.train_sets)
        sampler = None
        if len(self.train_sets) > 1 or self.weights is not None:
            sizes = [len(ds) for ds in self.train_sets]
            weights = self.weights or [float(n) for n in sizes]
            sampler = WeightedRandomSampler(mixing_weights(sizes, weights), len(data))
        return DataLoader(data, self.batch_size, shuffle=sampler is None, sampler=sampler,
                          num_workers=self.num_workers, collate_fn=collate,
                          drop_last=len(data) >= 2 * self.batch_size,
                          persistent_workers=self.num_workers > 0,
                          pin_memory=torch.cuda.is_available())

    def val_dataloader(self) -> DataLoader:
        return DataLoader(self.val_set, self.batch_size, shuffle=False,
                          num_workers=self.num_workers, collate_fn=collate,
                          persistent_workers=self.num_workers > 0)

"""Synthetic lunar scenes: terrain, Hapke rendering, stereo, lidar, exact COCO labels.

Public API::

    from lunarnav_ml.synth import SynthConfig, generate_dataset
    ann_path = generate_dataset("data/synth", n_images=200, seed=0, config=SynthConfig())
"""

from lunarnav_ml.synth.config import SynthConfig
from lunarnav_ml.synth.generate import generate_dataset, merge_annotations

__all__ = ["SynthConfig", "generate_dataset", "merge_annotations"]

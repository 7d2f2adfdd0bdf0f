"""Shared helpers for synth tests: small, fast scenes."""

import numpy as np
import pytest

from lunarnav_ml.synth.config import SynthConfig
from lunarnav_ml.synth.scene import SceneSpec, TargetCrater, TerrainSpec
from lunarnav_ml.synth.sensor import SensorParams


@pytest.fixture
def small_cfg() -> SynthConfig:
    """A fast config: 40 m DEM at 10 cm, fewer rocks."""
    return SynthConfig.from_dict({
        "terrain": {"extent_m": 40.0, "resolution_m": 0.1},
        "craters": {"max_diameter_m": 12.0, "min_diameter_m": 1.0},
        "rocks": {"density_per_m2": [0.05, 0.1]},
        "camera": {"max_range_m": 60.0},
    })


def one_crater_spec(diameter=8.0, x=12.0, y=1.0, zenith=60.0, azimuth=90.0, pitch=20.0,
                    roll=0.0, relief=0.0, rocks=0.0, height=1.5) -> SceneSpec:
    """Flat ground (no relief, texture or noise) with one fresh crater."""
    ts = TerrainSpec(seed=3, relief_rms_m=relief, roughness_rms_m=0.0, crater_density=0.0,
                     fresh_fraction=1.0, rock_density=rocks, albedo_rms=0.0,
                     targets=(TargetCrater(x, y, diameter),))
    sensor = SensorParams(read_noise_e=0.0, blur_sigma_px=0.0, full_well_e=1e7)
    return SceneSpec(ts, zenith, azimuth, 0.0, 0.0, 0.0, height, pitch, roll, 0.19, sensor, 0)


def two_crater_spec(first_small: bool) -> SceneSpec:
    """Flat ground, a 4 m crater on the far wall of a 10 m crater (its centre inside the rim); the
    first listed is stamped first (``first_small``: the big one excavates the small one)."""
    small, big = TargetCrater(15.0, 0.5, 4.0), TargetCrater(12.0, 0.0, 10.0)
    ts = TerrainSpec(seed=3, relief_rms_m=0.0, roughness_rms_m=0.0, crater_density=0.0,
                     fresh_fraction=1.0, rock_density=0.0, albedo_rms=0.0,
                     targets=(small, big) if first_small else (big, small))
    sensor = SensorParams(read_noise_e=0.0, blur_sigma_px=0.0, full_well_e=1e7)
    return SceneSpec(ts, 60.0, 90.0, 0.0, 0.0, 0.0, 1.5, 20.0, 0.0, 0.19, sensor, 0)


def image_box(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) of a boolean mask, pixel-index bounds (inclusive)."""
    ys, xs = np.nonzero(mask)
    return xs.min(), ys.min(), xs.max(), ys.max()

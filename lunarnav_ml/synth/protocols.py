"""The paper's evaluation grids (DESIGN.md "The paper's evaluation protocol").

Each item places one target crater at the scene origin and the camera (or lidar) on an approach
line at a given near-rim range, looking at it. Terrain is shared by all items of one diameter
(seeded by the diameter index), so the range and sun sweeps see the same ground.

- ``paper-stereo``: 7 diameters x 4 approach angles x near-rim range 5..20 m step 1 x sun
  zenith {20, 40, 60, 80} deg = 1,792 pairs. The paper lists zeniths {0, 20, 40, 60, 80} but
  states 1,792 pairs, which is 7 x 4 x 16 x 4; we keep the stated count and drop zenith 0
  (no shadows). Sun azimuth 90 deg (from the side).
- ``paper-lidar``: 7 x 4 x 16 = 448 scans (sun irrelevant; images still rendered at zenith 40).
- ``paper-mono``: range sweep 7 x 4 x near-rim range 5..29 m step 2 x zenith {0, 20, 40, 60, 80}
  at azimuth 90 deg (1,820 items), then a sun-azimuth sweep 7 x 4 x ranges {10, 20} m at
  zenith 60 deg x azimuth 0..180 step 30 (392 items): 2,212 in all.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np

from lunarnav_ml.errors import ConfigError
from lunarnav_ml.synth.config import SynthConfig
from lunarnav_ml.synth.scene import SceneSpec, TargetCrater, TerrainSpec, sample_sensor

DIAMETERS_M = (5.0, 7.0, 10.0, 12.0, 15.0, 17.0, 20.0)
APPROACH_DEG = (0.0, 90.0, 180.0, 270.0)
PROTOCOLS = ("paper-mono", "paper-stereo", "paper-lidar")
TARGET_DEPTH_RATIO = 0.2  # the target crater is fresh: depth / diameter 0.2, rim 0.04 D


def target_distance_m(diameter_m: float, near_rim_range_m: float) -> float:
    """Horizontal distance from the sensor's ground point to the target's centre, m: the
    target lies straight ahead (along the approach heading) at near-rim range + radius."""
    return near_rim_range_m + diameter_m / 2


def protocol_config(cfg: SynthConfig) -> SynthConfig:
    """The config used for protocol scenes: small background craters only, no artifacts."""
    d = cfg.to_dict()
    d["craters"]["max_diameter_m"] = min(4.0, d["craters"]["max_diameter_m"])
    d["craters"]["min_diameter_m"] = min(d["craters"]["min_diameter_m"], 4.0)
    d["craters"]["near_camera_boost"] = [0, 0]
    d["artifacts"]["probability"] = 0.0
    return SynthConfig.from_dict(d)


def grid(protocol: str) -> list[tuple[int, float, float, float, float]]:
    """Items as (diameter index, approach deg, near-rim range m, sun zenith, sun azimuth)."""
    d_idx = range(len(DIAMETERS_M))
    if protocol == "paper-stereo":
        return [(d, a, float(r), z, 90.0) for d, a, r, z in itertools.product(
            d_idx, APPROACH_DEG, range(5, 21), (20.0, 40.0, 60.0, 80.0))]
    if protocol == "paper-lidar":
        return [(d, a, float(r), 40.0, 90.0)
                for d, a, r in itertools.product(d_idx, APPROACH_DEG, range(5, 21))]
    if protocol == "paper-mono":
        sweep = [(d, a, float(r), z, 90.0) for d, a, r, z in itertools.product(
            d_idx, APPROACH_DEG, range(5, 30, 2), (0.0, 20.0, 40.0, 60.0, 80.0))]
        sun = [(d, a, r, 60.0, float(az)) for d, a, r, az in itertools.product(
            d_idx, APPROACH_DEG, (10.0, 20.0), range(0, 181, 30))]
        return sweep + sun
    raise ConfigError(f"protocol: unknown '{protocol}' (known: {', '.join(PROTOCOLS)})")


def protocol_specs(protocol: str, cfg: SynthConfig, seed: int) -> list[SceneSpec]:
    """Scene specs of every grid item, in grid order (render with :func:`protocol_config`)."""
    items = grid(protocol)
    out = []
    for index, (d_i, approach, rng_m, zen, az) in enumerate(items):
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), index]))
        out.append(_item_spec(protocol, cfg, seed, d_i, approach, rng_m, zen, az, rng))
    return out


def _item_spec(protocol: str, cfg: SynthConfig, seed: int, d_i: int, approach: float,
               near_m: float, zen: float, az: float, rng: np.random.Generator) -> SceneSpec:
    diameter = DIAMETERS_M[d_i]
    tr = np.random.default_rng(np.random.SeedSequence([int(seed), 7919, d_i]))
    mid = lambda r: 0.5 * (r[0] + r[1])
    ter = TerrainSpec(
        seed=int(tr.integers(2**31)), relief_rms_m=mid(cfg.terrain.relief_rms_m),
        roughness_rms_m=mid(cfg.terrain.roughness_rms_m),
        crater_density=mid(cfg.craters.density_per_m2), fresh_fraction=0.5,
        rock_density=mid(cfg.rocks.density_per_m2), albedo_rms=mid(cfg.hapke.albedo_texture_rms),
        targets=(TargetCrater(0.0, 0.0, diameter, degradation=0.1,
                              depth_ratio=TARGET_DEPTH_RATIO, rim_ratio=0.04),),
        clear_radius_m=1.0)
    dist = target_distance_m(diameter, near_m)
    a = math.radians(approach)
    sensor = dataclasses.replace(sample_sensor(cfg, rng), exposure=0.85)
    item = {"diameter_m": diameter, "approach_deg": approach, "near_rim_range_m": near_m,
            "sun_zenith_deg": zen, "sun_azimuth_deg": az}
    return SceneSpec(
        terrain=ter, sun_zenith_deg=zen, sun_azimuth_deg=az, cam_x=-dist * math.cos(a),
        cam_y=-dist * math.sin(a), yaw_deg=approach, height_m=1.5,
        pitch_deg=mid(cfg.camera.pitch_deg), roll_deg=0.0, w_soil=mid(cfg.hapke.w),
        sensor=sensor, noise_seed=int(rng.integers(2**31)), fov_deg=mid(cfg.camera.fov_deg),
        aspect=mid(cfg.camera.aspect), micro_slope_rms=mid(cfg.terrain.micro_slope_rms),
        micro_albedo_rms=mid(cfg.terrain.micro_albedo_rms),
        pebble_per_m2=mid(cfg.terrain.pebble_per_m2),
        extra={"protocol": protocol, "protocol_item": item})

"""Render one item: stereo images, depth, disparity, lidar scan and its COCO labels."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from lunarnav_ml.synth import labels as L
from lunarnav_ml.synth import render as R
from lunarnav_ml.synth.camera import StereoRig, make_rig, sun_vector
from lunarnav_ml.synth.config import SynthConfig
from lunarnav_ml.synth.scene import Scene, SceneSpec, TerrainSpec, build_terrain, hapke_params
from lunarnav_ml.synth.sensor import expose, exposure_gain


@dataclass
class Rendered:
    """Everything written for one item.

    Attributes:
        left, right: (H, W) uint8 images (right None without stereo).
        depth: (H, W) float32 z-depth, m (inf = sky). disparity: (H, W) float32, px (0 = sky).
        annotations: COCO annotation dicts without ids / image ids.
        image_info: extra COCO image keys (sun, camera, ...).
        lidar: arrays for the lidar .npz, or None.
        ids: (H, W) encoded object ids of the left view.
    """

    left: np.ndarray
    right: np.ndarray | None
    depth: np.ndarray
    disparity: np.ndarray
    annotations: list[dict[str, Any]]
    image_info: dict[str, Any]
    lidar: dict[str, np.ndarray] | None
    ids: np.ndarray


class TerrainCache:
    """Keeps the last built terrain (protocol items reuse the same ground)."""

    def __init__(self) -> None:
        self._key: tuple[TerrainSpec, int] | None = None
        self._scene: Scene | None = None

    def get(self, ts: TerrainSpec, cfg: SynthConfig) -> Scene:
        """Build or reuse the scene for ``ts`` (the config must not change between calls)."""
        key = (ts, id(cfg))
        if self._key != key or self._scene is None:
            self._scene, self._key = build_terrain(ts, cfg), key
        return self._scene


def make_scene_rig(spec: SceneSpec, scene: Scene, cfg: SynthConfig, size: int) -> StereoRig:
    """Stereo rig standing on the bare ground at the spec's camera position."""
    gz = float(scene.ter.height_at(spec.cam_x, spec.cam_y, bare=True))
    return make_rig(np.array([spec.cam_x, spec.cam_y, gz]), width=size, height=size,
                    fov_deg=spec.fov_deg, height_m=spec.height_m, yaw_deg=spec.yaw_deg,
                    pitch_deg=spec.pitch_deg, roll_deg=spec.roll_deg,
                    baseline_m=cfg.camera.baseline_m, aspect=spec.aspect)


def render_item(spec: SceneSpec, cfg: SynthConfig, size: int, *, stereo: bool = True,
                lidar: bool = False, cache: TerrainCache | None = None) -> Rendered:
    """Render one item of ``size`` x ``size`` pixels."""
    scene = (cache or TerrainCache()).get(spec.terrain, cfg)
    rig = make_scene_rig(spec, scene, cfg, size)
    sun = sun_vector(spec.sun_zenith_deg, spec.sun_azimuth_deg, spec.yaw_deg)
    prep = R.prepare(scene.ter, sun)
    hp = hapke_params(cfg, spec.w_soil)
    micro = R.MicroTexture(spec.micro_slope_rms, spec.micro_albedo_rms,
                           cfg.terrain.micro_wavelength_m, salt=float(spec.terrain.seed % 997),
                           pebble_per_m2=spec.pebble_per_m2,
                           pebble_max_radius_m=cfg.terrain.pebble_max_radius_m)
    kw = {"w_soil": spec.w_soil, "hp": hp, "max_range_m": cfg.camera.max_range_m,
          "supersample": cfg.camera.supersample, "micro": micro}
    left = R.render_view(prep, rig.left, **kw)
    hit = np.isfinite(left.depth)
    gain = exposure_gain(left.radiance, hit, spec.sensor.exposure)
    rng = np.random.default_rng(spec.noise_seed)
    left_img = expose(left.radiance, gain, spec.sensor, rng)
    right_img = None
    if stereo:
        right = R.render_view(prep, rig.right, need_ids=False, **kw)
        right_img = expose(right.radiance, gain, spec.sensor, rng)
    disparity = np.where(hit, rig.left.fx * rig.baseline_m / left.depth, 0).astype(np.float32)
    anns = L.crater_annotations(scene.craters, scene.ter, rig.left, left.depth, cfg.labels,
                                cfg.camera.max_range_m)
    anns += L.object_annotations(left.ids, scene.objects, cfg.labels)
    scan = None
    if lidar:
        from lunarnav_ml.synth.lidar import scan_lidar

        scan = scan_lidar(prep, spec, cfg.lidar, rng)
    info = {"sun_zenith_deg": round(spec.sun_zenith_deg, 4),
            "sun_azimuth_deg": round(spec.sun_azimuth_deg, 4), "camera": rig.camera_dict(),
            "w_soil": round(spec.w_soil, 4), **spec.extra}
    return Rendered(left_img, right_img, left.depth, disparity, anns, info, scan, left.ids)

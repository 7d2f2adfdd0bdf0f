"""Scene sampling (domain randomization) and terrain assembly.

A :class:`SceneSpec` holds every random draw of one item (sun, camera, photometry, sensor) and
a hashable :class:`TerrainSpec`; terrain is built from its own seed, so protocol items that
share a TerrainSpec share the same ground (and a one-entry cache skips rebuilding it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lunarnav_ml.synth import craters as C
from lunarnav_ml.synth import objects as O
from lunarnav_ml.synth import terrain as T
from lunarnav_ml.synth.config import SynthConfig, uniform
from lunarnav_ml.synth.hapke import HapkeParams
from lunarnav_ml.synth.sensor import SensorParams


@dataclass(frozen=True)
class TargetCrater:
    """A crater placed on purpose (protocol grids, tests): center (m), diameter (m), shape."""

    x: float
    y: float
    diameter: float
    degradation: float = 0.0
    depth_ratio: float = 0.2
    rim_ratio: float = 0.04


@dataclass(frozen=True)
class TerrainSpec:
    """Everything that fixes the ground; equal specs build identical terrain."""

    seed: int
    relief_rms_m: float
    roughness_rms_m: float
    crater_density: float
    fresh_fraction: float
    rock_density: float
    albedo_rms: float
    n_boost: int = 0
    view_x: float = 0.0  # boost craters and artifacts go ahead of this pose
    view_y: float = 0.0
    view_yaw_deg: float = 0.0
    artifacts: tuple[str, ...] = ()
    targets: tuple[TargetCrater, ...] = ()
    clear_radius_m: float = 0.0  # no random crater overlaps the targets by more than this


@dataclass(frozen=True)
class SceneSpec:
    """One item: terrain, sun, camera pose, photometry and sensor draws."""

    terrain: TerrainSpec
    sun_zenith_deg: float
    sun_azimuth_deg: float
    cam_x: float
    cam_y: float
    yaw_deg: float
    height_m: float
    pitch_deg: float
    roll_deg: float
    w_soil: float
    sensor: SensorParams
    noise_seed: int
    fov_deg: float = 90.0
    aspect: float = 1.0
    micro_slope_rms: float = 0.0
    micro_albedo_rms: float = 0.0
    pebble_per_m2: float = 0.0
    extra: dict = field(default_factory=dict, hash=False, compare=False)


def sample_scene(cfg: SynthConfig, rng: np.random.Generator) -> SceneSpec:
    """Draw a random scene from the config ranges (camera at the origin, heading +x)."""
    cr, art = cfg.craters, cfg.artifacts
    n_art = 0
    if art.kinds and art.max_count > 0 and rng.uniform() < art.probability:
        n_art = int(rng.integers(1, art.max_count + 1))
    kinds = tuple(str(rng.choice(list(art.kinds))) for _ in range(n_art))
    ter = TerrainSpec(
        seed=int(rng.integers(2**31)), relief_rms_m=uniform(rng, cfg.terrain.relief_rms_m),
        roughness_rms_m=uniform(rng, cfg.terrain.roughness_rms_m),
        crater_density=uniform(rng, cr.density_per_m2), fresh_fraction=uniform(rng, cr.fresh_fraction),
        rock_density=uniform(rng, cfg.rocks.density_per_m2),
        albedo_rms=uniform(rng, cfg.hapke.albedo_texture_rms),
        n_boost=round(uniform(rng, cr.near_camera_boost)), artifacts=kinds)
    fov, aspect = cfg.camera.fov_deg, cfg.camera.aspect
    slope, speckle = cfg.terrain.micro_slope_rms, cfg.terrain.micro_albedo_rms
    return SceneSpec(
        terrain=ter, sun_zenith_deg=uniform(rng, cfg.sun.zenith_deg),
        sun_azimuth_deg=uniform(rng, cfg.sun.azimuth_deg) % 360.0, cam_x=0.0, cam_y=0.0,
        yaw_deg=0.0, height_m=uniform(rng, cfg.camera.height_m),
        pitch_deg=uniform(rng, cfg.camera.pitch_deg), roll_deg=uniform(rng, cfg.camera.roll_deg),
        w_soil=uniform(rng, cfg.hapke.w), sensor=sample_sensor(cfg, rng),
        noise_seed=int(rng.integers(2**31)),
        # Keyword arguments are evaluated in order, so the field of view, the pixel aspect and
        # the sub-DEM texture and pebbles are drawn last, each only when it is a real range: a
        # config that fixes them (the default: the paper's 90 deg, square pixels, no texture)
        # draws exactly the scenes it drew before they could vary.
        fov_deg=_draw(rng, fov), aspect=_draw(rng, aspect), micro_slope_rms=_draw(rng, slope),
        micro_albedo_rms=_draw(rng, speckle), pebble_per_m2=_draw(rng, cfg.terrain.pebble_per_m2))


def _draw(rng: np.random.Generator, r: tuple[float, float]) -> float:
    """A value of range ``r``, drawn only when it is one (a fixed value takes no random draw)."""
    return uniform(rng, r) if r[0] < r[1] else r[0]


def sample_sensor(cfg: SynthConfig, rng: np.random.Generator) -> SensorParams:
    """Draw the sensor settings of one scene."""
    s = cfg.sensor
    return SensorParams(exposure=uniform(rng, s.exposure), full_well_e=s.full_well_e,
                        read_noise_e=uniform(rng, s.read_noise_e),
                        blur_sigma_px=uniform(rng, s.blur_sigma_px), gamma=uniform(rng, s.gamma),
                        adc_bits=int(s.adc_bits))


def hapke_params(cfg: SynthConfig, w: float) -> HapkeParams:
    """Photometric parameters of a scene with soil albedo ``w``."""
    h = cfg.hapke
    return HapkeParams(w=w, b=h.b, c=h.c, b_s0=h.b_s0, h_s=h.h_s, b_c0=h.b_c0, h_c=h.h_c,
                       theta_bar_deg=h.theta_bar_deg)


@dataclass
class Scene:
    """Built terrain with its craters and labelled objects (id -> object)."""

    ter: T.Terrain
    craters: list[C.Crater]
    objects: dict[int, O.SceneObject]


def build_terrain(ts: TerrainSpec, cfg: SynthConfig) -> Scene:
    """Assemble the DEM: relief, craters (old to fresh), roughness, rocks, artifacts."""
    rng = np.random.default_rng(ts.seed)
    n = round(cfg.terrain.extent_m / cfg.terrain.resolution_m)
    res = cfg.terrain.extent_m / n
    x0 = -0.5 * n * res
    h = T.base_relief(n, res, relief_rms_m=ts.relief_rms_m, hurst=cfg.terrain.hurst, rng=rng)
    ter = T.Terrain(h, np.ones((n, n), np.float32), np.zeros((n, n), np.uint8),
                    np.zeros((n, n), np.int32), x0, x0, res)
    craters = _crater_population(ts, cfg, rng, ter)
    C.stamp_craters(ter.h, x0, x0, res, craters)
    if ts.roughness_rms_m > 0:
        ter.h += T.fine_roughness(n, res, rms_m=ts.roughness_rms_m, rng=rng)
    ter.bare = ter.h.copy()
    if ts.albedo_rms > 0:
        ter.albedo = T.albedo_texture(n, res, rms=ts.albedo_rms, rng=rng)
    objs = _objects(ts, cfg, rng, ter)
    O.stamp_objects(ter, objs)
    return Scene(ter, craters, {o.oid: o for o in objs})


def _crater_population(ts: TerrainSpec, cfg: SynthConfig, rng: np.random.Generator,
                       ter: T.Terrain) -> list[C.Crater]:
    """Random craters over the DEM, boost craters ahead of the view, then the targets."""
    cc = cfg.craters
    diam = C.sample_diameters(rng, ter.period**2, ts.crater_density, cc.sfd_slope,
                              cc.min_diameter_m, cc.max_diameter_m)
    xy = rng.uniform(0, ter.period, (diam.size, 2)) + ter.x0
    if ts.n_boost:
        d_b = np.exp(rng.uniform(np.log(2.0), np.log(min(20.0, cc.max_diameter_m)), ts.n_boost))
        xy_b = _ahead(rng, ts, ts.n_boost, *cc.near_camera_range_m, 40.0, d_b / 2)
        diam, xy = np.concatenate([diam, d_b]), np.concatenate([xy, xy_b])
    out = []
    for d, (x, y) in zip(diam, xy):
        if _too_close(x, y, d, ts, ter.period):
            continue
        deg, dd, rim = C.sample_morphology(rng, ts.fresh_fraction, cc.depth_ratio_fresh,
                                           cc.depth_ratio_degraded, cc.rim_ratio_fresh)
        out.append(C.make_crater(float(x), float(y), float(d), deg, dd, rim, cc.crest_at_rim))
    out.sort(key=lambda c: -c.degradation)  # degraded (old) first, fresh overprint them
    out += [C.make_crater(t.x, t.y, t.diameter, t.degradation, t.depth_ratio, t.rim_ratio,
                          cc.crest_at_rim) for t in ts.targets]
    return out


def _too_close(x: float, y: float, d: float, ts: TerrainSpec, period: float) -> bool:
    """True when a random crater of diameter d at (x, y) would touch a target crater."""
    for t in ts.targets:
        dx = (x - t.x + period / 2) % period - period / 2
        dy = (y - t.y + period / 2) % period - period / 2
        if math.hypot(dx, dy) < 0.5 * (d + t.diameter) * 1.5 + ts.clear_radius_m:
            return True
    return False


def _ahead(rng: np.random.Generator, ts: TerrainSpec, k: int, r0: float, r1: float,
           half_angle_deg: float, extra: np.ndarray | float = 0.0) -> np.ndarray:
    """(k, 2) points ahead of the view pose at distance r0..r1 (+ extra) within +-half_angle."""
    r = rng.uniform(r0, r1, k) + extra
    a = np.radians(ts.view_yaw_deg + rng.uniform(-half_angle_deg, half_angle_deg, k))
    return np.column_stack([ts.view_x + r * np.cos(a), ts.view_y + r * np.sin(a)])


def _objects(ts: TerrainSpec, cfg: SynthConfig, rng: np.random.Generator,
             ter: T.Terrain) -> list[O.SceneObject]:
    """Rocks everywhere, artifacts ahead of the view."""
    rc = cfg.rocks
    objs = O.sample_rocks(rng, ter, density=ts.rock_density, slope=rc.sfd_slope,
                          d_min=rc.min_diameter_m, d_max=rc.max_diameter_m, burial=rc.burial,
                          albedo_factor=rc.albedo_factor, first_id=1)
    next_id = len(objs) + 1
    for kind in ts.artifacts:
        x, y = _ahead(rng, ts, 1, *cfg.artifacts.range_m, 35.0)[0]
        z = float(ter.height_at(x, y, bare=True))
        objs.append(O.make_artifact(kind, next_id, float(x), float(y), z, rng))
        next_id += 1
    return objs

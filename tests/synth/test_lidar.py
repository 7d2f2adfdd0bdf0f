"""Lidar: returns lie on the terrain surface; occluded crater walls give no returns."""

import numpy as np

from lunarnav_ml.synth import lidar as LD
from lunarnav_ml.synth import pipeline as P
from lunarnav_ml.synth import render as R
from lunarnav_ml.synth.camera import sun_vector
from lunarnav_ml.synth.config import LidarConfig

from .conftest import one_crater_spec


def _scan(cfg, spec, **kw):
    scene = P.TerrainCache().get(spec.terrain, cfg)
    prep = R.prepare(scene.ter, sun_vector(40.0, 90.0, 0.0))
    lc = LidarConfig(**{"h_res_deg": 0.5, "v_res_deg": 0.5, **kw})
    return scene, LD.scan_lidar(prep, spec, lc, np.random.default_rng(0))


def test_beam_grid_matches_paper_table():
    dirs, az, el = LD.beam_directions(LidarConfig())
    assert az.size == 1081 and el.size == 226  # 360 / 0.333, 75 / 0.333 + 1
    tilt = np.degrees(np.arcsin(-dirs[el.size // 2, np.argmin(np.abs(az)), 2]))
    assert abs(tilt - 23.0) < 0.2


def test_points_lie_on_the_surface(small_cfg):
    spec = one_crater_spec(relief=0.3, rocks=0.1)
    scene, scan = _scan(small_cfg, spec, range_noise_m=0.0, range_noise_per_m=0.0)
    pts = scan["points_true"].astype(np.float64) + scan["origin_scene_m"]
    assert len(pts) > 1000
    surface = scene.ter.height_at(pts[:, 0], pts[:, 1])
    assert np.abs(pts[:, 2] - surface).max() < 2e-3
    np.testing.assert_allclose(scan["points"], scan["points_true"], atol=1e-4)


def test_range_noise_has_the_configured_sigma(small_cfg):
    spec = one_crater_spec()
    _, scan = _scan(small_cfg, spec, range_noise_m=0.05, range_noise_per_m=0.0)
    err = np.linalg.norm(scan["points"] - scan["points_true"], axis=1)
    assert 0.03 < np.sqrt(np.mean(err**2)) < 0.07


def test_no_returns_from_hidden_crater_wall(small_cfg):
    """A 10 m fresh crater 7 m ahead: its near inner wall faces away and gets no returns."""
    spec = one_crater_spec(diameter=10.0, x=12.0, y=0.0)
    scene, scan = _scan(small_cfg, spec, range_noise_m=0.0, range_noise_per_m=0.0)
    pts = scan["points_true"].astype(np.float64) + scan["origin_scene_m"]
    r = np.hypot(pts[:, 0] - 12.0, pts[:, 1])
    near_wall = (r < 4.5) & (pts[:, 0] < 12.0 - 2.0) & (np.abs(pts[:, 1]) < 1.5)
    far_wall = (r < 4.5) & (pts[:, 0] > 12.0 + 2.0) & (np.abs(pts[:, 1]) < 1.5)
    assert near_wall.sum() == 0
    assert far_wall.sum() > 20
    # every return is visible: the segment from the sensor stays above the terrain
    origin = scan["origin_scene_m"] + (0, 0, 1.5)
    s = np.linspace(0.02, 0.98, 60)[:, None, None]
    seg = origin + s * (pts[None, ::7] - origin)
    assert np.all(seg[..., 2] >= scene.ter.height_at(seg[..., 0], seg[..., 1]) - 2e-3)

"""360 deg scanning lidar (paper table: 75 deg vertical FOV, 0.333 deg steps, 1.5 m, 23 deg tilt).

Beams are marched through the same heightfield as the cameras, so occlusion is exact: no
returns from crater floors or walls hidden behind the near rim. Output frame ("site"): origin on
the ground below the sensor, x forward (camera heading), y left, z up, m.
"""

from __future__ import annotations

import math

import numpy as np

from lunarnav_ml.synth import render as R
from lunarnav_ml.synth.config import LidarConfig
from lunarnav_ml.synth.scene import SceneSpec

LIDAR_STEP_FRACTION = 0.001  # march step / range: 1 mm per m, so thin rims are not skipped


def beam_directions(lc: LidarConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Beam grid in the site frame.

    Returns:
        dirs (n_el, n_az, 3) unit vectors after the downward tilt, azimuths (n_az,) and
        elevations (n_el,) in the sensor frame, deg (elevation ascending).
    """
    n_az = max(1, round(lc.h_fov_deg / lc.h_res_deg))
    n_el = round(lc.v_fov_deg / lc.v_res_deg) + 1
    az = -0.5 * lc.h_fov_deg + lc.h_res_deg * np.arange(n_az) if lc.h_fov_deg < 360 else \
        lc.h_res_deg * np.arange(n_az) - 180.0
    el = np.linspace(-0.5 * lc.v_fov_deg, 0.5 * lc.v_fov_deg, n_el)
    a, e = np.meshgrid(np.radians(az), np.radians(el))
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1)
    tau = math.radians(lc.tilt_deg)
    tilt = np.array([[math.cos(tau), 0, math.sin(tau)], [0, 1, 0],
                     [-math.sin(tau), 0, math.cos(tau)]])
    return d @ tilt.T, az, el


def scan_lidar(prep: R.PreparedTerrain, spec: SceneSpec, lc: LidarConfig,
               rng: np.random.Generator) -> dict[str, np.ndarray]:
    """One scan from above the camera's ground point, heading ``spec.yaw_deg``.

    Returns:
        ``range_m`` (n_el, n_az) float32 noisy ranges, NaN = no return; ``points`` (M, 3)
        float32 noisy returns in the site frame; ``points_true`` (M, 3) noise-free;
        ``azimuth_deg`` (n_az,), ``elevation_deg`` (n_el,), ``origin_scene_m`` (3,),
        ``yaw_deg``, ``tilt_deg``, ``height_m``.
    """
    dirs, az, el = beam_directions(lc)
    yaw = math.radians(spec.yaw_deg)
    rz = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0],
                   [0, 0, 1]])
    ground = np.array([spec.cam_x, spec.cam_y,
                       float(prep.ter.height_at(spec.cam_x, spec.cam_y, bare=True))])
    origin = ground + (0.0, 0.0, lc.height_m)
    flat = dirs.reshape(-1, 3)
    t = R.cast(prep, origin, flat @ rz.T, 0.0, lc.max_range_m, step_frac=LIDAR_STEP_FRACTION)
    hit = np.isfinite(t)
    sigma = lc.range_noise_m + lc.range_noise_per_m * np.where(hit, t, 0.0)
    noisy = np.where(hit, t + rng.normal(0.0, 1.0, t.shape) * sigma, np.nan)
    sensor_pos = np.array([0.0, 0.0, lc.height_m])
    return {
        "range_m": noisy.reshape(dirs.shape[:2]).astype(np.float32),
        "points": (sensor_pos + flat[hit] * noisy[hit, None]).astype(np.float32),
        "points_true": (sensor_pos + flat[hit] * t[hit, None]).astype(np.float32),
        "azimuth_deg": az.astype(np.float32), "elevation_deg": el.astype(np.float32),
        "origin_scene_m": ground, "yaw_deg": np.float64(spec.yaw_deg),
        "tilt_deg": np.float64(lc.tilt_deg), "height_m": np.float64(lc.height_m),
    }

"""Analytic single-crater scenes with exact answers, for known-answer tests and benchmarks.

A scene is a plane (optionally sloped) carrying axisymmetric craters. It is sampled the way the
paper's sensors see it: a 360 deg lidar scan ray-cast against the heightfield, and a left-camera
disparity map d = f B / Z from the same ray caster. Everything is in the rover frame
(x forward, y left, z up, origin on the ground below the sensor / left camera).

This is not the project's scene generator (``lunarnav_ml.synth``); it exists so the baselines can
be checked against geometry whose answer is known to the millimetre.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from lunarnav_ml.baselines.crater_model import CraterProfile
from lunarnav_ml.errors import InputError
from lunarnav_ml.geometry.frames import camera_to_rover_rotation


@dataclass(frozen=True)
class CraterSpec:
    """One crater of an analytic scene.

    Attributes:
        center_xy: rim-circle center in the rover frame, m.
        profile: shape (diameter, floor depth, rim height), m.
    """

    center_xy: tuple[float, float]
    profile: CraterProfile


@dataclass(frozen=True)
class AnalyticScene:
    """Sloped plane z = sx x + sy y plus craters.

    Attributes:
        craters: craters on the plane (their profiles add to the plane height).
        slope: (sx, sy) plane gradient, m/m.
    """

    craters: Sequence[CraterSpec] = field(default_factory=tuple)
    slope: tuple[float, float] = (0.0, 0.0)

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Terrain height z(x, y), m.

        Shape:
            x, y: any broadcastable shape -> same shape.
        """
        z = self.slope[0] * np.asarray(x, float) + self.slope[1] * np.asarray(y, float)
        for c in self.craters:
            r = np.hypot(x - c.center_xy[0], y - c.center_xy[1])
            z = z + c.profile.height(r)
        return z

    def _band(self) -> tuple[float, float]:
        """Lowest and highest crater relief relative to the plane, m."""
        lo = min([-c.profile.depth_m for c in self.craters], default=0.0)
        hi = max([c.profile.rim_height_m for c in self.craters], default=0.0)
        return lo, hi


def raycast(
    scene: AnalyticScene, origin: np.ndarray, dirs: np.ndarray, max_range_m: float,
    step_m: float = 0.03,
) -> np.ndarray:
    """Distance along each ray to the first terrain hit (inf when none within range).

    Rays are intersected exactly with the plane; rays passing over a crater are marched in steps
    of ``step_m`` through the band the relief occupies, then refined by bisection.

    Args:
        scene: the terrain.
        origin: ray origin, rover frame, m.
        dirs: unit ray directions.
        max_range_m: returns farther than this are dropped (inf).
        step_m: marching step over craters, m.

    Returns:
        t: range along each ray, m.

    Shape:
        origin: (3,); dirs: (N, 3) -> t (N,).
    """
    o = np.asarray(origin, float)
    d = np.asarray(dirs, float)
    sx, sy = scene.slope
    lo, hi = scene._band()

    def t_at_offset(off: float) -> np.ndarray:  # ray parameter where z - plane(x, y) = off
        rate = d[:, 2] - sx * d[:, 0] - sy * d[:, 1]
        gap = o[2] - sx * o[0] - sy * o[1] - off
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(rate < 0, gap / -rate, np.inf)
        return np.where(t >= 0, t, np.inf)

    t = t_at_offset(0.0)
    if scene.craters:
        t_a = np.minimum(t_at_offset(hi + 1e-3), max_range_m)
        t_b = np.minimum(t_at_offset(lo - 1e-3), max_range_m)
        t_in, t_out = _crater_interval(scene, o, d)
        t_a, t_b = np.maximum(t_a, t_in), np.minimum(t_b, t_out)
        idx = np.nonzero((t_a < t_b) & ~(t < t_in))  # skip rays that land before a crater
        idx = idx[0]
        hit = _march(scene, o, d[idx], t_a[idx], t_b[idx], step_m)
        t[idx] = np.where(np.isfinite(hit), hit, t[idx])
    t[t > max_range_m] = np.inf
    return t


def _crater_interval(
    scene: AnalyticScene, o: np.ndarray, d: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameters where each ray's ground track enters and leaves the union of the craters'
    disks of influence (t_in > t_out when it misses all)."""
    t_in, t_out = np.full(len(d), np.inf), np.full(len(d), -np.inf)
    a = d[:, 0] ** 2 + d[:, 1] ** 2 + 1e-12
    for c in scene.craters:
        reach = c.profile.radius_m * c.profile.outer_extent
        ox, oy = o[0] - c.center_xy[0], o[1] - c.center_xy[1]
        b = 2 * (ox * d[:, 0] + oy * d[:, 1])
        disc = b**2 - 4 * a * (ox**2 + oy**2 - reach**2)
        hit = disc > 0
        root = np.sqrt(np.where(hit, disc, 0.0))
        t_in = np.where(hit, np.minimum(t_in, (-b - root) / (2 * a)), t_in)
        t_out = np.where(hit, np.maximum(t_out, (-b + root) / (2 * a)), t_out)
    return np.maximum(t_in, 0.0), t_out


def _march(
    scene: AnalyticScene, o: np.ndarray, d: np.ndarray, t_a: np.ndarray, t_b: np.ndarray,
    step_m: float,
) -> np.ndarray:
    """First crossing of the terrain on [t_a, t_b] per ray (inf when none)."""
    out = np.full(len(d), np.inf)
    if not len(d):
        return out
    order = np.argsort(t_b - t_a)  # chunks of similar window length march similar steps
    for start in range(0, len(d), 4096):
        sl = order[start : start + 4096]
        n = int(np.ceil(np.max(t_b[sl] - t_a[sl]) / step_m)) + 1
        ts = t_a[sl, None] + np.minimum(np.arange(n)[None, :] * step_m, (t_b - t_a)[sl, None])
        pts = o + ts[..., None] * d[sl, None, :]
        below = pts[..., 2] <= scene.height(pts[..., 0], pts[..., 1])
        first = np.argmax(below, axis=1)
        hit = below[np.arange(len(first)), first] & (first > 0)
        lo_t = ts[np.arange(len(first)), np.maximum(first - 1, 0)]
        hi_t = ts[np.arange(len(first)), first]
        out[sl] = np.where(hit, _bisect(scene, o, d[sl], lo_t, hi_t), np.inf)
    return out


def _bisect(
    scene: AnalyticScene, o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> np.ndarray:
    """Refine bracketed crossings to ~1e-5 of the bracket."""
    for _ in range(16):
        mid = 0.5 * (lo + hi)
        p = o + mid[:, None] * d
        below = p[:, 2] <= scene.height(p[:, 0], p[:, 1])
        hi = np.where(below, mid, hi)
        lo = np.where(below, lo, mid)
    return 0.5 * (lo + hi)


def lidar_directions(
    tilt_deg: float = 23.0, vfov_deg: float = 75.0, res_deg: float = 0.333
) -> np.ndarray:
    """Beam directions of a spinning lidar whose spin axis is pitched forward by ``tilt_deg``.

    Returns:
        unit directions in the rover frame, elevation-major order.

    Shape:
        -> (n_el * n_az, 3).
    """
    el = np.radians(np.arange(-vfov_deg / 2, vfov_deg / 2 + 1e-9, res_deg))
    az = np.radians(np.arange(0.0, 360.0, res_deg))
    e, a = np.meshgrid(el, az, indexing="ij")
    v = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    t = np.radians(tilt_deg)
    rot = np.array([[np.cos(t), 0.0, np.sin(t)], [0.0, 1.0, 0.0], [-np.sin(t), 0.0, np.cos(t)]])
    return v @ rot.T


def simulate_lidar(
    scene: AnalyticScene,
    *,
    sensor_height_m: float = 1.5,
    tilt_deg: float = 23.0,
    vfov_deg: float = 75.0,
    res_deg: float = 0.333,
    max_range_m: float = 60.0,
    range_noise_m: float = 0.0,
    rng: np.random.Generator | int = 0,
) -> np.ndarray:
    """A 360 deg lidar scan of the scene (paper sensor defaults), rover frame.

    Args:
        scene: terrain.
        sensor_height_m: sensor above the origin, m.
        tilt_deg: forward pitch of the spin axis, deg.
        vfov_deg: vertical field of view, deg.
        res_deg: angular resolution in both axes, deg.
        max_range_m: farthest return kept, m.
        range_noise_m: Gaussian range noise sigma, m.
        rng: generator or seed for the noise.

    Returns:
        points (N, 3), m; rays without a return are left out.
    """
    if sensor_height_m <= 0:
        raise InputError(f"sensor_height_m: must be positive, got {sensor_height_m}")
    rng = np.random.default_rng(rng)
    origin = np.array([0.0, 0.0, sensor_height_m])
    dirs = lidar_directions(tilt_deg, vfov_deg, res_deg)
    t = raycast(scene, origin, dirs, max_range_m)
    ok = np.isfinite(t)
    t = t[ok] + rng.normal(0.0, range_noise_m, ok.sum()) if range_noise_m > 0 else t[ok]
    return origin + t[:, None] * dirs[ok]


def render_disparity(
    scene: AnalyticScene,
    *,
    width: int = 1024,
    height: int = 1024,
    fx: float = 512.0,
    cx: float | None = None,
    cy: float | None = None,
    baseline_m: float = 0.30,
    camera_height_m: float = 1.5,
    pitch_deg: float = 20.0,
    max_range_m: float = 80.0,
    noise_px: float = 0.0,
    rng: np.random.Generator | int = 0,
) -> np.ndarray:
    """Left-camera disparity d = fx B / Z of the scene (Z: optical-axis depth), 0 where no hit.

    The camera sits at (0, 0, camera_height_m), looks along rover +x pitched down by
    ``pitch_deg``; the principal point (cx, cy) defaults to the image center (W - 1) / 2.

    Returns:
        disparity, px, float32.

    Shape:
        -> (height, width).
    """
    rng = np.random.default_rng(rng)
    cx = (width - 1) / 2 if cx is None else cx
    cy = (height - 1) / 2 if cy is None else cy
    cam_dirs, axis = camera_rays(width, height, fx, cx, cy, pitch_deg)
    t = raycast(scene, np.array([0.0, 0.0, camera_height_m]), cam_dirs, max_range_m)
    z = t * (cam_dirs @ axis)
    with np.errstate(divide="ignore"):
        disp = np.where(np.isfinite(z), fx * baseline_m / z, 0.0)
    if noise_px > 0:
        disp = np.where(disp > 0, disp + rng.normal(0.0, noise_px, disp.shape), 0.0)
    return disp.reshape(height, width).astype(np.float32)


def camera_rays(
    width: int, height: int, fx: float, cx: float, cy: float, pitch_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Unit pixel rays of a pinhole camera in the rover frame, and its optical axis.

    Shape:
        -> rays (height * width, 3) row-major, axis (3,).
    """
    v, u = np.mgrid[0:height, 0:width].astype(float)
    cam = np.stack([(u - cx) / fx, (v - cy) / fx,
                    np.ones_like(u)], -1).reshape(-1, 3)
    rot = camera_to_rover_rotation(pitch_deg)
    rays = cam @ rot.T
    return rays / np.linalg.norm(rays, axis=1, keepdims=True), rot[:, 2]

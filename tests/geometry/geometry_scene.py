"""Test helper: ray-cast a single bowl crater in flat terrain, seen by a rectified stereo rig.

Independent of lunarnav_ml.synth on purpose: the geometry tests need a scene whose truth is
known in closed form. The terrain is z = h(r) around the crater center (rover frame), a parabolic
bowl inside the rim and a raised rim falling off as r^-4 outside (truncated at 3 R); texture is
multi-octave value noise on the ground plane, shading Lommel-Seeliger with cast shadows.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import scipy.ndimage

from lunarnav_ml.geometry.ellipse import Ellipse, fit_ellipse_points
from lunarnav_ml.geometry.frames import StereoRig, camera_to_rover_rotation, rover_to_camera


@dataclass
class Crater:
    """center_xy rover m; diameter m; depth (rim to floor) and rim height as fractions of D."""

    center_xy: np.ndarray
    diameter: float
    depth_ratio: float = 0.2
    rim_ratio: float = 0.045

    @property
    def radius(self) -> float:
        return self.diameter / 2.0

    @property
    def rim_height(self) -> float:
        return self.rim_ratio * self.diameter

    def height(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Terrain height and its x, y gradient at rover (x, y)."""
        dx, dy = x - self.center_xy[0], y - self.center_xy[1]
        r = np.hypot(dx, dy)
        rho = r / self.radius
        hr = self.rim_height
        d0 = self.depth_ratio * self.diameter - hr
        inner = -d0 + (hr + d0) * rho**2
        dinner = 2 * (hr + d0) * rho / self.radius
        k = 3.0**-4
        outer = hr * (np.maximum(rho, 1) ** -4 - k) / (1 - k)
        douter = -4 * hr * np.maximum(rho, 1) ** -5 / (1 - k) / self.radius
        h = np.where(rho <= 1, inner, np.where(rho < 3, outer, 0.0))
        dh = np.where(rho <= 1, dinner, np.where(rho < 3, douter, 0.0))
        rs = np.maximum(r, 1e-9)
        return h, dh * dx / rs, dh * dy / rs


def _cast(crater: Crater, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Ray parameter t of the first terrain hit (inf for sky). Lipschitz-bounded marching."""
    t_plane = np.where(dirs[:, 2] < 0, -origin[2] / np.minimum(dirs[:, 2], -1e-12), np.inf)
    # entry/exit of the vertical cylinder r = 3 R around the crater
    oc = origin[:2] - crater.center_xy
    dxy = dirs[:, :2]
    a = (dxy**2).sum(1)
    b = 2 * dxy @ oc
    c = oc @ oc - (3 * crater.radius) ** 2
    disc = b**2 - 4 * a * c
    sq = np.sqrt(np.maximum(disc, 0))
    t_in = np.maximum((-b - sq) / (2 * np.maximum(a, 1e-12)), 0)
    t_out = (-b + sq) / (2 * np.maximum(a, 1e-12))
    t = t_plane.copy()
    active = (disc > 0) & (t_out > 0) & (t_in < t_plane)
    t_top = np.where(dirs[:, 2] < 0, (origin[2] - crater.rim_height) / -np.minimum(dirs[:, 2], -1e-12), 0)
    idx = np.nonzero(active)[0]
    tt = np.maximum(t_in[idx], t_top[idx])
    lip = 2.2 * (crater.depth_ratio + crater.rim_ratio) + 0.05
    slope = lip * np.linalg.norm(dirs[idx, :2], axis=1) + np.abs(dirs[idx, 2])
    live = np.arange(len(idx))
    for _ in range(2000):
        d = dirs[idx[live]]
        p = origin + tt[live, None] * d
        gap = p[:, 2] - crater.height(p[:, 0], p[:, 1])[0]
        done = (gap < 2e-4) | (tt[live] > t_out[idx[live]])
        tt[live] += np.where(done, 0.0, np.maximum(gap / slope[live], 1e-4))
        live = live[~done]
        if len(live) == 0:
            break
    inside = tt <= t_out[idx]
    t[idx[inside]] = tt[inside]
    return t


def _texture(rng: np.random.Generator, extent: float) -> callable:
    """Albedo(x, y) in about [0.2, 0.8]: value noise at 0.08, 0.3 and 1.2 m."""
    layers = []
    for cell, amp in ((0.08, 0.18), (0.3, 0.12), (1.2, 0.08)):
        n = int(2 * extent / cell) + 2
        layers.append((cell, amp, rng.uniform(-1, 1, (n, n)).astype(np.float32)))

    def albedo(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        out = np.full(x.shape, 0.5)
        for cell, amp, grid in layers:
            coords = np.stack([(x + extent) / cell, (y + extent) / cell])
            out += amp * scipy.ndimage.map_coordinates(grid, coords, order=1, mode="reflect")
        return np.clip(out, 0.05, 1.0)

    return albedo


def _shade(crater: Crater, pts: np.ndarray, view: np.ndarray, sun: np.ndarray, albedo) -> np.ndarray:
    """Lommel-Seeliger radiance with cast shadows (checked inside the crater's influence)."""
    _, hx, hy = crater.height(pts[:, 0], pts[:, 1])
    n = np.column_stack([-hx, -hy, np.ones(len(pts))])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    mu0 = np.clip(n @ sun, 0, None)
    mu = np.clip(-(n * view).sum(1), 1e-3, None)
    radiance = albedo(pts[:, 0], pts[:, 1]) * mu0 / (mu0 + mu + 1e-9)
    # only the concave bowl casts shadows on itself
    near = np.hypot(pts[:, 0] - crater.center_xy[0], pts[:, 1] - crater.center_xy[1]) < crater.radius
    idx = np.nonzero(near & (mu0 > 0))[0]
    if len(idx):
        reach = crater.diameter / max(np.hypot(sun[0], sun[1]), 0.2)
        steps = np.linspace(0.01, reach, 60)
        p = pts[idx, None, :] + steps[None, :, None] * sun[None, None, :] + np.array([0, 0, 1e-3])
        h, _, _ = crater.height(p[..., 0], p[..., 1])
        radiance[idx[(p[..., 2] < h).any(axis=1)]] = 0.0
    return radiance


def render_view(crater, rig: StereoRig, cam_offset_x: float, size, sun, albedo, ss: int = 2):
    """Render one camera (offset along camera x, m); returns (image float, z-depth)."""
    w, h = size
    rot = camera_to_rover_rotation(rig.pitch_deg, rig.roll_deg)
    origin = np.array([0.0, 0.0, rig.height_m]) + rot @ np.array([cam_offset_x, 0.0, 0.0])
    f, cx, cy = rig.focal_px * ss, (rig.cx + 0.5) * ss - 0.5, (rig.cy + 0.5) * ss - 0.5
    vv, uu = np.mgrid[0 : h * ss, 0 : w * ss].astype(np.float64)
    q = np.stack([(uu - cx) / f, (vv - cy) / f, np.ones_like(uu)], -1).reshape(-1, 3)
    dirs = q @ rot.T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t = _cast(crater, origin, dirs)
    img = np.zeros(len(t))
    hit = np.isfinite(t)
    pts = origin + t[hit, None] * dirs[hit]
    img[hit] = _shade(crater, pts, dirs[hit], sun, albedo)
    zdepth = np.where(hit, t * (dirs @ (rot @ np.array([0, 0, 1.0]))), np.inf)
    img = cv2.resize(img.reshape(h * ss, w * ss), (w, h), interpolation=cv2.INTER_AREA)
    z = zdepth.reshape(h * ss, w * ss)[ss // 2 :: ss, ss // 2 :: ss]
    return img, z


@dataclass
class Scene:
    left: np.ndarray
    right: np.ndarray
    depth: np.ndarray
    rig: StereoRig
    crater: Crater
    center_rover: np.ndarray
    ellipse: Ellipse
    box: np.ndarray


def render_crater_scene(
    diameter: float = 5.0,
    near_rim_range: float = 8.0,
    *,
    bearing_deg: float = 0.0,
    size: tuple[int, int] = (384, 288),
    fov_deg: float = 90.0,
    pitch_deg: float = 8.0,
    sun_zenith_deg: float = 60.0,
    sun_azimuth_deg: float = 30.0,
    seed: int = 0,
    ss: int = 2,
) -> Scene:
    """Render a stereo pair of one crater; size is (width, height) px."""
    w, h = size
    f = (w / 2) / np.tan(np.radians(fov_deg) / 2)
    rig = StereoRig(f, 0.3, (w - 1) / 2, (h - 1) / 2, 1.5, pitch_deg, 0.0)
    dist = near_rim_range + diameter / 2
    b = np.radians(bearing_deg)
    crater = Crater(np.array([dist * np.cos(b), dist * np.sin(b)]), diameter)
    z, az = np.radians(sun_zenith_deg), np.radians(sun_azimuth_deg)
    sun = np.array([np.sin(z) * np.cos(az), np.sin(z) * np.sin(az), np.cos(z)])
    albedo = _texture(np.random.default_rng(seed), 3 * dist + 3 * diameter)
    left, depth = render_view(crater, rig, 0.0, size, sun, albedo, ss)
    right, _ = render_view(crater, rig, rig.baseline_m, size, sun, albedo, ss)
    scale = 255.0 / max(np.percentile(left, 99.5), 1e-6)
    to8 = lambda im: np.clip(im * scale, 0, 255).astype(np.uint8)
    center = np.array([*crater.center_xy, crater.rim_height])
    tt = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    rim = center + crater.radius * np.column_stack([np.cos(tt), np.sin(tt), np.zeros_like(tt)])
    cam = rover_to_camera(rim, rig.height_m, rig.pitch_deg)
    uv = np.column_stack([f * cam[:, 0] / cam[:, 2] + rig.cx, f * cam[:, 1] / cam[:, 2] + rig.cy])
    ell = fit_ellipse_points(uv, refine=False)
    lo, hi = uv.min(0), uv.max(0)
    box = np.array([lo[0], lo[1], hi[0] - lo[0], hi[1] - lo[1]])
    return Scene(to8(left), to8(right), depth, rig, crater, center, ell, box)

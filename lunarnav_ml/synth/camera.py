"""Pinhole stereo rig in the scene (DEM) frame: x forward, y left, z up, meters.

Camera frame is OpenCV's (x right, y down, z forward). Pixel coordinates follow OpenCV too:
pixel (i, j) has its center at u = i, v = j and the principal point of a W x H image is
((W - 1) / 2, (H - 1) / 2). COCO boxes written by :mod:`lunarnav_ml.synth.labels` are shifted
by +0.5 px so that pixel i spans [i, i + 1) as pycocotools expects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PinholeCam:
    """One pinhole camera.

    Attributes:
        position: (3,) optical center in the scene frame, m.
        rot: (3, 3) camera-to-scene rotation; columns are the camera x, y, z axes.
        fx, fy, cx, cy: intrinsics, px (OpenCV convention).
        width, height: image size, px.
    """

    position: np.ndarray
    rot: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def to_cam(self, pts: np.ndarray) -> np.ndarray:
        """Scene points (N, 3) -> camera-frame points (N, 3), m."""
        d = np.asarray(pts, np.float64) - self.position
        r = self.rot  # explicit sums: no BLAS threads for a (N, 3) x (3, 3) product
        return np.stack([d[:, 0] * r[0, k] + d[:, 1] * r[1, k] + d[:, 2] * r[2, k]
                         for k in range(3)], axis=1)

    def project(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Scene points (N, 3) -> pixel coords (N, 2) and camera z-depth (N,), m.

        Points with z <= 0 get NaN pixels.
        """
        pc = self.to_cam(pts)
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * pc[:, 0] / z + self.cx
            v = self.fy * pc[:, 1] / z + self.cy
        uv = np.stack([u, v], axis=1)
        uv[z <= 1e-6] = np.nan
        return uv, z

    def ray_dirs(self, scale: int = 1) -> np.ndarray:
        """Unit ray directions in the scene frame for every pixel center.

        Args:
            scale: render at ``scale`` x the image size (supersampling); pixel centers of the
                fine grid map to the coarse grid by u = (u_fine + 0.5) / scale - 0.5.

        Returns:
            (H * scale * W * scale, 3) float64, row-major (v slowest).
        """
        w, h = self.width * scale, self.height * scale
        u = (np.arange(w) + 0.5) / scale - 0.5
        v = (np.arange(h) + 0.5) / scale - 0.5
        uu, vv = np.meshgrid((u - self.cx) / self.fx, (v - self.cy) / self.fy)
        x, y = uu.ravel(), vv.ravel()
        inv = 1.0 / np.sqrt(x * x + y * y + 1.0)
        r = self.rot  # explicit sums: no BLAS threads for an (N, 3) x (3, 3) product
        return np.stack([(r[k, 0] * x + r[k, 1] * y + r[k, 2]) * inv for k in range(3)], axis=1)

    def pixel_angle(self) -> float:
        """Angle subtended by one pixel at the image center (the smaller side), rad."""
        return 1.0 / max(self.fx, self.fy)


def rotation_from_angles(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """Camera-to-scene rotation for a camera looking along ``yaw`` (0 = +x, 90 = +y).

    Args:
        yaw_deg: heading, counter-clockwise from the scene x axis seen from above, deg.
        pitch_deg: depression of the optical axis below horizontal, deg (positive = down).
        roll_deg: rotation about the optical axis, deg (positive turns the image clockwise).

    Returns:
        (3, 3) matrix whose columns are the camera x (right), y (down), z (forward) axes.
    """
    yw, p, r = (math.radians(a) for a in (yaw_deg, pitch_deg, roll_deg))
    fwd = np.array([math.cos(yw) * math.cos(p), math.sin(yw) * math.cos(p), -math.sin(p)])
    right = np.array([math.sin(yw), -math.cos(yw), 0.0])
    down = np.cross(fwd, right)
    right_r = right * math.cos(r) + down * math.sin(r)
    down_r = down * math.cos(r) - right * math.sin(r)
    return np.stack([right_r, down_r, fwd], axis=1)


@dataclass(frozen=True)
class StereoRig:
    """Rectified stereo pair: the right camera sits ``baseline_m`` along the left camera's x."""

    left: PinholeCam
    right: PinholeCam
    baseline_m: float
    height_m: float
    yaw_deg: float
    pitch_deg: float
    roll_deg: float
    fov_deg: float

    def camera_dict(self) -> dict[str, float]:
        """The ``camera`` entry of a COCO image (ARCHITECTURE.md)."""
        c = self.left
        return {"height_m": round(self.height_m, 6), "pitch_deg": round(self.pitch_deg, 6),
                "roll_deg": round(self.roll_deg, 6), "yaw_deg": round(self.yaw_deg, 6),
                "fov_deg": self.fov_deg, "baseline_m": self.baseline_m,
                "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy}


def make_rig(ground_xyz: np.ndarray, *, width: int, height: int, fov_deg: float,
             height_m: float, yaw_deg: float, pitch_deg: float, roll_deg: float,
             baseline_m: float, aspect: float = 1.0) -> StereoRig:
    """Build the rig with the left camera ``height_m`` above ``ground_xyz`` (3,), m.

    ``fov_deg`` is the horizontal field of view; ``aspect`` = fy / fx stretches the image
    vertically (a wide frame resized to a square one, as the Chang'e frames were).
    """
    f = (width / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    rot = rotation_from_angles(yaw_deg, pitch_deg, roll_deg)
    pos = np.asarray(ground_xyz, np.float64) + np.array([0.0, 0.0, height_m])
    kw = {"rot": rot, "fx": f, "fy": f * aspect, "cx": (width - 1) / 2.0, "cy": (height - 1) / 2.0,
          "width": width, "height": height}
    left = PinholeCam(position=pos, **kw)
    right = PinholeCam(position=pos + baseline_m * rot[:, 0], **kw)
    return StereoRig(left, right, baseline_m, height_m, yaw_deg, pitch_deg, roll_deg, fov_deg)


def sun_vector(zenith_deg: float, azimuth_deg: float, yaw_deg: float) -> np.ndarray:
    """Unit vector toward the sun in the scene frame.

    Args:
        zenith_deg: sun zenith angle, deg.
        azimuth_deg: relative to the camera heading, clockwise seen from above
            (0 = in front of the camera, 90 = to its right, 180 = behind).
        yaw_deg: camera heading, deg (see :func:`rotation_from_angles`).
    """
    z, a = math.radians(zenith_deg), math.radians(yaw_deg - azimuth_deg)
    return np.array([math.sin(z) * math.cos(a), math.sin(z) * math.sin(a), math.cos(z)])

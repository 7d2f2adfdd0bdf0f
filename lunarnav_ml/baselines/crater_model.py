"""The parametric crater model of the paper's lidar Stage 3: a simple bowl crater given by its
diameter and depth, sampled uniformly in points.

Profile (axisymmetric, heights relative to the surrounding surface, rho = r / R from the
rim-circle center):

- interior rho <= 1: z = -depth + (depth + rim) ((1 - c) rho^2 + c rho^3), the quadratic-cubic
  bowl of Fassett & Thomson 2014 (c = 0.6; c = 0 is a paraboloid),
- exterior 1 < rho <= E: uplift and ejecta falling off as rho^-k (k = 3, as in cratermaker),
  shifted and scaled to reach 0 at rho = E (E = 3),
- beyond E: 0.

Fresh simple craters have depth/diameter ~0.2 (Pike 1977); the rim rises ~0.04 D above the
surroundings (the cratermaker morphology cited in DESIGN.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lunarnav_ml.errors import InputError

RIM_RATIO = 0.04  # default rim height / diameter


@dataclass(frozen=True)
class CraterProfile:
    """Axisymmetric bowl crater.

    Attributes:
        diameter_m: rim-crest diameter D, m.
        depth_m: floor depth below the surrounding surface, m.
        rim_height_m: rim crest above the surrounding surface, m (None: 0.04 D).
        cubic_weight: c, the cubic share of the interior profile.
        flank_power: exponent k of the exterior fall-off.
        outer_extent: E, where the flank reaches the surrounding surface, in radii.
    """

    diameter_m: float
    depth_m: float
    rim_height_m: float | None = None
    cubic_weight: float = 0.6
    flank_power: float = 3.0
    outer_extent: float = 3.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.diameter_m) and self.diameter_m > 0):
            raise InputError(f"diameter_m: must be positive and finite, got {self.diameter_m}")
        if not (np.isfinite(self.depth_m) and self.depth_m >= 0):
            raise InputError(f"depth_m: must be >= 0 and finite, got {self.depth_m}")
        if self.rim_height_m is None:
            object.__setattr__(self, "rim_height_m", RIM_RATIO * self.diameter_m)
        if self.outer_extent <= 1.0:
            raise InputError(f"outer_extent: must exceed 1, got {self.outer_extent}")

    @property
    def radius_m(self) -> float:
        """Rim radius R, m."""
        return 0.5 * self.diameter_m

    def height(self, r: np.ndarray) -> np.ndarray:
        """Height above the surrounding surface at horizontal distance r from the center, m.

        Shape:
            r: any shape (m) -> same shape (m).
        """
        r = np.asarray(r, float)
        big_r, h, d = self.radius_m, float(self.rim_height_m), self.depth_m
        rho = r / big_r
        q = np.clip(rho, 0, 1)
        inside = -d + (d + h) * ((1.0 - self.cubic_weight) * q**2 + self.cubic_weight * q**3)
        tail = (1.0 / self.outer_extent) ** self.flank_power
        with np.errstate(divide="ignore"):
            flank = h * (np.maximum(rho, 1.0) ** -self.flank_power - tail) / (1.0 - tail)
        return np.where(rho <= 1.0, inside, np.where(rho <= self.outer_extent, flank, 0.0))

    def sample(self, spacing_m: float, extent: float = 1.25) -> tuple[np.ndarray, np.ndarray]:
        """Model points on a uniform square grid out to ``extent`` radii.

        Args:
            spacing_m: grid spacing, m.
            extent: outer radius of the sampled disk, in rim radii.

        Returns:
            points relative to the rim-circle center (x, y, z), m, and their radius r / R.

        Shape:
            -> points (M, 3), rho (M,).
        """
        if spacing_m <= 0:
            raise InputError(f"spacing_m: must be positive, got {spacing_m}")
        reach = extent * self.radius_m
        g = np.arange(-reach, reach + 1e-9, spacing_m)
        x, y = np.meshgrid(g, g, indexing="ij")
        r = np.hypot(x, y)
        keep = r <= reach
        pts = np.column_stack([x[keep], y[keep], self.height(r[keep])])
        return pts, r[keep] / self.radius_m


def occluded(
    profile: CraterProfile, points: np.ndarray, sensor_xy: np.ndarray, sensor_z: float,
    n_steps: int = 48,
) -> np.ndarray:
    """Which model points the sensor cannot see, by marching each line of sight over the model.

    Args:
        profile: the crater model.
        points: model points relative to the crater center, m.
        sensor_xy: sensor position relative to the crater center, m.
        sensor_z: sensor height above the surrounding surface, m.
        n_steps: samples per line of sight over the crater.

    Returns:
        True where terrain of the model hides the point from the sensor.

    Shape:
        points: (M, 3), sensor_xy: (2,) -> (M,) bool.
    """
    s = np.asarray(sensor_xy, float)
    frac = np.linspace(0.0, 1.0, n_steps + 2)[1:-1]  # strictly between sensor and point
    # only the stretch of each sight line within the crater's reach can occlude
    dist = np.hypot(points[:, 0] - s[0], points[:, 1] - s[1])
    reach = profile.outer_extent * profile.radius_m
    f0 = np.clip(1.0 - (2 * reach) / np.maximum(dist, 1e-9), 0.0, 1.0)
    f = f0[:, None] + (1.0 - f0[:, None]) * frac[None, :]
    qx = s[0] + f * (points[:, 0:1] - s[0])
    qy = s[1] + f * (points[:, 1:2] - s[1])
    line_z = sensor_z + f * (points[:, 2:3] - sensor_z)
    terrain = profile.height(np.hypot(qx, qy))
    return np.any(terrain > line_z + 1e-3, axis=1)

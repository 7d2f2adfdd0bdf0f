"""Left camera frame <-> rover frame, and the rectified stereo rig of one image.

Camera frame (OpenCV): x right, y down, z forward. Rover frame (DESIGN.md): x forward, y left,
z up, origin on the ground below the left camera, so the left camera sits at (0, 0, height_m).
A camera with zero pitch and roll looks along rover +x. ``pitch_deg`` > 0 tilts the optical
axis down (below the horizon); ``roll_deg`` > 0 is the right-handed rotation of the camera
about its optical axis (the camera's +x axis turns toward the level camera's +y: right side down).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from lunarnav_ml.errors import InputError
from lunarnav_ml.geometry._checks import as_points

# Camera axes expressed in the rover frame at zero pitch and roll (columns: x_c, y_c, z_c).
_CAM_AXES_LEVEL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_to_rover_rotation(pitch_deg: float, roll_deg: float = 0.0) -> np.ndarray:
    """Rotation taking camera-frame vectors to rover-frame vectors.

    Args:
        pitch_deg: optical axis below the horizon, degrees.
        roll_deg: right-handed rotation about the optical axis, degrees.

    Returns:
        (3, 3) rotation R with x_rover = R @ x_cam (plus the camera position).
    """
    p, r = np.radians(pitch_deg), np.radians(roll_deg)
    pitch = np.array([[np.cos(p), 0.0, np.sin(p)], [0.0, 1.0, 0.0], [-np.sin(p), 0.0, np.cos(p)]])
    roll = np.array([[np.cos(r), -np.sin(r), 0.0], [np.sin(r), np.cos(r), 0.0], [0.0, 0.0, 1.0]])
    return pitch @ _CAM_AXES_LEVEL @ roll


def camera_to_rover(
    points_cam: np.ndarray, height_m: float, pitch_deg: float, roll_deg: float = 0.0
) -> np.ndarray:
    """Left-camera-frame points to the rover frame.

    Shape:
        points_cam: (N, 3) or (3,) m -> (N, 3) m.
    """
    pts = as_points("points_cam", points_cam, 3)
    return pts @ camera_to_rover_rotation(pitch_deg, roll_deg).T + np.array([0.0, 0.0, height_m])


def rover_to_camera(
    points_rover: np.ndarray, height_m: float, pitch_deg: float, roll_deg: float = 0.0
) -> np.ndarray:
    """Rover-frame points to the left camera frame.

    Shape:
        points_rover: (N, 3) or (3,) m -> (N, 3) m.
    """
    pts = as_points("points_rover", points_rover, 3) - np.array([0.0, 0.0, height_m])
    return pts @ camera_to_rover_rotation(pitch_deg, roll_deg)


CAMERA_KEYS = ("fx", "fy", "cx", "cy", "baseline_m", "height_m", "pitch_deg", "roll_deg")
# Possible camera angles, degrees: the optical axis between straight down (pitch 90) and
# straight up (-90); any roll about it.
CAMERA_ANGLE_RANGES = {"pitch_deg": (-90.0, 90.0), "roll_deg": (-180.0, 180.0)}


def camera_values(record: Any) -> dict[str, float]:
    """The ``CAMERA_KEYS`` of a camera record (a dataset image's ``camera``) as floats,
    ``roll_deg`` 0 when absent.

    Raises:
        InputError: not an object, a key missing, or a value that is not a finite number.
    """
    if not isinstance(record, Mapping):
        raise InputError(f"camera: expected an object, got {type(record).__name__}")
    out = {}
    for key in CAMERA_KEYS:
        value = record.get(key, 0.0 if key == "roll_deg" else None)
        if value is None:
            raise InputError(f"camera: missing key {key!r} (needs {', '.join(CAMERA_KEYS)})")
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not np.isfinite(value):
            raise InputError(f"camera: {key} must be a finite number, got {value!r}")
        out[key] = float(value)
    return out


@dataclass(frozen=True)
class StereoRig:
    """A rectified stereo pair on the rover: intrinsics of the left image plus its pose.

    Attributes:
        focal_px: rectified focal length (fx = fy), px.
        baseline_m: stereo baseline, m (right camera at +baseline along camera x).
        cx, cy: principal point, px.
        height_m: left camera height above the ground, m.
        pitch_deg: optical axis below the horizon, degrees.
        roll_deg: rotation about the optical axis, degrees.
    """

    focal_px: float
    baseline_m: float
    cx: float
    cy: float
    height_m: float
    pitch_deg: float
    roll_deg: float = 0.0

    def __post_init__(self) -> None:
        vals = [self.focal_px, self.baseline_m, self.cx, self.cy, self.height_m, self.pitch_deg,
                self.roll_deg]
        if not np.all(np.isfinite(vals)):
            raise InputError(f"StereoRig: non-finite value in {vals}")
        if self.focal_px <= 0 or self.baseline_m <= 0:
            raise InputError(
                f"StereoRig: focal_px and baseline_m must be positive, got "
                f"{self.focal_px}, {self.baseline_m}"
            )

    @classmethod
    def from_camera_record(cls, record: Mapping[str, Any],
                           image_size: tuple[int, int] | None = None) -> StereoRig:
        """Build from a dataset image's ``camera`` record (ARCHITECTURE.md).

        Args:
            record: the camera record.
            image_size: (width, height) px of the image it describes; when given, the principal
                point must lie in the image (:func:`check_principal_point`).

        Raises:
            InputError: naming the field: a key is missing or not a finite number
                (:func:`camera_values`), a value is impossible (fx, fy, baseline_m or
                height_m not positive, pitch_deg or roll_deg out of range), or fx and fy
                differ (the lifter needs square pixels).
        """
        cam = camera_values(record)
        for key in ("fx", "fy", "baseline_m", "height_m"):
            if cam[key] <= 0:
                raise InputError(f"camera: {key} must be positive, got {cam[key]}")
        for key, (lo, hi) in CAMERA_ANGLE_RANGES.items():
            if not lo <= cam[key] <= hi:
                raise InputError(f"camera: {key} must lie in [{lo:g}, {hi:g}], got {cam[key]}")
        fx, fy = cam["fx"], cam["fy"]
        if abs(fx - fy) > 1e-6 * fx:
            raise InputError(f"camera: fx ({fx}) and fy ({fy}) differ; expected a rectified pair")
        rig = cls(fx, cam["baseline_m"], cam["cx"], cam["cy"], cam["height_m"],
                  cam["pitch_deg"], cam["roll_deg"])
        if image_size is not None:
            check_principal_point(rig, *image_size)
        return rig

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) camera -> rover rotation."""
        return camera_to_rover_rotation(self.pitch_deg, self.roll_deg)

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Camera-frame ray vectors q = K^-1 [u, v, 1] (z component 1).

        Shape:
            uv: (N, 2) px -> (N, 3).
        """
        pix = as_points("uv", uv, 2)
        return np.column_stack([(pix[:, 0] - self.cx) / self.focal_px,
                                (pix[:, 1] - self.cy) / self.focal_px, np.ones(len(pix))])

    def to_rover(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) m to the rover frame (N, 3) m."""
        return camera_to_rover(points_cam, self.height_m, self.pitch_deg, self.roll_deg)


def check_principal_point(rig: StereoRig, width: int, height: int) -> None:
    """Refuse a principal point outside a width x height px image (a record for another
    image size, or cx and cy swapped with the size).

    Raises:
        InputError: naming ``cx`` or ``cy``, its value and the image size.
    """
    for key, value, side, what in (("cx", rig.cx, width, "wide"), ("cy", rig.cy, height, "high")):
        if not 0.0 <= value <= side:
            raise InputError(f"camera: {key} ({value}) lies outside the image, which is {side} "
                             f"px {what} (expected 0..{side})")

"""Pinhole and CAHV (Yakimovsky-Cunningham) camera models, conversions and stereo rectification.

Conventions (DESIGN.md): pixel (u, v) with origin top-left, u right, v down; the camera frame is
OpenCV's (x right, y down, z forward), in meters. A CAHV model maps a world point P to

    u = (P - C) . H / (P - C) . A,        v = (P - C) . V / (P - C) . A

so with M = [H; V; A] (rows) the model is the 3x4 projection M [I | -C]. Writing M = K R
(RQ decomposition, K upper triangular with a positive diagonal, R a rotation) converts a CAHV
model to a pinhole K, R, t = -R C exactly, skew included; the reverse is H, V, A = rows of K R.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.linalg

from lunarnav_ml.errors import InputError
from lunarnav_ml.geometry._checks import as_array, as_points

_UNIT_TOL = 1e-4  # |A| may differ from 1 by this much (published tables round to 1e-6)


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole camera: ``x_cam = R @ x_world + t``, ``p ~ K @ x_cam``.

    Attributes:
        K: (3, 3) intrinsics, px (upper triangular, K[2, 2] = 1; K[0, 1] is the skew).
        R: (3, 3) rotation world -> camera.
        t: (3,) translation, m.
        width: image width, px.
        height: image height, px.
    """

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int

    @property
    def center(self) -> np.ndarray:
        """Camera center in the world frame, m. Shape: (3,)."""
        return -self.R.T @ self.t

    def project(self, points: np.ndarray) -> np.ndarray:
        """Project world points (N, 3) m to pixels (N, 2); see :func:`pinhole_project`."""
        return pinhole_project(self, points)

    def backproject(self, uv: np.ndarray) -> np.ndarray:
        """Unit world ray directions (N, 3) for pixels (N, 2); see :func:`pinhole_backproject`."""
        return pinhole_backproject(self, uv)


@dataclass(frozen=True)
class CAHVModel:
    """A CAHV camera model (Yakimovsky & Cunningham 1978).

    Attributes:
        c: (3,) camera center, m.
        a: (3,) unit pointing axis.
        h: (3,) horizontal vector, px.
        v: (3,) vertical vector, px.
        width: image width, px.
        height: image height, px.
    """

    c: np.ndarray
    a: np.ndarray
    h: np.ndarray
    v: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("c", "a", "h", "v"):
            object.__setattr__(self, name, as_array(name, getattr(self, name), (3,)))
        norm = float(np.linalg.norm(self.a))
        if abs(norm - 1.0) > _UNIT_TOL:
            raise InputError(f"a: CAHV pointing axis must be a unit vector, |a| = {norm:.6f}")
        if np.linalg.matrix_rank(np.stack([self.h, self.v, self.a]), tol=1e-9) < 3:
            raise InputError("h, v, a: CAHV vectors are linearly dependent")
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"width, height: must be positive, got {self.width}x{self.height}")

    def project(self, points: np.ndarray) -> np.ndarray:
        """Project world points (N, 3) m to pixels (N, 2); see :func:`cahv_project`."""
        return cahv_project(self, points)

    def backproject(self, uv: np.ndarray) -> np.ndarray:
        """Unit world ray directions (N, 3) through pixels (N, 2); see :func:`cahv_backproject`."""
        return cahv_backproject(self, uv)


def parse_cahv(text: str, width: int, height: int) -> CAHVModel:
    """Parse a CAHV model written as lines ``C = x y z``, ``A = ...``, ``H = ...``, ``V = ...``.

    Separators may be spaces, commas or both; anything else on other lines is ignored.

    Args:
        text: the model text (e.g. one column of the paper's Chang'e tables).
        width: image width, px.
        height: image height, px.

    Raises:
        InputError: a vector is missing, repeated or does not have 3 numbers.
    """
    vectors: dict[str, np.ndarray] = {}
    for line in text.splitlines():
        m = re.match(r"\s*([CAHVcahv])\s*[=:]\s*(.*)$", line)
        if not m:
            continue
        key = m.group(1).upper()
        fields = [f for f in re.split(r"[\s,]+", m.group(2).strip()) if f]
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise InputError(f"CAHV {key}: not numbers: {m.group(2)!r}") from None
        if len(values) != 3 or key in vectors:
            raise InputError(f"CAHV {key}: expected one line of 3 numbers, got {m.group(2)!r}")
        vectors[key] = np.asarray(values)
    missing = [k for k in "CAHV" if k not in vectors]
    if missing:
        raise InputError(f"CAHV text: missing vector(s) {', '.join(missing)}")
    return CAHVModel(vectors["C"], vectors["A"], vectors["H"], vectors["V"], width, height)


def cahv_project(model: CAHVModel, points: np.ndarray) -> np.ndarray:
    """Project world points with a CAHV model.

    Args:
        model: the camera.
        points: world points, m.

    Returns:
        Pixels (u, v); NaN for points on or behind the camera plane ((P - C) . A <= 0).

    Shape:
        points: (N, 3) or (3,) -> (N, 2).
    """
    pts = as_points("points", points, 3) - model.c
    w = pts @ model.a
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([pts @ model.h, pts @ model.v], axis=1) / w[:, None]
    uv[w <= 0] = np.nan
    return uv


def cahv_backproject(model: CAHVModel, uv: np.ndarray) -> np.ndarray:
    """Unit ray directions (world frame) through pixels; rays start at ``model.c``.

    The ray d satisfies (H - u A) . d = 0 and (V - v A) . d = 0, so d ∝ (V - v A) x (H - u A),
    with the sign that makes d . A > 0 (in front of the camera).

    Shape:
        uv: (N, 2) or (2,) px -> (N, 3).
    """
    pix = as_points("uv", uv, 2)
    hh = model.h[None, :] - pix[:, :1] * model.a[None, :]
    vv = model.v[None, :] - pix[:, 1:] * model.a[None, :]
    d = np.cross(vv, hh)
    d *= np.sign(d @ model.a)[:, None]
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def cahv_to_pinhole(model: CAHVModel) -> PinholeCamera:
    """Convert a CAHV model to an exactly equivalent pinhole camera (skew kept in K[0, 1])."""
    m = np.stack([model.h, model.v, model.a])  # rows: H, V, A
    k, r = scipy.linalg.rq(m)
    flip = np.diag(np.sign(np.diag(k)))  # make diag(K) positive; flip @ flip = I
    k, r = k @ flip, flip @ r
    if np.linalg.det(r) < 0:  # a mirrored CAHV model has no proper-rotation pinhole form
        raise InputError("h, v, a: CAHV model is left-handed (det < 0); cannot convert")
    k = k / k[2, 2]
    return PinholeCamera(k, r, -r @ model.c, model.width, model.height)


def pinhole_to_cahv(camera: PinholeCamera) -> CAHVModel:
    """Convert a pinhole camera to the equivalent CAHV model."""
    m = camera.K @ camera.R
    scale = np.linalg.norm(m[2])
    m = m / scale
    return CAHVModel(camera.center, m[2], m[0], m[1], camera.width, camera.height)


def pinhole_project(camera: PinholeCamera, points: np.ndarray) -> np.ndarray:
    """Project world points with a pinhole camera.

    Returns:
        Pixels (u, v); NaN for points with camera z <= 0.

    Shape:
        points: (N, 3) or (3,) m -> (N, 2) px.
    """
    pts = as_points("points", points, 3) @ camera.R.T + camera.t
    p = pts @ camera.K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = p[:, :2] / p[:, 2:]
    uv[pts[:, 2] <= 0] = np.nan
    return uv


def pinhole_backproject(camera: PinholeCamera, uv: np.ndarray) -> np.ndarray:
    """Unit ray directions in the world frame through pixels; rays start at ``camera.center``.

    Shape:
        uv: (N, 2) or (2,) px -> (N, 3).
    """
    pix = as_points("uv", uv, 2)
    rays_cam = np.linalg.solve(camera.K, np.column_stack([pix, np.ones(len(pix))]).T).T
    d = rays_cam @ camera.R  # R^T applied to each row
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def pinhole_from_fov(width: int, height: int, fov_deg: float) -> PinholeCamera:
    """An ideal camera at the world origin (world = camera frame) with a horizontal FOV.

    Args:
        width, height: image size, px.
        fov_deg: horizontal field of view, degrees (90 gives fx = width / 2).
    """
    if not 0.0 < fov_deg < 180.0:
        raise InputError(f"fov_deg: must be in (0, 180), got {fov_deg}")
    f = (width / 2.0) / np.tan(np.radians(fov_deg) / 2.0)
    k = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return PinholeCamera(k, np.eye(3), np.zeros(3), width, height)


@dataclass(frozen=True)
class StereoRectification:
    """A rectified stereo pair: both cameras share K and R; the right one sits at +baseline on x.

    Attributes:
        left, right: rectified CAHV models (world frame of the input models).
        maps_left, maps_right: (map_x, map_y) float32 (H, W) for ``cv2.remap``: rectified
            pixel -> original pixel.
        focal_px: rectified focal length, px.
        baseline_m: distance between the camera centers, m.
        cx, cy: rectified principal point, px.
        rotation: (3, 3) world -> rectified left camera.
    """

    left: CAHVModel
    right: CAHVModel
    maps_left: tuple[np.ndarray, np.ndarray]
    maps_right: tuple[np.ndarray, np.ndarray]
    focal_px: float
    baseline_m: float
    cx: float
    cy: float
    rotation: np.ndarray


def rectify_cahv_pair(
    left: CAHVModel, right: CAHVModel, *, focal_px: float | None = None
) -> StereoRectification:
    """Rectify a CAHV stereo pair so that epipolar lines are image rows.

    The rectified x axis points from the left to the right camera center, z is the mean pointing
    axis made orthogonal to x, y = z × x. Both cameras get K = [[f, 0, cx], [0, f, cy], [0, 0, 1]]
    with the principal point at the image center, so disparity u_left - u_right = f B / z.

    Args:
        left, right: the two models in one world frame (same image size).
        focal_px: rectified focal length, px (default: mean of the four input focal lengths).

    Raises:
        InputError: different image sizes, coincident centers, or non-positive focal length.
    """
    if (left.width, left.height) != (right.width, right.height):
        raise InputError(
            f"right: image size {right.width}x{right.height} differs from left "
            f"{left.width}x{left.height}"
        )
    baseline = right.c - left.c
    b = float(np.linalg.norm(baseline))
    if b < 1e-9:
        raise InputError("left.c, right.c: camera centers coincide; no stereo baseline")
    x = baseline / b
    z = left.a + right.a
    z = z - (z @ x) * x
    z /= np.linalg.norm(z)
    rot = np.stack([x, np.cross(z, x), z])
    if focal_px is None:
        ks = [cahv_to_pinhole(m).K for m in (left, right)]
        focal_px = float(np.mean([k[i, i] for k in ks for i in (0, 1)]))
    if not focal_px > 0:
        raise InputError(f"focal_px: must be positive, got {focal_px}")
    w, h = left.width, left.height
    k = np.array([[focal_px, 0, (w - 1) / 2.0], [0, focal_px, (h - 1) / 2.0], [0, 0, 1.0]])
    rect = [pinhole_to_cahv(PinholeCamera(k, rot, -rot @ m.c, w, h)) for m in (left, right)]
    maps = [_rectify_map(orig, k, rot) for orig in (left, right)]
    return StereoRectification(
        rect[0], rect[1], maps[0], maps[1], focal_px, b, k[0, 2], k[1, 2], rot
    )


def _rectify_map(
    original: CAHVModel, k: np.ndarray, rot: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """For every rectified pixel, the pixel of the original camera that sees the same ray."""
    w, h = original.width, original.height
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)])
    dirs = (rot.T @ np.linalg.solve(k, pix)).T  # (H*W, 3) world directions
    uv = cahv_project(original, original.c + dirs)
    uv = np.nan_to_num(uv, nan=-1.0)
    return (uv[:, 0].reshape(h, w).astype(np.float32), uv[:, 1].reshape(h, w).astype(np.float32))


def rectify_images(
    rect: StereoRectification, left: np.ndarray, right: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Resample a stereo pair with the maps of :func:`rectify_cahv_pair` (bilinear).

    Shape:
        left, right: (H, W) or (H, W, C) -> same shapes.
    """
    out = []
    for name, img, maps in (("left", left, rect.maps_left), ("right", right, rect.maps_right)):
        img = np.asarray(img)
        if img.shape[:2] != maps[0].shape:
            raise InputError(
                f"{name}: image shape {img.shape[:2]} differs from the model's {maps[0].shape}"
            )
        out.append(cv2.remap(img, maps[0], maps[1], cv2.INTER_LINEAR, borderValue=0))
    return out[0], out[1]


# The paper's Chang'e 3 and Chang'e 4 PCAM tables hold the same numbers (2352 x 1728 images).
_PCAM_LEFT = """
C = -0.000000 -0.000000 -0.000000
A = 0.000000 0.000000 1.000000
H = 6773.068749 0.000000 1175.500000
V = 0.000000 6791.594910 863.500000
"""
_PCAM_RIGHT = """
C = 0.269990 -0.001864 -0.001342
A = -0.033442 0.001049 0.999440
H = 6729.968393 5.565861 1401.340421
V = 32.980904 6792.495564 855.751098
"""
PCAM_SIZE = (2352, 1728)  # width, height, px


def change_pcam_pair(mission: int = 3) -> tuple[CAHVModel, CAHVModel]:
    """Left and right PCAM CAHV models of Chang'e 3 or 4 (the paper's camera tables).

    Args:
        mission: 3 or 4.
    """
    if mission not in (3, 4):
        raise InputError(f"mission: Chang'e PCAM models exist for 3 and 4, got {mission}")
    w, h = PCAM_SIZE
    return parse_cahv(_PCAM_LEFT, w, h), parse_cahv(_PCAM_RIGHT, w, h)

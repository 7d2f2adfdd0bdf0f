"""Dense stereo on rectified pairs: OpenCV StereoSGBM with subpixel output, left-right check,
invalid mask, and disparity -> depth / 3D points in the left camera frame.

Disparity convention: d = u_left - u_right > 0 (px) for the left image as reference, so
depth z = f B / d (f in px, B in m). Invalid pixels are NaN in the returned disparity.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from lunarnav_ml.errors import InputError
from lunarnav_ml.geometry._checks import as_image

_SGBM_SCALE = 16.0  # StereoSGBM returns fixed-point disparities with 4 fractional bits
# Aggregation modes. "hh" (8 paths) is the default: the 5-path single-pass mode only aggregates
# from above, which biases disparities low by ~0.2 px on ground seen at grazing angles (where
# disparity grows down the image), i.e. a range bias of a few percent.
SGBM_MODES = {
    "hh": cv2.STEREO_SGBM_MODE_HH, "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
    "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY, "hh4": cv2.STEREO_SGBM_MODE_HH4,
}


@dataclass(frozen=True)
class DisparityResult:
    """Output of :func:`compute_disparity`.

    Attributes:
        disparity: (H, W) float32 px, left image reference; NaN where invalid.
        valid: (H, W) bool, True where the disparity passed every check.
        lr_rejected: (H, W) bool, pixels SGBM matched but the left-right check rejected.

    A pixel is valid when SGBM matched it, the left-right check passed and its block has
    texture (``min_texture``).
    """

    disparity: np.ndarray
    valid: np.ndarray
    lr_rejected: np.ndarray


def compute_disparity(
    left: np.ndarray,
    right: np.ndarray,
    *,
    num_disparities: int = 64,
    min_disparity: int = 0,
    block_size: int = 5,
    uniqueness_ratio: int = 5,
    lr_max_diff_px: float = 1.0,
    speckle_window: int = 100,
    speckle_range: int = 2,
    mode: str = "hh",
    min_texture: float = 1.0,
    rows: tuple[int, int] | None = None,
    penalties: tuple[float, float] = (8.0, 32.0),
) -> DisparityResult:
    """Disparity of a rectified pair with StereoSGBM and a left-right consistency check.

    SGBM's own interpolation gives 1/16 px resolution. The right-reference disparity is SGBM run
    on the mirrored pair; a left pixel u with disparity d is kept when the right disparity at
    round(u - d) is within ``lr_max_diff_px`` of d.

    Args:
        left, right: rectified images, uint8 (or float in [0, 1]), gray or 3-channel.
        num_disparities: search range, px (rounded up to a multiple of 16).
        min_disparity: smallest disparity searched, px.
        block_size: SGBM matching block (odd, >= 1).
        uniqueness_ratio: SGBM uniqueness margin, percent.
        lr_max_diff_px: left-right tolerance, px; <= 0 disables the check.
        speckle_window: SGBM speckle filter window, px (0 disables).
        speckle_range: SGBM speckle filter disparity range, px.
        mode: SGBM aggregation, one of ``SGBM_MODES`` ("hh": 8 paths, unbiased on slanted
            ground; "sgbm": 5 paths, faster).
        min_texture: pixels whose left-image standard deviation over the matching block is
            below this (gray levels) are invalid: a textureless patch (black sky, a flat
            shadow) matches anywhere.
        rows: compute only image rows [rows[0], rows[1]) (plus a margin for the matcher);
            the other rows come back invalid. Saves time when only some rows matter.
        penalties: SGBM's smoothness penalties (P1, P2) as multiples of ``block_size``²
            (OpenCV's suggested 8 and 32; 0 <= P1 < P2). A smaller P1 follows slanted
            surfaces (ground, crater flanks) more closely.

    Returns:
        DisparityResult with NaN at invalid pixels.

    Shape:
        left, right: (H, W) or (H, W, 3), same H, W -> disparity (H, W).
    """
    l_img, r_img = as_image("left", left), as_image("right", right)
    if l_img.shape != r_img.shape:
        raise InputError(f"right: shape {r_img.shape} differs from left {l_img.shape}")
    if rows is not None:
        return _on_rows(l_img, r_img, rows, {
            "num_disparities": num_disparities, "min_disparity": min_disparity,
            "block_size": block_size,
            "uniqueness_ratio": uniqueness_ratio, "lr_max_diff_px": lr_max_diff_px,
            "speckle_window": speckle_window, "speckle_range": speckle_range, "mode": mode,
            "min_texture": min_texture, "penalties": penalties})
    if block_size < 1 or block_size % 2 == 0:
        raise InputError(f"block_size: must be odd and >= 1, got {block_size}")
    if mode not in SGBM_MODES:
        raise InputError(f"mode: expected one of {sorted(SGBM_MODES)}, got {mode!r}")
    try:
        p1, p2 = (float(v) for v in penalties)
    except (TypeError, ValueError):
        raise InputError(f"penalties: expected two numbers (P1, P2), got {penalties!r}") from None
    if not 0 <= p1 < p2:
        raise InputError(f"penalties: expected 0 <= P1 < P2, got {tuple(penalties)}")
    num = int(np.ceil(max(num_disparities, 16) / 16.0) * 16)
    sgbm = cv2.StereoSGBM_create(
        minDisparity=min_disparity, numDisparities=num, blockSize=block_size,
        P1=round(p1 * block_size**2), P2=round(p2 * block_size**2), disp12MaxDiff=-1,
        uniquenessRatio=uniqueness_ratio, speckleWindowSize=speckle_window,
        speckleRange=speckle_range, mode=SGBM_MODES[mode],
    )
    disp_l = sgbm.compute(l_img, r_img).astype(np.float32) / _SGBM_SCALE
    matched = disp_l >= min_disparity
    if lr_max_diff_px > 0:
        disp_r = sgbm.compute(r_img[:, ::-1].copy(), l_img[:, ::-1].copy())[:, ::-1]
        disp_r = disp_r.astype(np.float32) / _SGBM_SCALE
        consistent = _left_right_consistent(disp_l, disp_r, matched, min_disparity, lr_max_diff_px)
    else:
        consistent = matched
    valid = consistent & (_local_std(l_img, block_size) >= min_texture)
    disparity = np.where(valid, disp_l, np.nan).astype(np.float32)
    return DisparityResult(disparity, valid, matched & ~consistent)


def _on_rows(left: np.ndarray, right: np.ndarray, rows: tuple[int, int],
             kwargs: dict) -> DisparityResult:
    """compute_disparity on a band of rows (with a margin), pasted into full-size outputs."""
    h = left.shape[0]
    v0, v1 = max(int(rows[0]), 0), min(int(rows[1]), h)
    if v1 <= v0:
        raise InputError(f"rows: empty row range {rows} for image height {h}")
    pad = 2 * kwargs["block_size"] + 8
    a, b = max(v0 - pad, 0), min(v1 + pad, h)
    part = compute_disparity(left[a:b], right[a:b], **kwargs)
    out = [np.full(left.shape, np.nan, np.float32), np.zeros(left.shape, bool),
           np.zeros(left.shape, bool)]
    for full, piece in zip(out, (part.disparity, part.valid, part.lr_rejected)):
        full[v0:v1] = piece[v0 - a : v1 - a]
    return DisparityResult(*out)


def _local_std(img: np.ndarray, size: int) -> np.ndarray:
    """Standard deviation of ``img`` over a size x size box around each pixel."""
    f = img.astype(np.float32)
    mean = cv2.blur(f, (size, size))
    sq = cv2.blur(f * f, (size, size))
    return np.sqrt(np.maximum(sq - mean * mean, 0.0))


def _left_right_consistent(
    disp_l: np.ndarray, disp_r: np.ndarray, matched: np.ndarray, min_disp: int, tol: float
) -> np.ndarray:
    """True where the right image's disparity at u - d agrees with the left's d."""
    h, w = disp_l.shape
    cols = np.arange(w)[None, :]
    u_r = np.rint(cols - disp_l).astype(np.int64)
    inside = matched & (u_r >= 0) & (u_r < w)
    rows = np.broadcast_to(np.arange(h)[:, None], (h, w))
    d_r = disp_r[rows, np.clip(u_r, 0, w - 1)]
    return inside & (d_r >= min_disp) & (np.abs(d_r - disp_l) <= tol)


def disparity_to_depth(disparity: np.ndarray, focal_px: float, baseline_m: float) -> np.ndarray:
    """Depth z = f B / d along the left camera's optical axis.

    Args:
        disparity: px; NaN or <= 0 means invalid.
        focal_px: rectified focal length, px.
        baseline_m: stereo baseline, m.

    Returns:
        z-depth, m; NaN where the disparity is invalid.

    Shape:
        disparity: (H, W) (or any shape) -> same shape, float32.
    """
    d = np.asarray(disparity, dtype=np.float32)
    if not (focal_px > 0 and baseline_m > 0):
        raise InputError(f"focal_px, baseline_m: must be positive, got {focal_px}, {baseline_m}")
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.float32(focal_px * baseline_m) / d
    z[~(d > 0)] = np.nan
    return z


def disparity_to_points(
    disparity: np.ndarray, focal_px: float, baseline_m: float, cx: float, cy: float
) -> np.ndarray:
    """3D points in the left (rectified) camera frame, x right, y down, z forward, m.

    Shape:
        disparity: (H, W) px -> (H, W, 3) m; NaN where the disparity is invalid.
    """
    d = np.asarray(disparity)
    if d.ndim != 2:
        raise InputError(f"disparity: expected shape (H, W), got {tuple(d.shape)}")
    z = disparity_to_depth(d, focal_px, baseline_m)
    v, u = np.mgrid[0 : d.shape[0], 0 : d.shape[1]].astype(np.float32)
    return np.stack([(u - cx) * z / focal_px, (v - cy) * z / focal_px, z], axis=-1)


@dataclass
class SGBMStereo:
    """Thin callable around :func:`compute_disparity` holding its settings."""

    num_disparities: int = 64
    min_disparity: int = 0
    block_size: int = 5
    uniqueness_ratio: int = 5
    lr_max_diff_px: float = 1.0
    mode: str = "hh"
    penalties: tuple[float, float] = (8.0, 32.0)

    @classmethod
    def for_width(cls, width: int) -> SGBMStereo:
        """Settings sized to the image: 128 disparities at 1024 px (at the rover's 0.3 m
        baseline and 90 deg field of view, ground about 1.2 m ahead), 16 per 128 px, at least 32.
        """
        return cls(num_disparities=int(max(32, 16 * round(width / 128))))

    def __call__(self, left: np.ndarray, right: np.ndarray,
                 rows: tuple[int, int] | None = None) -> DisparityResult:
        """Disparity of a rectified pair; see :func:`compute_disparity`."""
        return compute_disparity(
            left, right, num_disparities=self.num_disparities, min_disparity=self.min_disparity,
            block_size=self.block_size, uniqueness_ratio=self.uniqueness_ratio,
            lr_max_diff_px=self.lr_max_diff_px, mode=self.mode, rows=rows,
            penalties=self.penalties,
        )


def match_strips(
    left: np.ndarray, right: np.ndarray, cols: np.ndarray, rows: np.ndarray, d0: np.ndarray,
    *, half_width: int = 7, half_height: int = 0, search_px: int = 3, min_score: float = 0.6,
) -> np.ndarray:
    """Disparity at chosen pixels from a short window matched along the epipolar line.

    Each left-image window (``2 half_height + 1`` rows by ``2 half_width + 1`` columns, centred
    on (col, row)) is matched by zero-mean normalized cross-correlation
    (``cv2.matchTemplate``, TM_CCOEFF_NORMED) against the right image's same rows, at
    disparities within ``search_px`` of ``d0``; the peak is refined to subpixel by a parabola
    through it and its neighbours. A window of one row does not reach across a horizontal
    depth edge just above or below it, where a block matcher's square window and smoothness
    terms mix both sides (the near rim of a crater seen from a rover).

    Args:
        left, right: rectified gray images (H, W), uint8 or float.
        cols, rows: (N,) integer pixel of each window's centre, left image.
        d0: (N,) prior disparity each search is centred on, px; NaN skips the pixel.
        half_width, half_height: window half sizes, px.
        search_px: disparities searched each side of round(d0), px.
        min_score: correlation peaks below this give NaN.

    Returns:
        (N,) float64 disparity, px; NaN where the window leaves the image, the peak is weak
        or lies at the end of the search range, or the window has no texture.

    Raises:
        InputError: the images are not gray and of one shape, or the arrays' lengths differ.
    """
    lf, rf = np.asarray(left), np.asarray(right)  # windows become float32 one at a time
    if lf.ndim != 2 or rf.shape != lf.shape:
        raise InputError(f"left, right: expected two gray images of one shape (H, W), got "
                         f"{lf.shape} and {rf.shape}")
    cols, rows, d0 = (np.asarray(a).reshape(-1) for a in (cols, rows, d0))
    if not len(cols) == len(rows) == len(d0):
        raise InputError(f"cols, rows, d0: expected one length, got {len(cols)}, {len(rows)}, "
                         f"{len(d0)}")
    h, w = lf.shape
    out = np.full(len(cols), np.nan)
    for i, (u, v, d) in enumerate(zip(cols, rows, d0)):
        if not np.isfinite(d):
            continue
        base = round(float(d))
        r0, r1 = int(v) - half_height, int(v) + half_height + 1
        x0 = int(u) - base - search_px - half_width
        x1 = int(u) - base + search_px + half_width + 1
        if r0 < 0 or r1 > h or x0 < 0 or x1 > w or int(u) + half_width + 1 > w:
            continue
        tmpl = lf[r0:r1, int(u) - half_width : int(u) + half_width + 1].astype(np.float32)
        if float(cv2.meanStdDev(tmpl)[1][0, 0]) < 1e-3:  # no texture (np.std, 10x slower)
            continue
        strip = rf[r0:r1, x0:x1].astype(np.float32)
        score = cv2.matchTemplate(strip, tmpl, cv2.TM_CCOEFF_NORMED)[0]
        k = int(np.argmax(score))
        if score[k] < min_score or k == 0 or k == len(score) - 1:
            continue
        a, b, c = score[k - 1], score[k], score[k + 1]
        denom = a - 2 * b + c
        sub = 0.5 * (a - c) / denom if denom < 0 else 0.0
        out[i] = base + search_px - (k + sub)
    return out

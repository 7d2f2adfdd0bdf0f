"""The paper's stereo crater detector (LunarNav 2022, "Stereo Image-based Approach").

1. Fit the disparity map with a plane A x + B y + C d + D = 0 (robust least squares).
2. Residual map r = d - plane: crater interiors seen beyond a near rim are farther than the
   plane (r < 0); the far interior wall rises smoothly back to r ~ 0 at the far rim.
3. In each column, segments that could be a far wall: runs of r rising going up the image,
   cut at the far crest where a two-line fit finds the rise slowing (the ground behind).
4. Connected components of those segments; small regions are deleted as noise.
5. Rim candidates: range discontinuities (a disparity drop going up a column, across small
   invalid gaps).
6. Pair each far-wall region with the rim right below it; weak pairs are dropped.
7. Fit: the near rim (lower side of the jump) and the far rim (the crest where r stops rising)
   are lifted to 3D, each with the nearest disparity a few rows around it (at an occluding
   crest the matcher may give the pixel the farther surface's), and a circle is fitted in the
   ground plane: center and diameter.

Disparity convention (``lunarnav_ml.geometry.stereo``): d = u_left - u_right > 0, px; invalid
pixels are NaN or <= 0. Results are in the rover frame (x forward, y left, z up, origin on the
ground below the left camera).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from lunarnav_ml.errors import InputError
from lunarnav_ml.geometry.frames import camera_to_rover


@dataclass(frozen=True)
class StereoConfig:
    """Settings of :func:`detect_craters_stereo` (pixel values at 1024 x 1024; the region and
    segment sizes scale with the image height).

    Attributes:
        min_disparity_px: pixels with less disparity (sky, horizon) are ignored.
        plane_stride: sub-sampling of the plane fit, px.
        plane_trim: residuals beyond this many robust sigmas leave the plane fit.
        median_px: median filter applied to the disparity first (3 or 5; 0 disables), px.
        slope_rows: half-width of the central difference that measures the residual's rise.
        min_rise_px, min_rise_frac: a far-wall segment rises by more than
            max(px, frac * plane disparity) from bottom to top.
        min_segment_rows: shortest far-wall segment in a column (at 1024 rows).
        crest_slope_ratio: a rising run whose upper part rises at less than this fraction of
            its lower part's rate is cut at the break (the far crest, where the terrain behind
            the crater takes over); 0 keeps whole runs.
        min_region_px: smallest far-wall region kept (at 1024 rows).
        jump_px, jump_frac: a rim discontinuity drops by more than max(px, frac * d).
        max_gap_rows: invalid rows bridged when looking for a discontinuity.
        pair_rows: a far-wall column pairs with a rim found within this many rows below it.
        min_pair_frac: fraction of a region's columns that must pair with the rim.
        rim_window_rows: a rim pixel whose disparity is a jump (jump_px, jump_frac) below the
            largest within this many rows of it (at 1024 rows) is lifted with that one: at an
            occluding crest the matcher may give it the farther surface's disparity.
        min_diameter_m, max_diameter_m: fitted diameters kept, m.
    """

    min_disparity_px: float = 1.0
    plane_stride: int = 4
    plane_trim: float = 2.5
    median_px: int = 5
    slope_rows: int = 2
    min_rise_px: float = 0.4
    min_rise_frac: float = 0.04
    min_segment_rows: int = 6
    crest_slope_ratio: float = 0.85
    min_region_px: int = 120
    jump_px: float = 0.6
    jump_frac: float = 0.06
    max_gap_rows: int = 12
    pair_rows: int = 16
    min_pair_frac: float = 0.4
    rim_window_rows: int = 2
    min_diameter_m: float = 2.0
    max_diameter_m: float = 40.0


@dataclass(frozen=True)
class StereoRigParams:
    """Rectified left camera on the rover.

    Attributes:
        fx: focal length, px (square pixels).  cx, cy: principal point, px.
        baseline_m: stereo baseline, m.  height_m: camera above the ground, m.
        pitch_deg: optical axis below the horizon, deg.
        roll_deg: rotation about the optical axis, deg (``lunarnav_ml.geometry.frames``).
    """

    fx: float
    cx: float
    cy: float
    baseline_m: float
    height_m: float
    pitch_deg: float
    roll_deg: float = 0.0

    @classmethod
    def from_record(cls, camera: Mapping[str, Any]) -> StereoRigParams:
        """From a dataset image's ``camera`` record (ARCHITECTURE.md)."""
        keys = ("fx", "cx", "cy", "baseline_m", "height_m", "pitch_deg")
        missing = [k for k in keys if k not in camera]
        if missing:
            raise InputError(f"camera: missing key(s) {', '.join(missing)}")
        vals = [float(camera[k]) for k in keys] + [float(camera.get("roll_deg", 0.0))]
        if not np.all(np.isfinite(vals)) or vals[0] <= 0 or vals[3] <= 0:
            raise InputError(f"camera: fx and baseline_m must be positive and finite, got {vals}")
        return cls(*vals)


@dataclass
class StereoDetection:
    """A crater found in one disparity map.

    Attributes:
        center_m: (3,) rim-circle center, rover frame, m.
        diameter_m: fitted diameter, m.
        score: fraction of the far-wall region's columns paired with the rim, 0-1.
        near_rim_range_m: horizontal distance from the camera's ground point to the nearest
            fitted rim point, m.
        bbox_px: (4,) [x, y, w, h] of the paired rim and far-wall region, px.
        n_near, n_far: rim points used in the circle fit.
    """

    center_m: np.ndarray
    diameter_m: float
    score: float
    near_rim_range_m: float
    bbox_px: np.ndarray
    n_near: int
    n_far: int


def detect_craters_stereo(
    disparity: np.ndarray,
    camera: StereoRigParams | Mapping[str, Any],
    *,
    config: StereoConfig | None = None,
) -> list[StereoDetection]:
    """Detect craters in a left-reference disparity map.

    Args:
        disparity: px, NaN or <= 0 where invalid.
        camera: rig parameters, or a dataset ``camera`` record.
        config: settings.

    Returns:
        detections, highest score first; empty for an empty, all-invalid or flat map.

    Raises:
        InputError: ``disparity`` not 2-D, or a bad ``camera``.

    Shape:
        disparity: (H, W).
    """
    cfg = config or StereoConfig()
    rig = camera if isinstance(camera, StereoRigParams) else StereoRigParams.from_record(camera)
    disp = _check_disparity(disparity)
    valid = np.isfinite(disp) & (disp >= cfg.min_disparity_px)
    if valid.sum() < 100:
        return []
    raw = np.where(valid, disp, np.nan)  # lifted to 3D: the median would bias rim ranges
    disp = median_filter(disp, valid, cfg.median_px)
    valid = np.isfinite(disp)
    plane = fit_disparity_plane(disp, valid, stride=cfg.plane_stride, trim=cfg.plane_trim)
    if plane is None:
        return []
    plane_d = plane_disparity(plane, disp.shape)
    resid = np.where(valid, disp - plane_d, np.nan)
    scale = disp.shape[0] / 1024.0
    walls = far_wall_mask(resid, plane_d, cfg, scale)
    labels = wall_regions(walls, max(int(cfg.min_region_px * scale**2), 8))
    rims = rim_discontinuities(np.where(valid, disp, np.nan), cfg)
    dets = []
    for lab in range(1, int(labels.max()) + 1):
        det = _pair_and_fit(lab, labels, rims, resid, raw, rig, cfg, scale)
        if det is not None:
            dets.append(det)
    return sorted(dets, key=lambda d: -d.score)


def _check_disparity(disparity: object) -> np.ndarray:
    try:
        d = np.asarray(disparity, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"disparity: cannot convert to a float array ({exc})") from None
    if d.ndim != 2 or min(d.shape) < 8:
        raise InputError(f"disparity: expected shape (H, W) with H, W >= 8, got {d.shape}")
    return d


def fit_disparity_plane(
    disp: np.ndarray, valid: np.ndarray, *, stride: int = 4, trim: float = 2.5, iters: int = 4
) -> np.ndarray | None:
    """Robust plane A x + B y + C d + D = 0 through the disparity map (x column, y row).

    Solved as d = a x + b y + c (C = -1) by least squares, re-fitted on the pixels within
    ``trim`` robust sigmas (1.4826 MAD) of the previous fit.

    Returns:
        (A, B, C, D) with C = -1, or None with fewer than 20 valid samples.

    Shape:
        disp, valid: (H, W) -> (4,).
    """
    rows, cols = np.nonzero((valid & np.isfinite(disp))[::stride, ::stride])
    rows, cols = rows * stride, cols * stride
    d = disp[rows, cols]
    if len(d) < 20:
        return None
    design = np.column_stack([cols, rows, np.ones(len(d))]).astype(np.float64)
    keep = np.ones(len(d), bool)
    for _ in range(iters):
        coef, *_ = np.linalg.lstsq(design[keep], d[keep], rcond=None)
        res = d - design @ coef
        sigma = 1.4826 * np.median(np.abs(res[keep] - np.median(res[keep]))) + 1e-6
        keep = np.abs(res) <= trim * sigma
        if keep.sum() < 20:
            return None
    return np.array([coef[0], coef[1], -1.0, coef[2]])


def plane_disparity(plane: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Disparity of the plane at every pixel, px.

    Shape:
        plane: (4,) -> (H, W).
    """
    a, b, c, d = plane
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
    return -(a * cols + b * rows + d) / c


def far_wall_mask(
    resid: np.ndarray, plane_d: np.ndarray, cfg: StereoConfig, scale: float = 1.0
) -> np.ndarray:
    """Per-column segments where the residual rises smoothly going up the image (the far
    interior wall), long enough and rising by enough.

    The rise is the central difference r(v - k) - r(v + k) with k = ``slope_rows`` (scaled),
    which bridges pixel noise; a segment must be ``min_segment_rows`` long and rise by
    max(min_rise_px, min_rise_frac * plane disparity) from its bottom to its top.

    Returns:
        (H, W) bool, pixels of accepted segments.

    Shape:
        resid, plane_d: (H, W) px (NaN invalid) -> (H, W).
    """
    k = max(round(cfg.slope_rows * scale), 1)
    rising = np.zeros(resid.shape, bool)
    with np.errstate(invalid="ignore"):
        rising[k:-k] = resid[: -2 * k] - resid[2 * k :] > 0  # NaN compares False
    starts, ends, cols = column_runs(rising)
    min_len = max(round(cfg.min_segment_rows * scale), 3)
    keep = ends - starts >= min_len
    starts, ends, cols = starts[keep], ends[keep], cols[keep]
    if cfg.crest_slope_ratio > 0:
        starts = _cut_at_crests(resid, starts, ends, cols, cfg.crest_slope_ratio, min_len)
    rise = resid[starts, cols] - resid[ends - 1, cols]
    need = np.maximum(cfg.min_rise_px, cfg.min_rise_frac * np.abs(plane_d[ends - 1, cols]))
    ok = rise >= need
    mask = np.zeros_like(rising)
    for s, e, c in zip(starts[ok], ends[ok], cols[ok]):
        mask[s:e, c] = True
    return mask


def _cut_at_crests(resid: np.ndarray, starts: np.ndarray, ends: np.ndarray, cols: np.ndarray,
                   ratio: float, min_len: int) -> np.ndarray:
    """New start rows of the runs after :func:`split_at_crest` (runs of one length at a time;
    a cut run keeps at least ``min_len`` rows)."""
    starts = starts.copy()
    lengths = ends - starts
    for n in np.unique(lengths):
        idx = np.nonzero(lengths == n)[0]
        rows = ends[idx, None] - 1 - np.arange(n)[None, :]  # bottom of the run upward
        drop = split_at_crest(resid[rows, cols[idx, None]], ratio)
        starts[idx] += np.minimum(drop, n - min_len)
    return starts


def split_at_crest(profiles: np.ndarray, ratio: float, min_piece: int = 3) -> np.ndarray:
    """Where rising profiles stop being the far wall: the best two-line fit's break, when the
    upper line rises at less than ``ratio`` times the lower one.

    The paper's far-wall cue is a roughly linear rise of the residual going up the column; on
    sloping ground the rise can run on past the far crest at a gentler rate, and the crest
    then sits at the kink between the two lines.

    Args:
        profiles: residuals from the bottom of each run upward (px, finite), one run per row.
        ratio: slope ratio below which a run is cut.
        min_piece: fewest samples on each side of the break.

    Returns:
        samples to drop from the top of each run (0: keep it whole).

    Shape:
        profiles: (K, n) -> (K,) int.
    """
    y = np.asarray(profiles, np.float64)
    k, n = y.shape
    if n < 2 * min_piece or k == 0:
        return np.zeros(k, int)
    x = np.broadcast_to(np.arange(n, dtype=np.float64), y.shape)
    sums = [np.concatenate([np.zeros((k, 1)), np.cumsum(v, axis=1)], axis=1)
            for v in (np.ones_like(y), x, x * x, y, x * y, y * y)]
    breaks = np.arange(min_piece, n - min_piece + 1)

    def fit(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Slopes and squared errors of the least-squares lines through samples lo..hi-1."""
        cnt, sx, sxx, sy, sxy, syy = (c[:, hi] - c[:, lo] for c in sums)
        cov = sxy - sx * sy / cnt
        slope = cov / np.maximum(sxx - sx * sx / cnt, 1e-12)
        return slope, np.maximum(syy - sy * sy / cnt - slope * cov, 0.0)

    low_slope, low_err = fit(np.zeros_like(breaks), breaks)
    high_slope, high_err = fit(breaks, np.full_like(breaks, n))
    best = np.argmin(low_err + high_err, axis=1)
    rows = np.arange(k)
    s_low, s_high = low_slope[rows, best], high_slope[rows, best]
    cut = (s_low > 0) & (s_high < ratio * s_low) & np.all(np.isfinite(y), axis=1)
    return np.where(cut, n - breaks[best], 0)


def column_runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertical runs of True in every column.

    Returns:
        start rows (inclusive), end rows (exclusive), columns.

    Shape:
        mask: (H, W) -> three (K,) int arrays.
    """
    padded = np.zeros((mask.shape[0] + 2, mask.shape[1]), np.int8)
    padded[1:-1] = mask
    diff = np.diff(padded, axis=0)  # +1 at starts, -1 after ends
    start_c, start_r = np.nonzero(diff.T == 1)  # column-major so starts and ends line up
    _, end_r = np.nonzero(diff.T == -1)
    return start_r, end_r, start_c


def wall_regions(mask: np.ndarray, min_area: int) -> np.ndarray:
    """8-connected components of the far-wall mask with regions under ``min_area`` px deleted.

    Returns:
        (H, W) int32 labels 1..K (0 background), relabelled consecutively.
    """
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = np.zeros(n, np.int32)
    big = np.nonzero(stats[1:, cv2.CC_STAT_AREA] >= min_area)[0] + 1
    keep[big] = np.arange(1, len(big) + 1)
    return keep[labels]


def jump_threshold(near_disparity: np.ndarray, cfg: StereoConfig) -> np.ndarray:
    """Smallest disparity drop from a nearer surface that counts as a range discontinuity:
    max(jump_px, jump_frac * the nearer disparity), px."""
    return np.maximum(cfg.jump_px, cfg.jump_frac * near_disparity)


def rim_discontinuities(disp: np.ndarray, cfg: StereoConfig) -> np.ndarray:
    """Near-side pixels of range discontinuities: going up a column, the disparity drops by
    more than max(jump_px, jump_frac * d), possibly across up to ``max_gap_rows`` invalid rows.

    Returns:
        (H, W) bool, True on the lower (nearer) pixel of each drop.

    Shape:
        disp: (H, W) px, NaN invalid.
    """
    h, w = disp.shape
    valid = np.isfinite(disp)
    rows = np.broadcast_to(np.arange(h)[:, None], (h, w))
    at_or_below = np.minimum.accumulate(np.where(valid, rows, h)[::-1], axis=0)[::-1]
    below = np.vstack([at_or_below[1:], np.full((1, w), h)])  # nearest valid row > v
    near_gap = valid & (below < h) & (below - rows <= cfg.max_gap_rows + 1)
    cols = np.broadcast_to(np.arange(w)[None, :], (h, w))
    d_below = np.where(near_gap, disp[np.minimum(below, h - 1), cols], np.nan)
    drop = d_below - disp
    is_jump = near_gap & (drop > jump_threshold(d_below, cfg))
    rim = np.zeros((h, w), bool)
    rim[below[is_jump], cols[is_jump]] = True
    return rim


def _pair_and_fit(
    label: int, labels: np.ndarray, rims: np.ndarray, resid: np.ndarray, disp: np.ndarray,
    rig: StereoRigParams, cfg: StereoConfig, scale: float = 1.0,
) -> StereoDetection | None:
    """Pair far-wall region ``label`` with the rim below it and fit the crater circle."""
    rr, cc = np.nonzero(labels == label)
    cols = np.unique(cc)
    bottom = np.full(labels.shape[1], -1)
    top = np.full(labels.shape[1], labels.shape[0])
    np.maximum.at(bottom, cc, rr)
    np.minimum.at(top, cc, rr)
    near_uv, far_uv = [], []
    for c in cols:
        hit = np.nonzero(rims[bottom[c] + 1 : bottom[c] + 1 + cfg.pair_rows, c])[0]
        if len(hit):
            near_uv.append((c, bottom[c] + 1 + hit[0]))
            far_uv.append((c, _far_crest(resid[:, c], rims[:, c], top[c], cfg.slope_rows + 2)))
    score = len(near_uv) / max(len(cols), 1)
    if score < cfg.min_pair_frac or len(near_uv) < 3:
        return None
    window = round(cfg.rim_window_rows * scale)
    near = pixels_to_rover(np.asarray(near_uv, float), disp, rig, window, cfg)
    far = pixels_to_rover(np.asarray(far_uv, float), disp, rig, window, cfg)
    pts = np.vstack([near, far])
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) < 5:
        return None
    circle = fit_circle(pts[:, :2])
    if circle is None:
        return None
    center_xy, radius = circle
    if not cfg.min_diameter_m <= 2 * radius <= cfg.max_diameter_m:
        return None
    if np.hypot(*center_xy) <= np.median(np.hypot(near[:, 0], near[:, 1])):
        return None  # the "near rim" must lie in front of the center
    box_u = np.concatenate([cc, [u for u, _ in near_uv]])
    box_v = np.concatenate([rr, [v for _, v in near_uv]])
    bbox = np.array([box_u.min(), box_v.min(), np.ptp(box_u) + 1, np.ptp(box_v) + 1], float)
    center = np.array([center_xy[0], center_xy[1], float(np.median(pts[:, 2]))])
    rim_range = max(float(np.hypot(*center_xy)) - radius, 0.0)
    return StereoDetection(center, 2 * radius, score, rim_range, bbox, len(near), len(far))


def _far_crest(column_resid: np.ndarray, column_rims: np.ndarray, top: int, reach: int) -> int:
    """Row of the far rim crest at the top of a far-wall segment (within ``reach`` rows): the
    range discontinuity the raised rim casts on the ground behind it when there is one (the
    lower pixel of that drop), else the residual's maximum."""
    lo, hi = max(top - reach, 0), min(top + reach + 1, len(column_resid))
    jumps = np.nonzero(column_rims[lo:hi])[0]
    if len(jumps):
        return lo + int(jumps[np.argmin(np.abs(lo + jumps - top))])
    seg = column_resid[lo:hi]
    if not np.isfinite(seg).any():
        return top
    return lo + int(np.nanargmax(seg))


def median_filter(disp: np.ndarray, valid: np.ndarray, ksize: int) -> np.ndarray:
    """Edge-preserving median of the valid disparities (invalid pixels stay NaN).

    Shape:
        disp, valid: (H, W) -> (H, W) float64.
    """
    if ksize <= 1:
        return np.where(valid, disp, np.nan)
    if ksize not in (3, 5):
        raise InputError(f"median_px: must be 0, 1, 3 or 5, got {ksize}")
    filled = np.where(valid, disp, 0.0).astype(np.float32)
    out = cv2.medianBlur(filled, ksize).astype(np.float64)
    return np.where(valid & (out > 0), out, np.nan)


def pixels_to_rover(uv: np.ndarray, disp: np.ndarray, rig: StereoRigParams,
                    window_rows: int = 0, config: StereoConfig | None = None) -> np.ndarray:
    """Lift pixels with their disparity to the rover frame (NaN where the disparity is
    invalid).

    With ``window_rows`` > 0 a pixel on the far side of a range discontinuity is moved to its
    near side: when the largest valid disparity within that many rows of it in its column
    exceeds its own by a jump (:func:`jump_threshold` with ``config``, default settings), or
    its own is invalid, it takes that largest one. A rim pixel whose disparity is the farther
    surface's (matching at an occluding crest) then lifts to the crest; one on the crest keeps
    its own.

    Shape:
        uv: (N, 2) px (column, row) -> (N, 3) m.
    """
    u, v = uv[:, 0], uv[:, 1]
    d = disp[v.astype(int), u.astype(int)]
    if window_rows > 0:
        rows = v.astype(int)[:, None] + np.arange(-window_rows, window_rows + 1)[None, :]
        around = disp[np.clip(rows, 0, disp.shape[0] - 1), u.astype(int)[:, None]]
        best = np.max(np.where(np.isfinite(around), around, -np.inf), axis=1)
        with np.errstate(invalid="ignore"):
            far_side = ~np.isfinite(d) | (best - d > jump_threshold(best, config or StereoConfig()))
        d = np.where(far_side & np.isfinite(best), best, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(d > 0, rig.fx * rig.baseline_m / d, np.nan)
    cam = np.column_stack([(u - rig.cx) * z / rig.fx, (v - rig.cy) * z / rig.fx, z])
    out = np.full(cam.shape, np.nan)
    ok = np.isfinite(z)
    if ok.any():
        out[ok] = camera_to_rover(cam[ok], rig.height_m, rig.pitch_deg, rig.roll_deg)
    return out


def fit_circle(xy: np.ndarray, iters: int = 2, trim: float = 3.0) -> tuple[np.ndarray, float] | None:
    """Algebraic (Kasa) circle fit, re-fitted without points beyond ``trim`` robust sigmas.

    Returns:
        center (2,) and radius, or None when degenerate.

    Shape:
        xy: (N, 2) m.
    """
    keep = np.ones(len(xy), bool)
    center, radius = None, 0.0
    for _ in range(iters + 1):
        p = xy[keep]
        if len(p) < 3:
            return None
        design = np.column_stack([2 * p, np.ones(len(p))])
        sol, *_ = np.linalg.lstsq(design, (p**2).sum(axis=1), rcond=None)
        center = sol[:2]
        r2 = sol[2] + center @ center
        if not np.isfinite(r2) or r2 <= 0:
            return None
        radius = float(np.sqrt(r2))
        res = np.linalg.norm(xy - center, axis=1) - radius
        sigma = 1.4826 * np.median(np.abs(res[keep])) + 1e-6
        keep = np.abs(res) <= trim * sigma
    return center, radius

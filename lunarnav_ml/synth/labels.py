"""COCO labels: craters from their projected 3D rim circle, rocks and artifacts from pixels.

Box coordinates are COCO's (pixel i spans [i, i + 1)), i.e. OpenCV pixel coordinates + 0.5.
Ellipses are in OpenCV pixel coordinates ([cx, cy, a, b, angle_deg], a and b semi-axes, angle
as ``cv2.fitEllipse``). Ignore rules: DESIGN.md, plus the extensions in :class:`LabelConfig`
(crater diameter below ``crater_min_diameter_m``; rim-to-floor depth below ``min_depth_m``;
less than ``min_visible_rim_fraction`` of the in-image rim visible in the depth buffer; less
than ``min_surviving_bowl_fraction`` of the bowl's relief left by later craters).
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

from lunarnav_ml.synth import raycast
from lunarnav_ml.synth import terrain as T
from lunarnav_ml.synth.camera import PinholeCam
from lunarnav_ml.synth.config import LabelConfig
from lunarnav_ml.synth.craters import Crater, surviving_bowl
from lunarnav_ml.synth.objects import SceneObject

N_RIM = 180  # rim samples per crater (polygon error 1.5e-4 radii)


def crater_annotations(craters: list[Crater], ter: T.Terrain, cam: PinholeCam,
                       depth: np.ndarray, rules: LabelConfig, max_range_m: float
                       ) -> list[dict[str, Any]]:
    """Annotations (no ids) for every crater copy (periodic tiles) that projects into view.

    Args:
        depth: (H, W) z-depth of the left view, m (for rim visibility).
        max_range_m: copies whose center is farther than this from the camera are skipped.
    """
    h_above = cam.position[2] - float(ter.bare.min())
    cand = _candidates(craters, ter.period, cam, h_above, rules.min_emit_height_px, max_range_m)
    if not cand:
        return []
    k = np.array([c[0] for c in cand])
    bowl = surviving_bowl(craters, ter.period, k)
    off = np.array([[c[1] * ter.period, c[2] * ter.period] for c in cand])
    ang = np.linspace(0.0, 2 * np.pi, N_RIM, endpoint=False)
    ctr = np.array([[craters[i].x, craters[i].y] for i in k]) + off
    rad = np.array([craters[i].radius for i in k])
    x = ctr[:, :1] + rad[:, None] * np.cos(ang)  # (K, N_RIM)
    y = ctr[:, 1:] + rad[:, None] * np.sin(ang)
    z = rim_plane(x, y, ter.height_at(x, y, bare=True))
    pts = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    uv, zc = cam.project(pts)
    uv, zc = uv.reshape(len(k), N_RIM, 2), zc.reshape(len(k), N_RIM)
    out = []
    for j, i in enumerate(k):
        ann = _crater_ann(craters[i], ctr[j], z[j], uv[j], zc[j], cam, depth, rules, bowl[j])
        if ann is not None:
            out.append(ann)
    return out


def rim_plane(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Heights of the rim circle: a robust plane fit through the terrain's rim heights.

    The labelled rim is a planar (possibly tilted) circle, so its projection is an exact
    ellipse even where later craters cut into the rim or the ground slopes. Samples more than
    3 median absolute residuals (+ 2 cm) off the first fit are dropped before the second.

    Args:
        x, y, z: (K, N) rim sample coordinates and terrain heights, m.

    Returns:
        (K, N) plane heights, m.
    """
    a = np.stack([x - x.mean(1, keepdims=True), y - y.mean(1, keepdims=True), np.ones_like(x)],
                 axis=-1)
    w = np.ones_like(z)
    for _ in range(2):
        ata = np.einsum("kni,knj,kn->kij", a, a, w)
        atz = np.einsum("kni,kn,kn->ki", a, z, w)
        coef = np.linalg.solve(ata + 1e-9 * np.eye(3), atz[..., None])[..., 0]
        fit = np.einsum("kni,ki->kn", a, coef)
        res = np.abs(z - fit)
        w = (res <= 3 * np.median(res, axis=1, keepdims=True) + 0.02).astype(float)
    return fit


def _candidates(craters: list[Crater], period: float, cam: PinholeCam, h_above: float,
                min_px: float, max_range_m: float) -> list[tuple[int, int, int]]:
    """(crater index, tile i, tile j) of crater copies that may show at least ``min_px`` tall.

    A conservative cull: the copy must reach in front of the camera, lie within the field of
    view (with its radius as margin) and span at least ``min_px`` pixels vertically by a
    generous estimate (camera ``h_above`` the lowest terrain, m; rim relief 0.1 r + 0.05 m;
    a factor 2 for perspective stretch).
    """
    if not craters:
        return []
    xy = np.array([[c.x, c.y] for c in craters])
    rad = np.array([c.radius for c in craters])
    off = np.arange(-2, 3) * period
    ti, tj, k = np.meshgrid(np.arange(5), np.arange(5), np.arange(len(craters)), indexing="ij")
    ti, tj, k = ti.ravel(), tj.ravel(), k.ravel()
    px, py = xy[k, 0] + off[ti] - cam.position[0], xy[k, 1] + off[tj] - cam.position[1]
    r = rad[k]
    dist = np.hypot(px, py)
    keep = dist - r <= max_range_m
    pc = cam.to_cam(np.stack([px, py, np.zeros_like(px)], 1) + cam.position * (1, 1, 0))
    zc = pc[:, 2]
    half = np.arctan(0.5 * max(cam.width, cam.height) / min(cam.fx, cam.fy)) * 1.05
    lateral = np.hypot(pc[:, 0], pc[:, 1])
    keep &= zc + r + 1.0 > 0
    keep &= np.arctan2(np.maximum(lateral - r - 1.0, 0), np.maximum(zc, 1e-3)) <= half
    near = np.maximum(dist - r, 0.05)
    span = h_above * 2 * r / (near * (dist + r)) + (0.1 * r + 0.05) / near
    keep &= (2.0 * max(cam.fx, cam.fy) * span >= min_px) | (dist < 3 * r)
    sel = np.flatnonzero(keep)
    return [(int(k[s]), int(ti[s]) - 2, int(tj[s]) - 2) for s in sel]


def _crater_ann(c: Crater, ctr: np.ndarray, z: np.ndarray, uv: np.ndarray, zc: np.ndarray,
                cam: PinholeCam, depth: np.ndarray, rules: LabelConfig, bowl: float
                ) -> dict[str, Any] | None:
    """One crater copy centred at ``ctr`` (2,) m, or None when it does not show.

    Args:
        z: (N_RIM,) rim heights, m. uv: (N_RIM, 2) projected rim, px. zc: (N_RIM,) camera z, m.
        bowl: the share of the bowl's relief later craters left (:func:`craters.surviving_bowl`).
    """
    front = zc > 0.05
    if not front.any():
        return None
    w, h = cam.width, cam.height
    box = _box(uv[front] + 0.5)
    clip = (max(box[0], 0.0), max(box[1], 0.0), min(box[2], w), min(box[3], h))
    cw, ch = clip[2] - clip[0], clip[3] - clip[1]
    if round(cw, 3) <= 0 or round(ch, 3) <= 0 or ch < rules.min_emit_height_px:
        return None  # no area in the image at the labels' 1e-3 px precision
    full_area = (box[2] - box[0]) * (box[3] - box[1])
    near = max(0.0, math.hypot(ctr[0] - cam.position[0], ctr[1] - cam.position[1]) - c.radius)
    vis = _visible_fraction(uv[front], zc[front], depth)
    center = cam.to_cam(np.array([[ctr[0], ctr[1], float(z.mean())]]))[0]
    ell = cv2.fitEllipse(uv[front].astype(np.float32))
    a, b = 0.5 * ell[1][0], 0.5 * ell[1][1]
    reasons = _ignore_reasons(front.all(), cw * ch / max(full_area, 1e-9), ch, 2 * min(a, b),
                              near, c, vis, bowl, rules)
    return {
        "category_id": 1,
        "bbox": [round(clip[0], 3), round(clip[1], 3), round(cw, 3), round(ch, 3)],
        "area": round(min(math.pi * a * b, cw * ch), 3),
        "ignore": bool(reasons), "iscrowd": int(bool(reasons)),
        "ignore_reasons": reasons,
        "diameter_m": round(c.diameter, 4), "depth_m": round(c.depth_m, 4),
        "center_cam_m": [round(float(v), 4) for v in center],
        "near_rim_range_m": round(near, 4),
        "ellipse": [round(ell[0][0], 3), round(ell[0][1], 3), round(a, 3), round(b, 3),
                    round(ell[2], 3)],
        "visible_rim_fraction": round(vis, 3),
        "surviving_bowl_fraction": round(bowl, 3),
        "degradation": round(c.degradation, 3),
    }


def _box(uv: np.ndarray) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1) of points (N, 2)."""
    return (float(uv[:, 0].min()), float(uv[:, 1].min()),
            float(uv[:, 0].max()), float(uv[:, 1].max()))


def _visible_fraction(uv: np.ndarray, zc: np.ndarray, depth: np.ndarray) -> float:
    """Share of in-image rim samples not hidden behind nearer terrain in ``depth``."""
    h, w = depth.shape
    iu, iv = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    inside = (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
    if not inside.any():
        return 0.0
    d = depth[iv[inside], iu[inside]]
    visible = zc[inside] <= d * 1.03 + 0.05
    return float(visible.mean())


def _ignore_reasons(all_front: bool, clip_frac: float, height_px: float, minor_px: float,
                    near_m: float, c: Crater, vis: float, bowl: float, r: LabelConfig
                    ) -> list[str]:
    """Names of the ignore rules a crater box trips (empty = a countable crater).

    Args:
        height_px: the clipped box's height. minor_px: the rim ellipse's minor axis (2 b).
    """
    reasons = []
    if not all_front:
        reasons.append("behind_camera")
    if clip_frac < r.min_clip_fraction:
        reasons.append("clipped")
    if height_px < r.min_box_height_px:
        reasons.append("small")
    if near_m > r.max_near_rim_range_m:
        reasons.append("far")
    if c.diameter < r.crater_min_diameter_m:
        reasons.append("tiny_diameter")
    if c.depth_m < r.min_depth_m:
        reasons.append("shallow")
    if vis < r.min_visible_rim_fraction:
        reasons.append("occluded")
    if bowl < r.min_surviving_bowl_fraction:
        reasons.append("overprinted")
    if r.edge_on(minor_px, height_px):
        reasons.append("edge_on")
    return reasons


def object_annotations(ids: np.ndarray, objects: dict[int, SceneObject],
                       rules: LabelConfig) -> list[dict[str, Any]]:
    """Rock and artifact annotations from the encoded id image (H, W) (visible pixels)."""
    flat = ids.ravel()
    sel = np.flatnonzero(flat > 0)
    if sel.size == 0:
        return []
    codes, inv, counts = np.unique(flat[sel], return_inverse=True, return_counts=True)
    w = ids.shape[1]
    rows, cols = sel // w, sel % w
    big = np.iinfo(np.int64).max
    x0 = np.full(codes.size, big)
    y0 = np.full(codes.size, big)
    x1 = np.full(codes.size, -1)
    y1 = np.full(codes.size, -1)
    np.minimum.at(x0, inv, cols)
    np.minimum.at(y0, inv, rows)
    np.maximum.at(x1, inv, cols)
    np.maximum.at(y1, inv, rows)
    oids, tiles = raycast.decode_ids(codes)
    out = []
    for k in range(codes.size):
        obj = objects[int(oids[k])]
        bw, bh = int(x1[k] - x0[k] + 1), int(y1[k] - y0[k] + 1)
        if bh < rules.min_emit_height_px:
            continue
        ignore = bh < rules.min_box_height_px
        out.append({
            "category_id": obj.category, "bbox": [int(x0[k]), int(y0[k]), bw, bh],
            "area": int(counts[k]), "ignore": bool(ignore), "iscrowd": int(ignore),
            "ignore_reasons": ["small"] if ignore else [], "kind": obj.kind,
            "size_m": round(obj.size_m, 4), "object_id": obj.oid, "tile": int(tiles[k]),
        })
    return out

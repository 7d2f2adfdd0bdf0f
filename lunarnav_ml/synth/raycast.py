"""Numba kernels: ray marching through a periodic heightfield and the sun shadow map.

The heightfield ``h[ix, iy]`` holds node heights at x = x0 + ix * res, y = y0 + iy * res
(scene frame, m). It is periodic with period n * res on both axes, so rays leaving the DEM
see a seamless tiling; the tile a hit falls in is reported so labels can tell copies apart.
Between nodes the surface is bilinear.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

BLOCK = 16  # cells per side of a coarse max-height block used to skip empty space
STEP_FRACTION = 0.015  # far-field march step / range: thinnest obstacle resolved at range t
N_TILE_CODES = 25  # tiles -2..2 on each axis are coded 0..24; farther tiles get code -1


@nb.njit(cache=True, inline="always")
def _bilinear(a: np.ndarray, gx: float, gy: float) -> float:
    """Periodic bilinear sample of a (n, n) grid at grid coordinates (gx, gy)."""
    n = a.shape[0]
    i0 = math.floor(gx)
    j0 = math.floor(gy)
    fx = gx - i0
    fy = gy - j0
    if i0 < 0 or i0 >= n:  # integer modulo is slow: only leave the home tile when needed
        i0 %= n
    if j0 < 0 or j0 >= n:
        j0 %= n
    i1 = i0 + 1 if i0 + 1 < n else 0
    j1 = j0 + 1 if j0 + 1 < n else 0
    return ((1 - fx) * ((1 - fy) * a[i0, j0] + fy * a[i0, j1])
            + fx * ((1 - fy) * a[i1, j0] + fy * a[i1, j1]))


def block_max(h: np.ndarray, block: int = BLOCK) -> np.ndarray:
    """Max node height per block including the shared border nodes, (nb, nb) float32."""
    n = h.shape[0]
    nbk = -(-n // block)
    pad = np.pad(h, ((0, nbk * block + 1 - n), (0, nbk * block + 1 - n)), mode="wrap")
    core = pad[:-1, :-1].reshape(nbk, block, nbk, block).max(axis=(1, 3))
    edge_x = pad[block::block, :-1].reshape(nbk, nbk, block).max(axis=2)
    edge_y = pad[:-1, block::block].reshape(nbk, block, nbk).max(axis=1)
    corner = pad[block::block, block::block]
    return np.maximum.reduce([core, edge_x, edge_y, corner]).astype(np.float32)


@nb.njit(cache=True, inline="always")
def _refine(oz, dz, gx0, gy0, dgx, dgy, h, lo, hi):
    """Crossing in [lo, hi] (above at lo, below at hi): 6 bisections, then a secant step.

    The ray is at height ``oz + t dz`` over grid point ``(gx0 + t dgx, gy0 + t dgy)``.
    """
    f_lo = oz + lo * dz - _bilinear(h, gx0 + lo * dgx, gy0 + lo * dgy)
    f_hi = oz + hi * dz - _bilinear(h, gx0 + hi * dgx, gy0 + hi * dgy)
    for _ in range(6):
        mid = 0.5 * (lo + hi)
        f = oz + mid * dz - _bilinear(h, gx0 + mid * dgx, gy0 + mid * dgy)
        if f <= 0.0:
            hi, f_hi = mid, f
        else:
            lo, f_lo = mid, f
    if f_lo - f_hi > 1e-12:
        return lo + (hi - lo) * f_lo / (f_lo - f_hi)
    return hi


@nb.njit(cache=True)
def _march(ox, oy, oz, dx, dy, dz, h, bmax, x0, y0, res, t_min, t_max, pix, hmax, frac):
    """March one ray; returns the hit distance t (m) or inf.

    Divisions are hoisted out of the loop (reciprocals): they dominate its cost otherwise.
    """
    n = h.shape[0]
    nbk = bmax.shape[0]
    inv_res = 1.0 / res
    inv_n = 1.0 / n
    inv_block = 1.0 / BLOCK
    dgx = dx * inv_res
    dgy = dy * inv_res
    inv_dgx = 1.0 / dgx if dgx != 0.0 else 0.0
    inv_dgy = 1.0 / dgy if dgy != 0.0 else 0.0
    gx0 = (ox - x0) * inv_res
    gy0 = (oy - y0) * inv_res
    hxy = math.sqrt(dx * dx + dy * dy)
    near_step = min(0.5 * res / max(hxy, 1e-9), 2.0 * res)
    far_frac = max(frac, pix)
    t = t_min
    while t < t_max:
        pz = oz + t * dz
        if dz >= 0.0 and pz > hmax:
            return math.inf
        gx = gx0 + t * dgx
        gy = gy0 + t * dgy
        wx = gx - n * math.floor(gx * inv_n)
        wy = gy - n * math.floor(gy * inv_n)
        bx = min(int(wx * inv_block), nbk - 1)
        by = min(int(wy * inv_block), nbk - 1)
        te = math.inf
        if dgx > 0:
            te = (min((bx + 1) * BLOCK, n) - wx) * inv_dgx
        elif dgx < 0:
            te = (bx * BLOCK - wx) * inv_dgx
        if dgy > 0:
            te = min(te, (min((by + 1) * BLOCK, n) - wy) * inv_dgy)
        elif dgy < 0:
            te = min(te, (by * BLOCK - wy) * inv_dgy)
        te = t + te + 1e-5
        top = bmax[bx, by]
        if pz > top and oz + te * dz > top:
            t = te
            continue
        # step: half a cell near, ``frac`` of the range (or one ray spacing) far;
        # the bracketed crossing is then refined by bisection
        tn = t + max(near_step, far_frac * t)
        if oz + tn * dz <= _bilinear(h, gx0 + tn * dgx, gy0 + tn * dgy):
            return _refine(oz, dz, gx0, gy0, dgx, dgy, h, t, tn)
        t = tn
    return math.inf


@nb.njit(cache=True, parallel=True)
def cast_rays(origin, dirs, h, bmax, x0, y0, res, t_min, t_max, pix, hmax, frac, out_t):
    """Hit distance of every ray from one origin.

    Args:
        origin: (3,) ray origin, m. dirs: (N, 3) unit directions.
        h: (n, n) heights, m. bmax: block maxima from :func:`block_max`.
        x0, y0, res: grid origin and cell size, m. t_min, t_max: search interval, m.
        pix: ray angular spacing, rad (coarsens the step with distance). hmax: h.max().
        frac: far-field step as a fraction of the range (obstacles thinner than frac * t
            along the ray may be missed; camera default STEP_FRACTION, lidar finer).
        out_t: (N,) output distances, m (inf = no hit).
    """
    for k in nb.prange(dirs.shape[0]):
        out_t[k] = _march(origin[0], origin[1], origin[2], dirs[k, 0], dirs[k, 1], dirs[k, 2],
                          h, bmax, x0, y0, res, t_min, t_max, pix, hmax, frac)


@nb.njit(cache=True, parallel=True)
def surface_at(px, py, h, shadow, gx_arr, gy_arr, obj, x0, y0, res, out_n, out_lit, out_id):
    """Surface attributes at hit points: normal, sunlit flag, object id with tile code.

    Args:
        px, py: (N,) hit coordinates, m (NaN = no hit, skipped).
        h, shadow: heights and shadow heights (n, n), m. gx_arr, gy_arr: dh/dx, dh/dy (n, n).
        obj: (n, n) int32 object ids (0 = soil).
        out_n: (N, 3) unit normals. out_lit: (N,) 1 lit / 0 shadowed. out_id: (N,) int64
            object id with tile code (see :func:`encode_id`), 0 for soil.
    """
    for k in nb.prange(px.shape[0]):
        if not math.isfinite(px[k]):
            continue
        gx = (px[k] - x0) / res
        gy = (py[k] - y0) / res
        sx = _bilinear(gx_arr, gx, gy)
        sy = _bilinear(gy_arr, gx, gy)
        norm = math.sqrt(sx * sx + sy * sy + 1.0)
        out_n[k, 0] = -sx / norm
        out_n[k, 1] = -sy / norm
        out_n[k, 2] = 1.0 / norm
        hz = _bilinear(h, gx, gy)
        out_lit[k] = 1.0 if hz >= _bilinear(shadow, gx, gy) - 0.004 else 0.0
        out_id[k] = encode_id(obj, gx, gy)


@nb.njit(cache=True, inline="always")
def encode_id(obj, gx, gy):
    """Object id of the node nearest grid point (gx, gy) with its tile code (0 soil, -1 far)."""
    n = obj.shape[0]
    i = int(math.floor(gx + 0.5))  # noqa: RUF046 (numba)
    j = int(math.floor(gy + 0.5))  # noqa: RUF046 (numba)
    oid = obj[i % n, j % n]
    if oid <= 0:
        return 0
    ti = (i - (i % n)) // n
    tj = (j - (j % n)) // n
    if abs(ti) <= 2 and abs(tj) <= 2:
        return oid + (1 << 20) * ((ti + 2) * 5 + (tj + 2))
    return -1


@nb.njit(cache=True)
def shadow_heights(h, sx, sy, tan_elev, res):
    """Shadow-height field: a point at height z over node (i, j) is sunlit iff z >= S[i, j].

    Sweeps the periodic grid twice in the direction away from the sun, carrying
    S = max(h, S_upstream - distance * tan(elevation)).

    Args:
        h: (n, n) heights, m. sx, sy: horizontal direction toward the sun (unit or zero).
        tan_elev: tangent of the sun elevation. res: cell size, m.

    Returns:
        (n, n) float32 shadow heights, m.
    """
    if abs(sx) < 1e-9 and abs(sy) < 1e-9:
        return h.copy()
    if abs(sy) > abs(sx):  # sweep along the second axis: work on the transpose (row access)
        return np.ascontiguousarray(_sweep_rows(np.ascontiguousarray(h.T), sy, sx,
                                                tan_elev, res).T)
    return _sweep_rows(h, sx, sy, tan_elev, res)


@nb.njit(cache=True)
def _sweep_rows(h, a, b, tan_elev, res):
    """:func:`shadow_heights` for a sun mostly along the first axis (|a| >= |b|)."""
    n = h.shape[0]
    s = h.copy()
    sgn = 1 if a > 0 else -1
    off = b / abs(a)
    drop = res * math.sqrt(1.0 + off * off) * tan_elev
    start = n - 1 if sgn > 0 else 0
    # the upstream sample is offset by the same ``off`` for every j: floor and wrap it once
    base = math.floor(off)
    f = off - base
    for k in range(2 * n):
        i = (start - sgn * k) % n
        iu = (i + sgn) % n
        j0 = base % n
        for j in range(n):
            j1 = j0 + 1 if j0 + 1 < n else 0
            s[i, j] = max(h[i, j], (1 - f) * s[iu, j0] + f * s[iu, j1] - drop)
            j0 = j1
    return s


def decode_ids(codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split encoded ids into (object id, tile code 0..24); soil and far tiles give id 0."""
    codes = np.asarray(codes, np.int64)
    valid = codes > 0
    oid = np.where(valid, codes & ((1 << 20) - 1), 0)
    tile = np.where(valid, codes >> 20, -1)
    return oid, tile


def tile_offset(code: int) -> tuple[int, int]:
    """Tile code 0..24 -> (ti, tj) tile offsets in periods."""
    return code // 5 - 2, code % 5 - 2

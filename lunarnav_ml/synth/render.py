"""The embedded CPU renderer: ray-cast heightfield, Hapke soil, shiny hardware, sun shadows.

One call renders a view: per-pixel rays are marched through the periodic DEM (numba), hit
points get normals, a sunlit flag from the precomputed shadow-height map and their object id;
soil is shaded with Hapke IMSA, artifact materials with Lambert + Blinn-Phong (foil gets
crinkled normals). The sky is black. A faint ambient term stands in for terrain
interreflection inside shadows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba as nb
import numpy as np

from lunarnav_ml.synth import raycast
from lunarnav_ml.synth import terrain as T
from lunarnav_ml.synth.camera import PinholeCam
from lunarnav_ml.synth.hapke import HapkeParams, hapke_one, hapke_reflectance

# material code -> (diffuse albedo, specular strength, Blinn-Phong exponent, normal crinkle)
MATERIALS = {
    T.GOLD_FOIL: (0.30, 0.55, 25.0, 0.35),
    T.SILVER_FOIL: (0.45, 0.70, 40.0, 0.30),
    T.WHITE_PAINT: (0.80, 0.04, 10.0, 0.0),
    T.DARK_PANEL: (0.06, 0.35, 150.0, 0.0),
}
AMBIENT = 0.012  # interreflection fill, fraction of a flat sunlit surface's reflectance
MICRO_OCTAVES = 3  # octaves of the sub-DEM soil texture, each half the wavelength of the last
MICRO_NORM = 1.0 / 0.42  # 1 / RMS of the value-noise fBm of MICRO_OCTAVES octaves (measured)
MICRO_GRAD_NORM = 1.0 / 0.99  # 1 / RMS of one component of its lattice-unit gradient
PEBBLE_ALBEDO = 1.3  # pebbles' albedo relative to the soil (the rocks' middle albedo factor)
PEBBLE_MIN_SUN = 0.12  # the sine of the lowest sun a pebble's cast shadow follows (7 deg)


@dataclass(frozen=True)
class MicroTexture:
    """Soil detail finer than the DEM, in the shading only (bump-mapped normals and albedo
    speckle from a smooth value-noise fBm), faded out where a pixel covers more than a
    quarter of an octave's wavelength so that wide views do not alias it into noise.

    Pebbles are half-buried spheres too small for the DEM: each lights like a hemisphere,
    is a little brighter than the soil and casts its shadow on the soil behind it (away from
    the sun); one sits in a cell of a jittered grid with the probability its density gives,
    radius between a quarter of and the full ``pebble_max_radius_m``. A pebble fades out where
    a pixel is wider than its diameter.

    Attributes:
        slope_rms: RMS of each component of the added surface slope.
        albedo_rms: relative RMS of the albedo speckle.
        wavelength_m: longest octave's wavelength, m.
        salt: per-scene offset of the noise lattice.
        pebble_per_m2: pebbles per square metre (at most one per cell of the grid).
        pebble_max_radius_m: the largest pebble radius, m.
    """

    slope_rms: float = 0.0
    albedo_rms: float = 0.0
    wavelength_m: float = 0.04
    salt: float = 0.0
    pebble_per_m2: float = 0.0
    pebble_max_radius_m: float = 0.04

    @property
    def pebble_cell_m(self) -> float:
        """Side of the pebble grid's cells, m: room for the largest pebble and its jitter."""
        return max(0.1, 2.5 * self.pebble_max_radius_m)

    def params(self, pix: float) -> np.ndarray:
        """The kernel's parameter vector (``pix``: angular ray spacing, rad)."""
        cell = self.pebble_cell_m
        return np.array([self.slope_rms, self.albedo_rms, self.wavelength_m, self.salt, pix,
                         min(self.pebble_per_m2 * cell * cell, 1.0), self.pebble_max_radius_m,
                         cell])


@dataclass
class PreparedTerrain:
    """Terrain plus the lookup structures the ray caster needs for one sun direction."""

    ter: T.Terrain
    bmax: np.ndarray
    hmax: float
    gx: np.ndarray
    gy: np.ndarray
    shadow: np.ndarray
    sun: np.ndarray


def prepare(ter: T.Terrain, sun: np.ndarray) -> PreparedTerrain:
    """Block maxima, slopes and the shadow-height map for unit sun vector ``sun`` (3,)."""
    gx, gy = T.gradients(ter.h, ter.res)
    horiz = math.hypot(sun[0], sun[1])
    if horiz < 1e-6:
        shadow = ter.h.copy()
    else:
        shadow = raycast.shadow_heights(ter.h, sun[0] / horiz, sun[1] / horiz,
                                        sun[2] / horiz, ter.res)
    return PreparedTerrain(ter, raycast.block_max(ter.h), float(ter.h.max()), gx, gy,
                           shadow, np.asarray(sun, np.float64))


@dataclass
class View:
    """One rendered view (H, W): radiance (1/sr, unit irradiance), z-depth (m, inf = sky),
    encoded object ids (int64, 0 soil/sky) and the hit points (H, W, 3) in the scene frame."""

    radiance: np.ndarray
    depth: np.ndarray
    ids: np.ndarray
    points: np.ndarray


def cast(prep: PreparedTerrain, origin: np.ndarray, dirs: np.ndarray, pix: float,
         t_max: float, step_frac: float = raycast.STEP_FRACTION) -> np.ndarray:
    """Hit distance along each unit ray (N, 3) from ``origin``, m (inf = none).

    ``pix`` is the angular ray spacing (rad), ``step_frac`` the far-field march step as a
    fraction of the range.
    """
    ter = prep.ter
    out = np.empty(dirs.shape[0], np.float64)
    raycast.cast_rays(np.asarray(origin, np.float64), np.ascontiguousarray(dirs), ter.h,
                      prep.bmax, ter.x0, ter.y0, ter.res, 0.0, t_max, pix, prep.hmax, step_frac, out)
    return out


def _surface(prep: PreparedTerrain, pts: np.ndarray) -> tuple[np.ndarray, ...]:
    """Normals (N, 3), lit (N,), encoded ids (N,) at hit points (N, 3) (NaN rows = miss)."""
    ter = prep.ter
    n = len(pts)
    normals = np.zeros((n, 3))
    lit = np.zeros(n)
    ids = np.zeros(n, np.int64)
    raycast.surface_at(np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1]),
                       ter.h, prep.shadow, prep.gx, prep.gy, ter.obj, ter.x0, ter.y0, ter.res,
                       normals, lit, ids)
    return normals, lit, ids


def shade(prep: PreparedTerrain, origin: np.ndarray, dirs: np.ndarray, t: np.ndarray,
          w_soil: float, hp: HapkeParams, micro: MicroTexture | None = None, pix: float = 0.0
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shade the hits of rays (N, 3) from ``origin`` (3,) at distances ``t`` (N,) (inf = miss).

    ``micro`` adds sub-DEM soil texture, faded by the pixel footprint ``t * pix`` (``pix``:
    angular ray spacing, rad).

    Returns:
        reflectance (N,) 1/sr (0 for misses), encoded object ids (N,) and hit points (N, 3)
        in the scene frame (NaN rows for misses).
    """
    ter, sun = prep.ter, prep.sun
    flat = hapke_reflectance(np.array([max(sun[2], 0.05)]), np.array([1.0]),
                             np.array([max(sun[2], 0.05)]), w_soil, hp)[0]
    n = len(dirs)
    r = np.empty(n)
    ids = np.empty(n, np.int64)
    pts = np.empty((n, 3))
    hpar = np.array([hp.b, hp.c, hp.b_s0, hp.h_s, hp.b_c0, hp.h_c,
                     math.tan(math.radians(hp.theta_bar_deg))])
    mpar = (micro or MicroTexture()).params(pix)  # the kernel skips a texture that is all 0
    _shade_kernel(np.asarray(origin, np.float64), np.ascontiguousarray(dirs),
                  np.ascontiguousarray(t, np.float64), np.asarray(sun, np.float64), ter.h,
                  prep.shadow, prep.gx, prep.gy, ter.obj, ter.material, ter.albedo, ter.x0,
                  ter.y0, ter.res, w_soil, hpar, _MAT_TABLE, AMBIENT * flat, mpar, r, ids, pts)
    return r, ids, pts


_MAT_TABLE = np.array([MATERIALS.get(k, (0.0, 0.0, 1.0, 0.0)) for k in range(5)], np.float64)


@nb.njit(cache=True, inline="always")
def _hash01(a: float, b: float, salt: float) -> float:
    """Deterministic pseudo-random value in [0, 1)."""
    v = math.sin(a * 12.9898 + b * 78.233 + salt * 37.719) * 43758.5453
    return v - math.floor(v)


@nb.njit(cache=True, inline="always")
def _lattice(i: float, j: float, salt: float) -> float:
    """Value at a noise lattice node, uniform in [-1, 1)."""
    return 2.0 * _hash01(i, j, salt) - 1.0


@nb.njit(cache=True)
def _micro(x, y, footprint, micro):
    """Sub-DEM soil texture at scene point (x, y): (albedo factor, slope x, slope y).

    A value-noise fBm (lattice values blended with the quintic fade, analytic gradient) of
    MICRO_OCTAVES octaves, each lattice turned by another angle so that no grid shows; an
    octave fades out between 4 and 2 pixel footprints per wavelength.
    """
    value, dx, dy = 0.0, 0.0, 0.0
    lam, amp = micro[2], 1.0
    for octave in range(MICRO_OCTAVES):
        fade = min(max(lam / (2.0 * footprint) - 1.0, 0.0), 1.0)
        if fade > 0.0:
            co, si = math.cos(0.9 * octave + 0.3), math.sin(0.9 * octave + 0.3)
            u, v = (co * x - si * y) / lam, (si * x + co * y) / lam
            i, j = math.floor(u), math.floor(v)
            fu, fv = u - i, v - j
            su = fu * fu * fu * (fu * (6 * fu - 15) + 10)
            sv = fv * fv * fv * (fv * (6 * fv - 15) + 10)
            dsu, dsv = 30 * fu * fu * (fu - 1) ** 2, 30 * fv * fv * (fv - 1) ** 2
            salt = micro[3] + 7.0 * octave
            a, b = _lattice(i, j, salt), _lattice(i + 1, j, salt)
            c, d = _lattice(i, j + 1, salt), _lattice(i + 1, j + 1, salt)
            k = a - b - c + d
            w = fade * amp
            value += w * (a + (b - a) * su + (c - a) * sv + k * su * sv)
            du = dsu * ((b - a) + k * sv)  # per lattice unit: each octave's slope weighs
            dv = dsv * ((c - a) + k * su)  # like its amplitude, not 2x per octave
            dx += w * (co * du + si * dv)
            dy += w * (-si * du + co * dv)
        lam *= 0.5
        amp *= 0.5
    return (max(1.0 + micro[1] * MICRO_NORM * value, 0.2),
            micro[0] * MICRO_GRAD_NORM * dx, micro[0] * MICRO_GRAD_NORM * dy)


@nb.njit(cache=True, inline="always")
def _pebble_at(ci, cj, micro):
    """The pebble of grid cell (ci, cj): (x, y, radius), radius 0 when the cell has none."""
    salt, cell, rmax = micro[3] + 101.0, micro[7], micro[6]
    if _hash01(ci, cj, salt) >= micro[5]:
        return 0.0, 0.0, 0.0
    r = rmax * (0.25 + 0.75 * _hash01(ci, cj, salt + 1.0) ** 2)
    x = (ci + _hash01(ci, cj, salt + 2.0)) * cell
    y = (cj + _hash01(ci, cj, salt + 3.0)) * cell
    # keep the disc inside its cell, so a point looks only at its own cell for the pebble
    x = min(max(x, ci * cell + r), (ci + 1) * cell - r)
    y = min(max(y, cj * cell + r), (cj + 1) * cell - r)
    return x, y, r


@nb.njit(cache=True)
def _pebbles(x, y, footprint, micro, sun):
    """Pebbles at scene point (x, y): (weight, albedo factor, slope x, slope y, shadowed).

    On a pebble the slopes are the hemisphere's; off one, ``shadowed`` is 1 where the
    shadow of a pebble sunward of the point falls (the sphere's shadow ellipse, cut at
    PEBBLE_MIN_SUN). ``weight`` fades the pebbles from 1 where a pixel spans at most their
    largest radius to 0 where it spans their diameter.
    """
    rmax, cell = micro[6], micro[7]
    weight = min(max(2.0 * rmax / footprint - 1.0, 0.0), 1.0)
    if weight <= 0.0:
        return 0.0, 1.0, 0.0, 0.0, 0.0
    ci, cj = math.floor(x / cell), math.floor(y / cell)
    px, py, r = _pebble_at(ci, cj, micro)
    if r > 0.0:
        ux, uy = (x - px) / r, (y - py) / r
        rho2 = ux * ux + uy * uy
        if rho2 < 1.0:
            nz = math.sqrt(max(1.0 - rho2, 0.04))
            return weight, PEBBLE_ALBEDO, -ux / nz, -uy / nz, 0.0
    # shadow: a pebble whose ellipse (semi-axes r and r / sin(elevation) along the anti-sun
    # direction, from its centre) covers the point lies within reach toward the sun
    horiz = math.hypot(sun[0], sun[1])
    if horiz < 1e-6:
        return weight, 1.0, 0.0, 0.0, 0.0
    sin_el = max(sun[2], PEBBLE_MIN_SUN)
    ax, ay = -sun[0] / horiz, -sun[1] / horiz  # anti-sun direction on the ground
    reach = rmax / sin_el
    ex, ey = x - reach * ax, y - reach * ay  # the farthest sunward centre that can reach
    lo_i, hi_i = math.floor((min(x, ex) - rmax) / cell), math.floor((max(x, ex) + rmax) / cell)
    lo_j, hi_j = math.floor((min(y, ey) - rmax) / cell), math.floor((max(y, ey) + rmax) / cell)
    for i in range(lo_i, hi_i + 1):
        for j in range(lo_j, hi_j + 1):
            qx, qy, q = _pebble_at(i, j, micro)
            if q <= 0.0:
                continue
            dx, dy = x - qx, y - qy
            along = dx * ax + dy * ay
            if along < 0.0:
                continue
            across = -dx * ay + dy * ax
            if (along * sin_el / q) ** 2 + (across / q) ** 2 < 1.0:
                return weight, 1.0, 0.0, 0.0, 1.0
    return weight, 1.0, 0.0, 0.0, 0.0


@nb.njit(cache=True, parallel=True)
def _shade_kernel(origin, dirs, t, sun, h, shadow, gxa, gya, obj, material, albedo, x0, y0,
                  res, w_soil, hp, mat_table, ambient, micro, out_r, out_id, out_pts):
    """Per ray: its hit point; per hit: normal, sunlit flag, id, material; Hapke soil or
    Lambert + Blinn-Phong (foil with crinkled facets per node and height step); plus the
    interreflection fill. Misses get radiance 0, id 0 and a NaN point."""
    n = h.shape[0]
    for k in nb.prange(dirs.shape[0]):
        if not math.isfinite(t[k]):
            out_r[k] = 0.0
            out_id[k] = 0
            out_pts[k, 0] = out_pts[k, 1] = out_pts[k, 2] = math.nan
            continue
        px = origin[0] + dirs[k, 0] * t[k]
        py = origin[1] + dirs[k, 1] * t[k]
        pz = origin[2] + dirs[k, 2] * t[k]
        out_pts[k, 0], out_pts[k, 1], out_pts[k, 2] = px, py, pz
        gx = (px - x0) / res
        gy = (py - y0) / res
        sx = raycast._bilinear(gxa, gx, gy)
        sy = raycast._bilinear(gya, gx, gy)
        i = int(math.floor(gx + 0.5)) % n  # noqa: RUF046 (numba)
        j = int(math.floor(gy + 0.5)) % n  # noqa: RUF046 (numba)
        mat = material[i, j]
        alb = raycast._bilinear(albedo, gx, gy)
        inv = 1.0 / math.sqrt(sx * sx + sy * sy + 1.0)
        nx, ny, nz = -sx * inv, -sy * inv, inv
        shade_h = raycast._bilinear(shadow, gx, gy) - 0.004
        lit = 1.0 if raycast._bilinear(h, gx, gy) >= shade_h else 0.0
        out_id[k] = raycast.encode_id(obj, gx, gy)
        vx, vy, vz = -dirs[k, 0], -dirs[k, 1], -dirs[k, 2]
        kd, ks, shin, crinkle = mat_table[mat, 0], mat_table[mat, 1], mat_table[mat, 2], \
            mat_table[mat, 3]
        if crinkle > 0:
            kz = math.floor(pz / res)
            a, b = i + 0.37 * kz, j - 0.61 * kz
            nx += 2 * crinkle * (_hash01(a, b, 1.0) - 0.5)
            ny += 2 * crinkle * (_hash01(a, b, 2.0) - 0.5)
            nz += 2 * crinkle * (_hash01(a, b, 3.0) - 0.5)
            norm = math.sqrt(nx * nx + ny * ny + nz * nz)
            nx, ny, nz = nx / norm, ny / norm, nz / norm
        # the sub-DEM texture tilts the normal for the light only (bump mapping): the view
        # term keeps the DEM's normal, since a facet turned from the camera is hidden, not dark
        lx, ly, lz = nx, ny, nz
        if mat == 0 and (micro[0] > 0.0 or micro[1] > 0.0 or micro[5] > 0.0):
            footprint = max(t[k] * micro[4], 1e-6)
            speckle, msx, msy = _micro(px, py, footprint, micro)
            if micro[5] > 0.0:
                pw, palb, psx, psy, pshade = _pebbles(px, py, footprint, micro, sun)
                speckle *= 1.0 + pw * (palb - 1.0)
                msx += pw * psx
                msy += pw * psy
                lit *= 1.0 - pw * pshade
            alb *= speckle
            bx, by = sx + msx, sy + msy
            binv = 1.0 / math.sqrt(bx * bx + by * by + 1.0)
            lx, ly, lz = -bx * binv, -by * binv, binv
        mu0 = lx * sun[0] + ly * sun[1] + lz * sun[2]
        mu = nx * vx + ny * vy + nz * vz
        if mat == 0:
            r = hapke_one(mu0, mu, vx * sun[0] + vy * sun[1] + vz * sun[2], w_soil * alb,
                          hp[0], hp[1], hp[2], hp[3], hp[4], hp[5], hp[6])
            fill = ambient * alb
        else:
            hx, hy, hz = vx + sun[0], vy + sun[1], vz + sun[2]
            hn = max(math.sqrt(hx * hx + hy * hy + hz * hz), 1e-9)
            nh = max((nx * hx + ny * hy + nz * hz) / hn, 0.0)
            spec = ks * (shin + 2) / (2 * math.pi) * nh**shin
            r = (kd * alb / math.pi + spec) * max(mu0, 0.0)
            fill = ambient
        out_r[k] = r * lit + fill * (0.5 + 0.5 * nz)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot of (N, 3) with (3,), without BLAS threads."""
    return a[:, 0] * b[0] + a[:, 1] * b[1] + a[:, 2] * b[2]


def render_view(prep: PreparedTerrain, cam: PinholeCam, *, w_soil: float, hp: HapkeParams,
                max_range_m: float, supersample: int = 1, need_ids: bool = True,
                micro: MicroTexture | None = None) -> View:
    """Render one camera: radiance, z-depth, object ids and hit points, each (H, W).

    With ``supersample`` k > 1 the radiance is rendered at k x size and Lanczos-downsampled;
    depth, ids and points come from a second cast through the output pixel centers.
    """
    h, w = cam.height, cam.width
    dirs = cam.ray_dirs(supersample)
    pix = cam.pixel_angle() / supersample
    t = cast(prep, cam.position, dirs, pix, max_range_m)
    hit = np.isfinite(t)
    rad, ids, pts = shade(prep, cam.position, dirs, t, w_soil, hp, micro, pix)
    k = supersample
    radiance = rad.reshape(h * k, w * k).astype(np.float32)
    if k > 1:
        radiance = np.maximum(cv2.resize(radiance, (w, h), interpolation=cv2.INTER_LANCZOS4), 0)
        dirs = cam.ray_dirs(1)
        t = cast(prep, cam.position, dirs, cam.pixel_angle(), max_range_m)
        hit = np.isfinite(t)
        pts = np.full(dirs.shape, np.nan)
        pts[hit] = cam.position + dirs[hit] * t[hit, None]
        ids = np.zeros(len(dirs), np.int64)
        if need_ids:
            ids[hit] = _surface(prep, pts[hit])[2]
    zdir = _dot(dirs, cam.rot[:, 2])
    depth = np.where(hit, t * zdir, np.inf).astype(np.float32).reshape(h, w)
    return View(radiance, depth, ids.reshape(h, w), pts.reshape(h, w, 3))

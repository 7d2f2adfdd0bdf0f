"""Rocks and human-made artifacts, rasterized into the heightfield with their own ids.

Every object is a set of primitives: a superellipse footprint (semi-axes a, b, exponent pe,
yaw) with a domed (rocks) or flat (hardware) top. Where a primitive rises above the terrain it
replaces the height and writes its object id, material and albedo factor into the DEM maps, so
the ray caster sees it and labels come from visible pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from lunarnav_ml.synth import terrain as T
from lunarnav_ml.synth.craters import sample_diameters


@dataclass
class Primitive:
    """Footprint center x, y (m), semi-axes a, b (m), yaw (rad), superellipse exponent pe,
    bottom z_base and top height above it (m), dome exponent (0 = flat top), lobe amplitudes,
    material code and albedo factor."""

    x: float
    y: float
    a: float
    b: float
    yaw: float
    pe: float
    z_base: float
    height: float
    dome: float
    material: int
    albedo: float
    lobes: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)


@dataclass
class SceneObject:
    """A labelled object: id in the DEM ``obj`` map, COCO category (2 rock, 3 artifact)."""

    oid: int
    category: int
    kind: str
    x: float
    y: float
    size_m: float
    primitives: list[Primitive]


@nb.njit(cache=True)
def _stamp_prims(h, albedo, material, obj, x0, y0, res, prims, oids, mats, albs):
    """Rasterize primitives in order.

    prims: (K, 13) rows [x, y, a, b, yaw, pe, z_base, height, dome, l1, ph1, l2, ph2];
    oids, mats, albs: (K,) object id, material code and albedo factor per primitive.
    """
    n = h.shape[0]
    for k in range(prims.shape[0]):
        p = prims[k]
        xc, yc, a, b, yaw, pe, zb, ht, dome = p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7], p[8]
        reach = int(math.ceil(1.3 * max(a, b) / res)) + 1  # noqa: RUF046 (numba)
        gx, gy = (xc - x0) / res, (yc - y0) / res
        ic, jc = int(math.floor(gx)), int(math.floor(gy))  # noqa: RUF046 (numba)
        cy_, sy_ = math.cos(yaw), math.sin(yaw)
        for i in range(ic - reach, ic + reach + 2):
            dx = (i - gx) * res
            for j in range(jc - reach, jc + reach + 2):
                dy = (j - gy) * res
                u = cy_ * dx + sy_ * dy
                v = -sy_ * dx + cy_ * dy
                s = 1.0
                if p[9] > 0 or p[11] > 0:
                    phi = math.atan2(v, u)
                    s += p[9] * math.sin(3 * phi + p[10]) + p[11] * math.sin(5 * phi + p[12])
                q = abs(u / (a * s)) ** pe + abs(v / (b * s)) ** pe
                if q >= 1.0:
                    continue
                z = zb + ht * ((1.0 - q) ** dome if dome > 0 else 1.0)
                if dome > 0:
                    z += 0.04 * ht * math.sin(9.0 * u / a + p[10]) * math.sin(9.0 * v / b + p[12])
                ii, jj = i % n, j % n
                if z > h[ii, jj]:
                    h[ii, jj] = z
                    obj[ii, jj] = oids[k]
                    material[ii, jj] = mats[k]
                    albedo[ii, jj] = albs[k]


def stamp_objects(ter: T.Terrain, objects: list[SceneObject]) -> None:
    """Rasterize objects into the terrain maps in place (in list order)."""
    prims = [(o.oid, p) for o in objects for p in o.primitives]
    if not prims:
        return
    rows = np.array([[p.x, p.y, p.a, p.b, p.yaw, p.pe, p.z_base, p.height, p.dome, *p.lobes]
                     for _, p in prims], np.float64)
    oids = np.array([oid for oid, _ in prims], np.int32)
    mats = np.array([p.material for _, p in prims], np.uint8)
    albs = np.array([p.albedo for _, p in prims], np.float32)
    _stamp_prims(ter.h, ter.albedo, ter.material, ter.obj, ter.x0, ter.y0, ter.res, rows,
                 oids, mats, albs)


def sample_rocks(rng: np.random.Generator, ter: T.Terrain, *, density: float, slope: float,
                 d_min: float, d_max: float, burial: tuple[float, float],
                 albedo_factor: tuple[float, float], first_id: int) -> list[SceneObject]:
    """Rocks over the whole DEM: sizes from N(>=D) = density (D / 0.1 m)^-slope per m^2.

    Shapes vary: footprint aspect 0.55-1, height 0.35-0.8 D, superellipse exponent 1.6-3.5,
    3- and 5-lobed outline wobble, random yaw; partly buried (``burial`` of the height).
    """
    diam = sample_diameters(rng, ter.period**2, density, slope, d_min, d_max, d_ref=0.1)
    k = diam.size
    xy = rng.uniform(0, ter.period, (k, 2)) + (ter.x0, ter.y0)
    aspect, h_ratio = rng.uniform(0.55, 1.0, k), rng.uniform(0.35, 0.8, k)
    bur, yaw, pe = rng.uniform(*burial, k), rng.uniform(0, np.pi, k), rng.uniform(1.6, 3.5, k)
    alb = rng.uniform(*albedo_factor, k)
    lobes = np.column_stack([rng.uniform(0, 0.15, k), rng.uniform(0, 6.3, k),
                             rng.uniform(0, 0.1, k), rng.uniform(0, 6.3, k)])
    ht = h_ratio * diam
    z0 = ter.height_at(xy[:, 0], xy[:, 1]) - bur * ht
    rocks = []
    for i in range(k):
        prim = Primitive(float(xy[i, 0]), float(xy[i, 1]), 0.5 * diam[i],
                         0.5 * diam[i] * aspect[i], float(yaw[i]), float(pe[i]), float(z0[i]),
                         float(ht[i]), 0.5, T.SOIL, float(alb[i]), tuple(lobes[i]))
        rocks.append(SceneObject(first_id + i, 2, "rock", float(xy[i, 0]), float(xy[i, 1]),
                                 float(diam[i]), [prim]))
    return rocks


def make_artifact(kind: str, oid: int, x: float, y: float, ground_z: float,
                  rng: np.random.Generator) -> SceneObject:
    """One artifact of ``kind`` ('lander', 'rover', 'hardware') standing at (x, y, ground_z)."""
    yaw = rng.uniform(0, np.pi)
    builders = {"lander": _lander, "rover": _rover, "hardware": _hardware}
    prims, size = builders[kind](rng)
    c, s = math.cos(yaw), math.sin(yaw)
    out = []
    for p in prims:  # primitives are built in the object frame at (0, 0, 0)
        out.append(Primitive(x + c * p.x - s * p.y, y + s * p.x + c * p.y, p.a, p.b,
                             p.yaw + yaw, p.pe, ground_z + p.z_base, p.height, p.dome,
                             p.material, p.albedo))
    return SceneObject(oid, 3, kind, x, y, size, out)


def _box(x, y, a, b, yaw, z0, top, mat, alb=1.0) -> Primitive:
    return Primitive(x, y, a, b, yaw, 12.0, z0, top - z0, 0.0, mat, alb)


def _cyl(x, y, r, z0, top, mat, alb=1.0) -> Primitive:
    return Primitive(x, y, r, r, 0.0, 2.0, z0, top - z0, 0.0, mat, alb)


def _lander(rng: np.random.Generator) -> tuple[list[Primitive], float]:
    """Descent stage in gold foil on four struts, white antenna dish; 3-4.5 m across."""
    w = rng.uniform(1.0, 1.5)
    top = rng.uniform(1.6, 2.4)
    foil = int(rng.choice([T.GOLD_FOIL, T.SILVER_FOIL]))
    prims = [_box(0, 0, w, w, 0.0, -0.2, top, foil)]
    for k in range(4):
        ang = np.pi / 4 + k * np.pi / 2
        for f in (1.2, 1.55):
            prims.append(_box(f * w * math.cos(ang), f * w * math.sin(ang), 0.35 * w, 0.06,
                              ang, -0.2, 0.8 - 0.4 * (f - 1.2) / 0.35, T.SILVER_FOIL))
        prims.append(_cyl(1.9 * w * math.cos(ang), 1.9 * w * math.sin(ang), 0.22, -0.1, 0.08,
                          T.WHITE_PAINT))
    prims.append(_cyl(0.3 * w, 0.2 * w, 0.35, top - 0.1, top + 0.5, T.WHITE_PAINT))
    return prims, 3.8 * w


def _rover(rng: np.random.Generator) -> tuple[list[Primitive], float]:
    """Rover: white body, dark solar panel, six wheels, camera mast; about 1.5 x 1 m."""
    ln, wd = rng.uniform(0.6, 0.9), rng.uniform(0.45, 0.6)
    prims = [_box(0, 0, ln, wd, 0.0, -0.1, 0.75, T.WHITE_PAINT),
             _box(0, 0, ln * 0.95, wd * 1.3, 0.0, 0.6, 0.8, T.DARK_PANEL, 0.4)]
    for xi in (-0.75, 0.0, 0.75):
        for side in (-1, 1):
            prims.append(_box(xi * ln, side * (wd * 1.35 + 0.1), 0.16, 0.1, 0.0, -0.1, 0.3,
                              T.DARK_PANEL, 0.6))
    prims.append(_cyl(0.7 * ln, 0.0, 0.06, 0.0, 1.5, T.WHITE_PAINT))
    prims.append(_box(0.7 * ln, 0.0, 0.08, 0.18, 0.0, 1.4, 1.6, T.SILVER_FOIL))
    return prims, 2 * ln


def _hardware(rng: np.random.Generator) -> tuple[list[Primitive], float]:
    """Left-behind hardware: a foil-wrapped package, a canister, or a pole with a flag plate."""
    kind = int(rng.integers(3))
    if kind == 0:
        a, b = rng.uniform(0.2, 0.45), rng.uniform(0.15, 0.35)
        return [_box(0, 0, a, b, 0.0, -0.05, rng.uniform(0.2, 0.5), T.GOLD_FOIL)], 2 * a
    if kind == 1:
        r = rng.uniform(0.15, 0.35)
        return [_cyl(0, 0, r, -0.05, rng.uniform(0.4, 0.9), T.SILVER_FOIL)], 2 * r
    return [_cyl(0, 0, 0.03, 0.0, 1.6, T.WHITE_PAINT),
            _box(0.3, 0, 0.3, 0.02, 0.0, 1.0, 1.55, T.WHITE_PAINT, 0.8)], 0.6

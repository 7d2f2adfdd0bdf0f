"""Crater population and morphology.

Sizes follow a cumulative power law N(>=D) = density * D^-slope per m^2 (D in m); the lunar
equilibrium density (Gault 1970) is 10^-1.1 D_km^-2 per km^2, about 0.08 D^-2 per m^2.
Shape: a bowl (quadratic-cubic interior after Fassett & Thomson 2014) from the floor to a raised
rim, uplift and ejecta outside the rim falling off as r^-3 (as in cratermaker); fresh craters
have depth/diameter about 0.2 (Pike 1977) and rim height about 0.04 D, degraded ones are
shallower with lower rims, and their profile is smoothed (softened rims).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numba as nb
import numpy as np

R_MAX = 2.5  # profile support, crater radii (ejecta at 2.5 R is 6 % of the rim height)
N_TABLE = 301  # profile samples over [0, R_MAX]
_RADII = np.linspace(0.0, R_MAX, N_TABLE)  # the profile table's radii, crater radii
BOWL_SAMPLES = 64  # points over a crater's bowl for :func:`surviving_bowl`
GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


@dataclass
class Crater:
    """One crater in the scene frame.

    Attributes:
        x, y: center, m. diameter: rim-crest diameter, m.
        depth_ratio: target depth / diameter. rim_ratio: target rim height / diameter.
        degradation: 0 (fresh) .. 1 (degraded): profile smoothing.
        table: (N_TABLE,) radial profile over r in [0, R_MAX] radii, m (relative to datum).
        depth_m: rim crest to floor, m (after smoothing). rim_height_m: crest above datum, m.
    """

    x: float
    y: float
    diameter: float
    depth_ratio: float
    rim_ratio: float
    degradation: float
    table: np.ndarray
    depth_m: float
    rim_height_m: float

    @property
    def radius(self) -> float:
        """Rim-crest radius, m."""
        return 0.5 * self.diameter


def profile_table(diameter: float, depth_ratio: float, rim_ratio: float,
                  degradation: float, crest_at_rim: bool = False) -> np.ndarray:
    """Radial height profile (N_TABLE,) over r = 0..R_MAX radii, m relative to the datum.

    Interior: floor + (rim - floor) * (0.4 r^2 + 0.6 r^3); exterior: rim * r^-3 tapered to 0 at
    R_MAX; then a Gaussian smoothing of width 0.03 + 0.3 * degradation radii (degradation
    quantized to 1/64). The profile is linear in (floor, rim), so it is a combination of two
    cached smoothed basis profiles. The smoothing moves the crest outward (1.03 radii fresh, 1.4
    degraded); ``crest_at_rim`` rescales the profile radially so that its crest lies at one
    radius, where the labels put the rim (DESIGN.md: the box of the projected rim crest).
    """
    rim = rim_ratio * diameter
    floor = rim - depth_ratio * diameter
    b_floor, b_rim = _basis(round(float(np.clip(degradation, 0.0, 1.0)) * 64))
    table = floor * b_floor + rim * b_rim
    if crest_at_rim:
        table = np.interp(_RADII * crest_radius(table), _RADII, table)
    return table


def crest_radius(table: np.ndarray) -> float:
    """Radius of a profile's crest, radii: its highest point between 0.8 and 2 radii, refined
    by a parabola through the three samples around it; 1.0 when that point is no peak (a
    crater without a raised rim has no crest to move)."""
    lo, hi = np.searchsorted(_RADII, (0.8, 2.0))
    i = lo + int(np.argmax(table[lo:hi]))
    a, b, c = table[i - 1], table[i], table[i + 1]
    if not (b > a and b > c):
        return 1.0
    shift = 0.5 * (a - c) / (a - 2 * b + c)
    return float(_RADII[i] + shift * (_RADII[1] - _RADII[0]))


@functools.lru_cache(maxsize=65)
def _basis(level: int) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed unit profiles (floor part, rim part) for degradation level / 64."""
    r = _RADII
    q = 0.4 * r**2 + 0.6 * r**3
    taper = np.clip((R_MAX - r) / (R_MAX - 2.0), 0.0, 1.0) ** 2
    inside = r < 1.0
    floor_part = np.where(inside, 1.0 - q, 0.0)
    rim_part = np.where(inside, q, np.maximum(r, 1.0) ** -3 * taper)
    sigma = (0.03 + 0.3 * level / 64) / (r[1] - r[0])
    half = math.ceil(3 * sigma)
    k = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
    k /= k.sum()

    def smooth(p: np.ndarray) -> np.ndarray:
        padded = np.concatenate([p[half:0:-1], p, np.repeat(p[-1], half)])
        out = np.convolve(padded, k, mode="valid")
        out.flags.writeable = False
        return out

    return smooth(floor_part), smooth(rim_part)


def make_crater(x: float, y: float, diameter: float, degradation: float,
                depth_ratio: float, rim_ratio: float, crest_at_rim: bool = False) -> Crater:
    """Build a crater and measure its rendered depth and rim height from the profile
    (``crest_at_rim``: :func:`profile_table`)."""
    table = profile_table(diameter, depth_ratio, rim_ratio, degradation, crest_at_rim)
    rim_idx = round((N_TABLE - 1) / R_MAX)
    crest = float(table[max(0, rim_idx - 20): rim_idx + 20].max())
    return Crater(x, y, diameter, depth_ratio, rim_ratio, degradation, table,
                  depth_m=crest - float(table[0]), rim_height_m=crest)


def sample_diameters(rng: np.random.Generator, area_m2: float, density: float, slope: float,
                     d_min: float, d_max: float, d_ref: float = 1.0) -> np.ndarray:
    """Diameters from N(>=D) = density * (D / d_ref)^-slope per m^2 within [d_min, d_max], m."""
    a, b = (d_min / d_ref) ** -slope, (d_max / d_ref) ** -slope
    count = rng.poisson(area_m2 * density * (a - b))
    u = rng.uniform(size=count)
    return d_ref * (a - u * (a - b)) ** (-1.0 / slope)


def sample_morphology(rng: np.random.Generator, fresh_fraction: float, dd_fresh: float,
                      dd_degraded: tuple[float, float], rim_fresh: float
                      ) -> tuple[float, float, float]:
    """(degradation, depth_ratio, rim_ratio) of one crater."""
    if rng.uniform() < fresh_fraction:
        deg = rng.uniform(0.0, 0.15)
        return deg, dd_fresh * rng.uniform(0.9, 1.05), rim_fresh * rng.uniform(0.8, 1.1)
    dd = rng.uniform(*dd_degraded)
    deg = float(np.clip((dd_fresh - dd) / max(dd_fresh - dd_degraded[0], 1e-6), 0.2, 1.0))
    return deg, dd, rim_fresh * (1.0 - 0.8 * deg) * rng.uniform(0.7, 1.1)


@nb.njit(cache=True)
def _kept(r2):
    """Weight the earlier relief keeps inside a stamp's rim, at squared radius ``r2`` in units
    of the stamp's radius: (r / R)^4 (scalars or arrays)."""
    return r2 * r2


@nb.njit(cache=True)
def _stamp(h, x0, y0, res, xc, yc, radius, table, r_max):
    """Stamp one crater (periodic): interior replaced, exterior added."""
    n = h.shape[0]
    gx, gy = (xc - x0) / res, (yc - y0) / res
    i0, j0 = int(math.floor(gx)), int(math.floor(gy))  # noqa: RUF046 (numba)
    h_ref = h[i0 % n, j0 % n]
    reach = int(math.ceil(r_max * radius / res)) + 1  # noqa: RUF046 (numba)
    m = table.shape[0] - 1
    scale = res / radius  # grid steps -> radii
    to_table = m / r_max
    r2_max = r_max * r_max
    for i in range(i0 - reach, i0 + reach + 2):
        dx = (i - gx) * scale
        ii = i % n
        jj = (j0 - reach) % n
        for j in range(j0 - reach, j0 + reach + 2):
            dy = (j - gy) * scale
            r2 = dx * dx + dy * dy
            if r2 < r2_max:
                r = math.sqrt(r2)
                q = r * to_table
                k = min(int(q), m - 1)
                f = q - k
                p = (1 - f) * table[k] + f * table[k + 1]
                if r < 1.0:
                    w = _kept(r2)
                    h[ii, jj] = p + h_ref * (1.0 - w) + h[ii, jj] * w
                else:
                    h[ii, jj] += p
            jj += 1
            if jj == n:
                jj = 0


def surviving_bowl(craters: list[Crater], period: float, index: np.ndarray) -> np.ndarray:
    """Share of each crater's bowl relief that later craters' stamps left in the DEM.

    Craters are stamped in list order, and inside a stamp's rim the earlier relief keeps the
    weight :func:`_kept` (r from the stamp's centre, R its radius; :func:`_stamp`). The
    share is the mean, over points spread evenly across the disk inside the crater's rim, of
    the product of those weights of every later crater: 1 where no later crater reached, 0
    for a bowl wholly excavated by a larger, later one. Distances are periodic (the DEM tiles).

    Args:
        index: (K,) crater indices (repeats allowed).

    Returns:
        (K,) shares in [0, 1].
    """
    k = np.arange(BOWL_SAMPLES) + 0.5
    disk = np.sqrt(k / BOWL_SAMPLES)[:, None] * np.stack(
        [np.cos(k * GOLDEN_ANGLE), np.sin(k * GOLDEN_ANGLE)], axis=1)  # unit disk, even
    xy = np.array([[c.x, c.y] for c in craters]).reshape(-1, 2)
    rad = np.array([c.radius for c in craters])
    uniq, inverse = np.unique(np.asarray(index, int), return_inverse=True)  # periodic copies
    out = np.ones(len(uniq))
    for m, i in enumerate(uniq):
        d = xy[i + 1:] - xy[i]
        d = (d + 0.5 * period) % period - 0.5 * period
        later = np.flatnonzero(np.hypot(d[:, 0], d[:, 1]) < rad[i] + rad[i + 1:])
        if later.size == 0:
            continue
        rel = rad[i] * disk[:, None, :] - d[later][None]  # (S, L, 2) from each later centre
        r2 = (rel[..., 0] ** 2 + rel[..., 1] ** 2) / rad[i + 1:][later] ** 2
        out[m] = float(np.where(r2 < 1.0, _kept(r2), 1.0).prod(axis=1).mean())
    return out[inverse]


def stamp_craters(h: np.ndarray, x0: float, y0: float, res: float,
                  craters: list[Crater]) -> None:
    """Stamp craters into ``h`` (n, n) in place, in list order (later overprints earlier)."""
    for c in craters:
        _stamp(h, x0, y0, res, c.x, c.y, c.radius, c.table, R_MAX)


def rim_points(c: Crater, n: int = 180) -> np.ndarray:
    """(n, 2) x, y of the rim circle, m."""
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return np.stack([c.x + c.radius * np.cos(a), c.y + c.radius * np.sin(a)], axis=1)

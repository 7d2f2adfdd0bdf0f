"""Periodic heightfield terrain: fractal relief plus per-cell material maps.

Arrays are indexed ``[ix, iy]`` with node (ix, iy) at x = x0 + ix * res, y = y0 + iy * res in
the scene frame (x forward, y left, z up, m). The grid is periodic (FFT synthesis, wrapped
stamping), so it tiles seamlessly.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

# Material codes per DEM node (shading in :mod:`lunarnav_ml.synth.render`).
SOIL, GOLD_FOIL, SILVER_FOIL, WHITE_PAINT, DARK_PANEL = 0, 1, 2, 3, 4


@dataclass
class Terrain:
    """A periodic DEM with materials.

    Attributes:
        h: (n, n) float32 node heights, m.
        albedo: (n, n) float32 single-scattering-albedo factor (soil texture, rocks).
        material: (n, n) uint8 material code.
        obj: (n, n) int32 object id (0 soil, rocks and artifacts from 1).
        x0, y0: scene coordinates of node (0, 0), m. res: node spacing, m.
        bare: (n, n) float32 heights before rocks and artifacts were added, m.
    """

    h: np.ndarray
    albedo: np.ndarray
    material: np.ndarray
    obj: np.ndarray
    x0: float
    y0: float
    res: float
    bare: np.ndarray | None = None
    objects: list = field(default_factory=list)

    @property
    def n(self) -> int:
        """Nodes per side."""
        return self.h.shape[0]

    @property
    def period(self) -> float:
        """Tiling period, m."""
        return self.n * self.res

    def height_at(self, x: np.ndarray, y: np.ndarray, bare: bool = False) -> np.ndarray:
        """Periodic bilinear height at scene points, m. Shape: like ``x``."""
        return bilinear(self.bare if bare else self.h, (np.asarray(x) - self.x0) / self.res,
                        (np.asarray(y) - self.y0) / self.res)


def bilinear(a: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Periodic bilinear sample of ``a`` (n, n) at grid coordinates; float64 like ``gx``."""
    n = a.shape[0]
    i0 = np.floor(gx).astype(np.int64)
    j0 = np.floor(gy).astype(np.int64)
    fx, fy = gx - i0, gy - j0
    i0, j0 = i0 % n, j0 % n
    i1, j1 = (i0 + 1) % n, (j0 + 1) % n
    return ((1 - fx) * ((1 - fy) * a[i0, j0] + fy * a[i0, j1])
            + fx * ((1 - fy) * a[i1, j0] + fy * a[i1, j1]))


def fractal_field(n: int, res: float, hurst: float, rng: np.random.Generator,
                  k_min: float = 0.0, k_max: float = np.inf) -> np.ndarray:
    """Periodic fractional-Brownian surface by spectral synthesis, zero mean, unit RMS.

    The amplitude spectrum falls as k^-(H + 1) (power k^-(2H + 2)), so height differences grow
    as lag^H. Wavenumbers outside [k_min, k_max] (cycles per m) are removed.

    Returns:
        (n, n) float32.
    """
    kx = np.fft.fftfreq(n, d=res)
    ky = np.fft.rfftfreq(n, d=res)
    k = np.sqrt(kx[:, None] ** 2 + ky[None, :] ** 2)
    amp = np.zeros_like(k)
    band = (k > max(k_min, 0.0)) & (k <= k_max)
    amp[band] = k[band] ** -(hurst + 1.0)
    noise = rng.standard_normal((n, ky.size)) + 1j * rng.standard_normal((n, ky.size))
    f = np.fft.irfft2(noise * amp, s=(n, n))
    std = f.std()
    return (f / std if std > 0 else f).astype(np.float32)


def rms_difference(h: np.ndarray, res: float, lag_m: float) -> float:
    """RMS height difference at horizontal lag ``lag_m`` along both axes (periodic), m."""
    s = max(1, round(lag_m / res))
    dx = np.roll(h, -s, axis=0) - h
    dy = np.roll(h, -s, axis=1) - h
    return float(np.sqrt(0.5 * (np.mean(dx.astype(np.float64) ** 2)
                                + np.mean(dy.astype(np.float64) ** 2))))


def _coarse_factor(n: int, res: float, target_res: float) -> int:
    """Largest factor f <= target_res / res dividing n (1 when none)."""
    for f in range(max(1, int(target_res / res)), 0, -1):
        if n % f == 0:
            return f
    return 1


def upsample_periodic(a: np.ndarray, factor: int) -> np.ndarray:
    """Bicubic upsampling of a periodic (m, m) field by an integer factor, keeping it periodic."""
    if factor == 1:
        return a
    m = a.shape[0]
    coords = (np.arange(m * factor, dtype=np.float32) / factor)
    map_x = np.broadcast_to(coords[None, :], (m * factor, m * factor))
    map_y = np.broadcast_to(coords[:, None], (m * factor, m * factor))
    return cv2.remap(a.astype(np.float32), np.ascontiguousarray(map_x),
                     np.ascontiguousarray(map_y), cv2.INTER_CUBIC, borderMode=cv2.BORDER_WRAP)


def base_relief(n: int, res: float, *, relief_rms_m: float, hurst: float,
                rng: np.random.Generator) -> np.ndarray:
    """Large-scale relief (wavelengths >= 1 m) scaled to ``relief_rms_m`` at 10 m lag, m.

    Synthesized on a grid up to 4 x coarser (wavelengths >= 1 m need no finer sampling) and
    upsampled bicubically.
    """
    f = _coarse_factor(n, res, 0.2)
    field = fractal_field(n // f, res * f, hurst, rng, k_max=1.0)
    d10 = rms_difference(field, res * f, min(10.0, n * res / 4))
    field = upsample_periodic(field, f)
    return (field * (relief_rms_m / d10 if d10 > 0 else 0.0)).astype(np.float32)


def fine_roughness(n: int, res: float, *, rms_m: float,
                   rng: np.random.Generator) -> np.ndarray:
    """Centimetre-to-metre roughness (wavelengths < 1 m), RMS ``rms_m``, m.

    Synthesized on a periodic tile of about 256 nodes (>= 6 m at 5 cm) repeated over the DEM:
    the longest wavelength kept (1 m) is far below the tile size, so repetition is not visible.
    """
    reps = next((r for r in range(max(1, -(-n // 256)), n + 1) if n % r == 0), 1)
    tile = fractal_field(n // reps, res, 0.5, rng, k_min=1.0)
    return (np.tile(tile, (reps, reps)) * rms_m).astype(np.float32)


def albedo_texture(n: int, res: float, *, rms: float, rng: np.random.Generator) -> np.ndarray:
    """Multiplicative albedo texture, mean 1: patches (0.4-10 m, relative RMS ``rms``) plus
    regolith grain below 0.4 m (RMS ``rms / 2``, on a repeated periodic tile)."""
    f = _coarse_factor(n, res, 0.2)
    field = upsample_periodic(fractal_field(n // f, res * f, 0.3, rng, k_min=0.1,
                                            k_max=0.5 / (res * f)), f)
    reps = next((r for r in range(max(1, -(-n // 256)), n + 1) if n % r == 0), 1)
    grain = np.tile(fractal_field(n // reps, res, 0.2, rng, k_min=0.5 / (res * f)), (reps, reps))
    return np.clip(1.0 + rms * field + 0.5 * rms * grain, 0.3, 2.0).astype(np.float32)


def gradients(h: np.ndarray, res: float) -> tuple[np.ndarray, np.ndarray]:
    """Periodic central-difference slopes dh/dx, dh/dy, (n, n) float32 each."""
    gx = (np.roll(h, -1, axis=0) - np.roll(h, 1, axis=0)) / (2 * res)
    gy = (np.roll(h, -1, axis=1) - np.roll(h, 1, axis=1)) / (2 * res)
    return gx.astype(np.float32), gy.astype(np.float32)

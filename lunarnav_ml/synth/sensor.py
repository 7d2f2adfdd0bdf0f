"""Camera sensor model: exposure, optical blur, shot and read noise, ADC, gamma, 8-bit output."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class SensorParams:
    """One scene's sensor settings.

    Attributes:
        exposure: level the 99.5th percentile of terrain radiance maps to (fraction of full scale).
        full_well_e: electrons at full scale. read_noise_e: read noise RMS, electrons.
        blur_sigma_px: Gaussian PSF sigma, px. gamma: output gamma. adc_bits: 8 or 12.
    """

    exposure: float = 0.85
    full_well_e: float = 12000.0
    read_noise_e: float = 5.0
    blur_sigma_px: float = 0.5
    gamma: float = 1.0
    adc_bits: int = 12


def exposure_gain(radiance: np.ndarray, hit: np.ndarray, level: float) -> float:
    """Gain (full-scale fraction per unit radiance) putting the 99.5th percentile at ``level``.

    Args:
        radiance: (H, W) radiance. hit: (H, W) bool, pixels that see terrain.
    """
    vals = radiance[hit]
    ref = float(np.percentile(vals, 99.5)) if vals.size else 0.0
    return level / ref if ref > 1e-9 else 1.0


def expose(radiance: np.ndarray, gain: float, sp: SensorParams,
           rng: np.random.Generator) -> np.ndarray:
    """Radiance (H, W) -> 8-bit image (H, W) uint8 through the sensor chain.

    Order: PSF blur, photo-electrons = gain * radiance * full well, Poisson shot noise,
    Gaussian read noise, clipping at full well, ADC quantization to ``adc_bits``, gamma,
    8-bit output.
    """
    img = radiance.astype(np.float32)
    if sp.blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), sp.blur_sigma_px, borderType=cv2.BORDER_REFLECT)
    electrons = np.clip(img * gain, 0, 4.0).astype(np.float64) * sp.full_well_e
    electrons = rng.poisson(electrons).astype(np.float64)
    electrons += rng.normal(0.0, sp.read_noise_e, size=electrons.shape)
    frac = np.clip(electrons / sp.full_well_e, 0.0, 1.0)
    levels = 2**sp.adc_bits - 1
    frac = np.rint(frac * levels) / levels
    out = frac ** (1.0 / sp.gamma)
    return np.rint(out * 255.0).astype(np.uint8)

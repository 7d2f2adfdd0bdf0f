"""Calibration statistics from real lunar data (read in place; nothing is copied).

- :func:`crater_sfd_from_boxes`: cumulative crater size-frequency N(>=D) per m^2 from
  orbital crater boxes (LRO NAC tiles near the Chang'e 4 site, 0.5 m/px), fitted as
  N(>=D) = density * D^-slope over a diameter range where the catalogue is complete.
- :func:`relief_from_heightmap`: RMS height difference versus lag (structure function) of a
  DEM heightmap PNG (Apollo 15 NAC DTM crop, about 2 m/px, 49 m over 0..255), giving the
  Hurst exponent (log-log slope) and the RMS difference extrapolated to the synth's 10 m lag.

``python -m lunarnav_ml.synth.calibrate`` prints both for the shared real-data folders.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lunarnav_ml.errors import InputError

LRO_DIR = Path("/work/shared/data/real/lro_nac_craters_ce4")
DTM_PNG = Path("/work/shared/data/real/gazebo_apollo15_nac_dtm/heightmaps/"
               "NAC_DTM_APOLLO15_E261N0036_257x257+7472+2152.png")


@dataclass(frozen=True)
class SfdFit:
    """Cumulative power law N(>=D) = density * D^-slope per m^2 (D in m)."""

    density_per_m2: float
    slope: float
    n_craters: int
    area_m2: float
    d_range_m: tuple[float, float]


def read_crater_boxes(folder: str | Path) -> tuple[np.ndarray, float]:
    """Diameters in pixels ((W + H) / 2) and total image area in px^2 from ``*.txt`` + ``*.png``.

    Label lines are ``ID,X,Y,W,H,C_X,CY`` separated by commas or tabs (both occur).

    Raises:
        InputError: no label files, or a malformed line (names the file and line).
    """
    import cv2

    folder = Path(folder)
    txts = sorted(folder.rglob("*.txt"))
    if not txts:
        raise InputError(f"{folder}: no crater label files (*.txt)")
    diam, area = [], 0.0
    for txt in txts:
        img = cv2.imread(str(txt.with_suffix(".png")), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise InputError(f"{txt.with_suffix('.png')}: missing or unreadable image")
        area += img.shape[0] * img.shape[1]
        for n, line in enumerate(txt.read_text().splitlines()[1:], start=2):
            parts = line.replace("\t", ",").split(",")
            try:
                w, h = float(parts[3]), float(parts[4])
            except (IndexError, ValueError):
                raise InputError(f"{txt}:{n}: expected ID,X,Y,W,H,C_X,CY, got {line!r}") from None
            diam.append(0.5 * (w + h))
    return np.asarray(diam), area


def fit_cumulative_sfd(diam_m: np.ndarray, area_m2: float, d_min: float,
                       d_max: float) -> SfdFit:
    """Least-squares line through log N(>=D) vs log D at the sorted diameters in [d_min, d_max]."""
    d = np.sort(diam_m[(diam_m >= d_min)])[::-1]
    cum = np.arange(1, d.size + 1) / area_m2  # N(>=d[i]) per m^2
    sel = d <= d_max
    if sel.sum() < 10:
        raise InputError(f"crater SFD: only {int(sel.sum())} craters in [{d_min}, {d_max}] m")
    slope, icpt = np.polyfit(np.log10(d[sel]), np.log10(cum[sel]), 1)
    return SfdFit(float(10**icpt), float(-slope), int(sel.sum()), float(area_m2), (d_min, d_max))


def crater_sfd_from_boxes(folder: str | Path = LRO_DIR, m_per_px: float = 0.5,
                          d_min_m: float = 6.0, d_max_m: float = 30.0) -> SfdFit:
    """Fit the crater SFD of an orbital crater-box catalogue.

    ``d_min_m`` sits above the catalogue's 8 px (4 m) cut so the fit avoids the roll-over of
    incomplete small-crater counts.
    """
    diam_px, area_px = read_crater_boxes(folder)
    return fit_cumulative_sfd(diam_px * m_per_px, area_px * m_per_px**2, d_min_m, d_max_m)


@dataclass(frozen=True)
class ReliefFit:
    """RMS height difference s(lag) = rms_at_10m * (lag / 10 m)^hurst."""

    hurst: float
    rms_at_10m: float
    lags_m: tuple[float, ...]
    rms_m: tuple[float, ...]


def relief_from_heightmap(path: str | Path = DTM_PNG, m_per_px: float = 2.0,
                          z_range_m: float = 49.0, smooth_px: float = 1.0,
                          lags_px: tuple[int, ...] = (2, 3, 4, 6, 8)) -> ReliefFit:
    """Structure function of an 8-bit heightmap after light smoothing (removes terracing).

    Args:
        m_per_px: horizontal spacing, m. z_range_m: height of grey level 255 over 0, m.
        smooth_px: Gaussian sigma against the 8-bit quantization, px.
        lags_px: lags of the fit, px (beyond the smoothing scale).
    """
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"{path}: missing or unreadable heightmap")
    z = img.astype(np.float64) * (z_range_m / 255.0)
    if z.ndim == 3:
        z = z[..., 0]
    if smooth_px > 0:
        z = cv2.GaussianBlur(z, (0, 0), smooth_px)
    z -= _plane(z)
    rms = []
    for lag in lags_px:
        dx = z[lag:, :] - z[:-lag, :]
        dy = z[:, lag:] - z[:, :-lag]
        rms.append(float(np.sqrt(0.5 * (np.mean(dx**2) + np.mean(dy**2)))))
    lags = np.asarray(lags_px, float) * m_per_px
    hurst, icpt = np.polyfit(np.log10(lags), np.log10(rms), 1)
    return ReliefFit(float(hurst), float(10 ** (icpt + hurst)), tuple(float(v) for v in lags),
                     tuple(float(v) for v in rms))


def _plane(z: np.ndarray) -> np.ndarray:
    """Least-squares plane through a (H, W) grid (regional tilt removed before statistics)."""
    yy, xx = np.mgrid[: z.shape[0], : z.shape[1]]
    a = np.column_stack([xx.ravel(), yy.ravel(), np.ones(z.size)])
    coef, *_ = np.linalg.lstsq(a, z.ravel(), rcond=None)
    return (a @ coef).reshape(z.shape)


def main(argv: list[str] | None = None) -> int:
    """Print the calibration statistics of the shared real data."""
    ap = argparse.ArgumentParser(description="synth calibration statistics from real data")
    ap.add_argument("--lro", type=Path, default=LRO_DIR)
    ap.add_argument("--dtm", type=Path, default=DTM_PNG)
    args = ap.parse_args(argv)
    sfd = crater_sfd_from_boxes(args.lro)
    print(f"LRO NAC crater boxes: {sfd.n_craters} craters {sfd.d_range_m[0]}-{sfd.d_range_m[1]} m "
          f"over {sfd.area_m2 / 1e6:.3f} km^2: N(>=D) = {sfd.density_per_m2:.4f} D^-{sfd.slope:.2f}"
          f" per m^2 (N(>=5 m) = {sfd.density_per_m2 * 5 ** -sfd.slope * 1000:.2f} per 1000 m^2)")
    rel = relief_from_heightmap(args.dtm)
    print(f"Apollo 15 DTM: Hurst {rel.hurst:.2f}, RMS height difference {rel.rms_at_10m:.3f} m at"
          f" 10 m (lags {rel.lags_m} m -> {tuple(round(v, 3) for v in rel.rms_m)} m)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

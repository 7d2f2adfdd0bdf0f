"""Spread of horizontal position errors, as the paper reports it and stricter."""

from __future__ import annotations

import numpy as np


def horizontal_spread(errors: np.ndarray) -> dict[str, float | list[float] | int | None]:
    """Spread of horizontal (x, y) position errors, m.

    The paper's sigma_p is the standard deviation of the error: here the RMS distance of the
    error vectors from their mean (``sigma_m``). ``rms_m`` is taken about zero, so a bias
    counts too (never flattering). Fewer than two errors give None for every spread.

    Args:
        errors: (N, 2) estimated minus true horizontal position, m.

    Returns:
        ``{"n", "sigma_m", "rms_m", "three_sigma_m", "three_rms_m", "bias_m"}``.
    """
    e = np.asarray(errors, dtype=np.float64).reshape(-1, 2)
    if len(e) < 2:
        return {"n": len(e), "sigma_m": None, "rms_m": None, "three_sigma_m": None,
                "three_rms_m": None, "bias_m": None}
    sigma = float(np.sqrt(np.mean(np.sum((e - e.mean(axis=0)) ** 2, axis=1))))
    rms = float(np.sqrt(np.mean(np.sum(e**2, axis=1))))
    return {"n": len(e), "sigma_m": sigma, "rms_m": rms, "three_sigma_m": 3 * sigma,
            "three_rms_m": 3 * rms, "bias_m": [float(x) for x in e.mean(axis=0)]}

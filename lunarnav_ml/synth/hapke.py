"""Hapke bidirectional reflectance: IMSA with opposition effects and macroscopic roughness.

r(i, e, g) = w / (4 pi) * mu0e / (mu0e + mue) * [p(g) (1 + B_SH(g)) + H(mu0e) H(mue) - 1]
             * (1 + B_CB(g)) * S(i, e, psi)

with a double Henyey-Greenstein phase function p, the shadow-hiding opposition term
B_SH = B_S0 / (1 + tan(g/2) / h_S), the coherent-backscatter term B_CB (Hapke 2002), the
Hapke (2002) approximation of the Chandrasekhar H function, and the Hapke (1984) roughness
correction (effective cosines mu0e, mue and shadowing function S for mean slope theta_bar).
Output: bidirectional reflectance, 1/sr (radiance for unit solar irradiance).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

_EPS = 1e-6


@dataclass(frozen=True)
class HapkeParams:
    """Photometric parameters (see :class:`lunarnav_ml.synth.config.HapkeConfig`)."""

    w: float = 0.19
    b: float = 0.21
    c: float = 0.7
    b_s0: float = 1.0
    h_s: float = 0.07
    b_c0: float = 0.6
    h_c: float = 0.03
    theta_bar_deg: float = 23.657


def h_function(x: np.ndarray, w: np.ndarray | float) -> np.ndarray:
    """Chandrasekhar H function, Hapke (2002) approximation; x = cosine (>= 0)."""
    x = np.maximum(x, _EPS)
    gamma = np.sqrt(1.0 - w)
    r0 = (1.0 - gamma) / (1.0 + gamma)
    return 1.0 / (1.0 - w * x * (r0 + (1.0 - 2.0 * r0 * x) / 2.0 * np.log((1.0 + x) / x)))


def phase_dhg(g: np.ndarray, b: float, c: float) -> np.ndarray:
    """Double Henyey-Greenstein phase function (c > 0: backscattering), g in rad."""
    cg = np.cos(g)
    back = (1.0 - b * b) / (1.0 - 2.0 * b * cg + b * b) ** 1.5
    fwd = (1.0 - b * b) / (1.0 + 2.0 * b * cg + b * b) ** 1.5
    return 0.5 * (1.0 + c) * back + 0.5 * (1.0 - c) * fwd


def opposition(g: np.ndarray, p: HapkeParams) -> tuple[np.ndarray, np.ndarray]:
    """(B_SH, B_CB): shadow-hiding and coherent-backscatter opposition terms, g in rad."""
    tg = np.tan(0.5 * np.minimum(g, np.pi - 1e-3))
    b_sh = p.b_s0 / (1.0 + tg / p.h_s)
    z = np.maximum(tg / p.h_c, 1e-9)
    b_cb = p.b_c0 * (1.0 + (1.0 - np.exp(-z)) / z) / (2.0 * (1.0 + z) ** 2)
    return b_sh, b_cb


def roughness(mu0: np.ndarray, mu: np.ndarray, cos_g: np.ndarray, theta_bar_deg: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hapke (1984) roughness: effective cosines (mu0e, mue) and shadowing S. Inputs > 0."""
    tb = np.radians(theta_bar_deg)
    if tb < 1e-6:
        return mu0, mu, np.ones_like(mu0)
    i = np.arccos(np.clip(mu0, _EPS, 1.0))
    e = np.arccos(np.clip(mu, _EPS, 1.0))
    si, se = np.maximum(np.sin(i), _EPS), np.maximum(np.sin(e), _EPS)
    cpsi = np.clip((cos_g - mu0 * mu) / (si * se), -1.0, 1.0)
    psi = np.arccos(cpsi)
    tan_tb = np.tan(tb)
    chi = 1.0 / np.sqrt(1.0 + np.pi * tan_tb**2)

    def e1(x):
        return np.exp(-2.0 / np.pi / tan_tb / np.maximum(np.tan(x), _EPS))

    def e2(x):
        return np.exp(-1.0 / np.pi / tan_tb**2 / np.maximum(np.tan(x), _EPS) ** 2)

    def eta(x):
        return chi * (np.cos(x) + np.sin(x) * tan_tb * e2(x) / (2.0 - e1(x)))

    s2 = np.sin(0.5 * psi) ** 2
    f = np.exp(-2.0 * np.tan(np.minimum(0.5 * psi, np.pi / 2 - 1e-4)))
    e1i, e1e, e2i, e2e = e1(i), e1(e), e2(i), e2(e)
    le = i <= e  # case i <= e
    den = np.where(le, 2.0 - e1e - psi / np.pi * e1i, 2.0 - e1i - psi / np.pi * e1e)
    mu0e = chi * (mu0 + si * tan_tb * np.where(le, cpsi * e2e + s2 * e2i, e2i - s2 * e2e) / den)
    mue = chi * (mu + se * tan_tb * np.where(le, e2e - s2 * e2i, cpsi * e2i + s2 * e2e) / den)
    eta_i, eta_e = eta(i), eta(e)
    corr = np.where(le, chi * mu0 / eta_i, chi * mu / eta_e)
    s = mue / eta_e * mu0 / eta_i * chi / (1.0 - f + f * corr)
    return mu0e, mue, s


def hapke_reflectance(mu0: np.ndarray, mu: np.ndarray, cos_g: np.ndarray,
                      w: np.ndarray | float, p: HapkeParams) -> np.ndarray:
    """Bidirectional reflectance (1/sr); zero where mu0 <= 0 or mu <= 0. Shapes broadcast."""
    ok = (mu0 > _EPS) & (mu > _EPS)
    m0, m = np.where(ok, mu0, 0.5), np.where(ok, mu, 0.5)
    g = np.arccos(np.clip(cos_g, -1.0, 1.0))
    mu0e, mue, s = roughness(m0, m, np.clip(cos_g, -1.0, 1.0), p.theta_bar_deg)
    b_sh, b_cb = opposition(g, p)
    w = np.minimum(w, 0.999)
    ms = h_function(mu0e, w) * h_function(mue, w) - 1.0
    r = (w / (4 * np.pi) * mu0e / (mu0e + mue) * (phase_dhg(g, p.b, p.c) * (1.0 + b_sh) + ms)
         * (1.0 + b_cb) * s)
    return np.where(ok, np.maximum(r, 0.0), 0.0)


@nb.njit(cache=True, inline="always")
def _h_scalar(x: float, w: float) -> float:
    x = max(x, _EPS)
    gamma = math.sqrt(1.0 - w)
    r0 = (1.0 - gamma) / (1.0 + gamma)
    return 1.0 / (1.0 - w * x * (r0 + (1.0 - 2.0 * r0 * x) / 2.0 * math.log((1.0 + x) / x)))


@nb.njit(cache=True)
def hapke_one(mu0, mu, cos_g, w, b, c, b_s0, h_s, b_c0, h_c, tan_tb):
    """Scalar :func:`hapke_reflectance` (same formulas), 1/sr.

    Angles enter through their cosines only: sin, tan and half-angle tangents come from
    identities (sin i = sqrt(1 - mu0^2), tan(x / 2) = sqrt((1 - cos x) / (1 + cos x))), which
    saves ten transcendental calls per sample against the vectorized form.
    """
    if mu0 <= _EPS or mu <= _EPS:
        return 0.0
    cg = min(max(cos_g, -1.0), 1.0)
    mu0e, mue, s = mu0, mu, 1.0
    if tan_tb > 1e-9:
        ci = min(max(mu0, _EPS), 1.0)
        ce = min(max(mu, _EPS), 1.0)
        si_raw = math.sqrt(max(1.0 - ci * ci, 0.0))
        se_raw = math.sqrt(max(1.0 - ce * ce, 0.0))
        si, se = max(si_raw, _EPS), max(se_raw, _EPS)
        cpsi = min(max((cg - mu0 * mu) / (si * se), -1.0), 1.0)
        psi = math.acos(cpsi)
        chi = 1.0 / math.sqrt(1.0 + math.pi * tan_tb**2)
        s2 = 0.5 * (1.0 - cpsi)  # sin^2(psi / 2)
        f = math.exp(-2.0 * _half_tan(cpsi, _TAN_PSI_MAX))
        ti, te = si_raw / ci, se_raw / ce
        e1i, e1e, e2i, e2e = _e1(ti, tan_tb), _e1(te, tan_tb), _e2(ti, tan_tb), _e2(te, tan_tb)
        eta_i = chi * (ci + si_raw * tan_tb * e2i / (2.0 - e1i))
        eta_e = chi * (ce + se_raw * tan_tb * e2e / (2.0 - e1e))
        if ci >= ce:  # i <= e
            den = 2.0 - e1e - psi / math.pi * e1i
            mu0e = chi * (mu0 + si * tan_tb * (cpsi * e2e + s2 * e2i) / den)
            mue = chi * (mu + se * tan_tb * (e2e - s2 * e2i) / den)
            corr = chi * mu0 / eta_i
        else:
            den = 2.0 - e1i - psi / math.pi * e1e
            mu0e = chi * (mu0 + si * tan_tb * (e2i - s2 * e2e) / den)
            mue = chi * (mu + se * tan_tb * (cpsi * e2i + s2 * e2e) / den)
            corr = chi * mu / eta_e
        s = mue / eta_e * mu0 / eta_i * chi / (1.0 - f + f * corr)
    tg = _half_tan(cg, _TAN_G_MAX)
    b_sh = b_s0 / (1.0 + tg / h_s)
    z = max(tg / h_c, 1e-9)
    b_cb = b_c0 * (1.0 + (1.0 - math.exp(-z)) / z) / (2.0 * (1.0 + z) ** 2)
    w = min(w, 0.999)
    q_back = 1.0 - 2.0 * b * cg + b * b
    q_fwd = 1.0 + 2.0 * b * cg + b * b
    back = (1.0 - b * b) / (q_back * math.sqrt(q_back))
    fwd = (1.0 - b * b) / (q_fwd * math.sqrt(q_fwd))
    p = 0.5 * (1.0 + c) * back + 0.5 * (1.0 - c) * fwd
    ms = _h_scalar(mu0e, w) * _h_scalar(mue, w) - 1.0
    r = w / (4 * math.pi) * mu0e / (mu0e + mue) * (p * (1.0 + b_sh) + ms) * (1.0 + b_cb) * s
    return max(r, 0.0)


_TAN_PSI_MAX = math.tan(math.pi / 2 - 1e-4)  # the vectorized form's clamp of psi / 2
_TAN_G_MAX = math.tan(0.5 * (math.pi - 1e-3))  # ... and of g / 2


@nb.njit(cache=True, inline="always")
def _half_tan(cos_x: float, cap: float) -> float:
    """tan(x / 2) from cos x (x in [0, pi]), capped at ``cap``."""
    if 1.0 + cos_x <= 0.0:
        return cap
    return min(math.sqrt(max(1.0 - cos_x, 0.0) / (1.0 + cos_x)), cap)


@nb.njit(cache=True, inline="always")
def _e1(tan_x: float, tan_tb: float) -> float:
    """Hapke's E1 of an angle x, from tan x."""
    return math.exp(-2.0 / math.pi / tan_tb / max(tan_x, _EPS))


@nb.njit(cache=True, inline="always")
def _e2(tan_x: float, tan_tb: float) -> float:
    """Hapke's E2 of an angle x, from tan x."""
    return math.exp(-1.0 / math.pi / tan_tb**2 / max(tan_x, _EPS) ** 2)


@nb.njit(cache=True, parallel=True)
def _hapke_many(mu0, mu, cos_g, w, b, c, b_s0, h_s, b_c0, h_c, tan_tb, out):
    for k in nb.prange(mu0.shape[0]):
        out[k] = hapke_one(mu0[k], mu[k], cos_g[k], w[k], b, c, b_s0, h_s, b_c0, h_c, tan_tb)


def hapke_fast(mu0: np.ndarray, mu: np.ndarray, cos_g: np.ndarray, w: np.ndarray,
               p: HapkeParams) -> np.ndarray:
    """Numba version of :func:`hapke_reflectance` for 1-D arrays (N,); same result."""
    n = mu0.shape[0]
    out = np.empty(n)
    wv = np.broadcast_to(np.asarray(w, np.float64), (n,)).copy()
    _hapke_many(np.ascontiguousarray(mu0, np.float64), np.ascontiguousarray(mu, np.float64),
                np.ascontiguousarray(cos_g, np.float64), wv, p.b, p.c, p.b_s0, p.h_s, p.b_c0,
                p.h_c, math.tan(math.radians(p.theta_bar_deg)), out)
    return out

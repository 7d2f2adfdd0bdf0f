"""Hapke reflectance: numba kernel equals the numpy formulas; physical behaviour."""

import numpy as np

from lunarnav_ml.synth.hapke import HapkeParams, hapke_fast, hapke_reflectance


def test_numba_matches_numpy():
    rng = np.random.default_rng(0)
    n = 2000
    i, e = rng.uniform(0, 1.5, n), rng.uniform(0, 1.5, n)
    phi = rng.uniform(0, np.pi, n)
    cos_g = np.cos(i) * np.cos(e) + np.sin(i) * np.sin(e) * np.cos(phi)
    w = rng.uniform(0.1, 0.3, n)
    for theta in (0.0, 23.657):
        p = HapkeParams(theta_bar_deg=theta)
        ref = hapke_reflectance(np.cos(i), np.cos(e), cos_g, w, p)
        np.testing.assert_allclose(hapke_fast(np.cos(i), np.cos(e), cos_g, w, p), ref,
                                   rtol=1e-6, atol=1e-9)


def test_opposition_surge_and_no_light_below_horizon():
    p = HapkeParams()
    mu0 = np.array([0.7, 0.7, -0.1])
    mu = np.array([0.7, 0.7, 0.7])
    # same incidence and emission, phase 0 (sun behind the viewer) vs phase 60 deg
    cos_g = np.array([1.0, np.cos(np.radians(60.0)), 0.5])
    r = hapke_reflectance(mu0, mu, cos_g, 0.19, p)
    assert r[0] > 1.5 * r[1] and r[2] == 0.0
    weak = hapke_reflectance(mu0, mu, cos_g, 0.19, HapkeParams(b_s0=0.0, b_c0=0.0))
    assert r[0] / r[1] > weak[0] / weak[1]

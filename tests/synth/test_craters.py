"""Crater profiles: where the smoothed crest lies against the labelled rim."""

import dataclasses

import numpy as np
import pytest

from lunarnav_ml.synth import craters as C
from lunarnav_ml.synth.scene import TargetCrater, TerrainSpec, build_terrain

SHAPES = [  # (degradation, depth/diameter, rim height/diameter): fresh to fully degraded
    (0.0, 0.2, 0.04), (0.1, 0.2, 0.04), (0.3, 0.14, 0.03), (0.6, 0.10, 0.02), (1.0, 0.05, 0.015)]


@pytest.mark.parametrize("deg, dd, rim", SHAPES)
def test_crest_at_rim_puts_the_crest_on_the_labelled_rim(deg, dd, rim):
    old = C.profile_table(6.0, dd, rim, deg)
    new = C.profile_table(6.0, dd, rim, deg, crest_at_rim=True)
    assert abs(C.crest_radius(new) - 1.0) < 0.003
    # the smoothing alone moves the crest outward, further the more degraded the crater
    assert C.crest_radius(old) > 1.02 + 0.3 * deg
    # a radial rescale: floor and crest heights stay (the crest within the sampling's reach)
    assert new[0] == pytest.approx(old[0])
    assert new.max() == pytest.approx(old.max(), rel=2e-3)


def test_crest_radius_finds_a_known_peak():
    r = np.linspace(0.0, C.R_MAX, C.N_TABLE)
    assert C.crest_radius(-((r - 1.234) ** 2)) == pytest.approx(1.234, abs=1e-6)
    # no raised rim, no crest: the profile is left where it is
    flat = C.profile_table(6.0, 0.2, 0.0, 0.0)
    assert C.crest_radius(flat) == 1.0
    assert np.array_equal(C.profile_table(6.0, 0.2, 0.0, 0.0, crest_at_rim=True), flat)


def test_crest_at_rim_reaches_the_rendered_ground(small_cfg):
    """The DEM's highest point along a ray from a lone degraded crater's centre lies on its rim
    (one cell) with ``craters.crest_at_rim``, and about 1.2 radii out without it."""
    diameter, res = 8.0, small_cfg.terrain.resolution_m
    ts = TerrainSpec(seed=3, relief_rms_m=0.0, roughness_rms_m=0.0, crater_density=0.0,
                     fresh_fraction=1.0, rock_density=0.0, albedo_rms=0.0,
                     targets=(TargetCrater(0.0, 0.0, diameter, 0.5, 0.11, 0.025),))

    def crest_m(crest_at_rim: bool) -> float:
        craters = dataclasses.replace(small_cfg.craters, crest_at_rim=crest_at_rim)
        ter = build_terrain(ts, dataclasses.replace(small_cfg, craters=craters)).ter
        x = np.arange(0.0, diameter, res / 2)
        return float(x[np.argmax(ter.height_at(x, np.zeros_like(x), bare=True))])

    assert crest_m(True) == pytest.approx(0.5 * diameter, abs=res)
    assert crest_m(False) > 1.15 * 0.5 * diameter

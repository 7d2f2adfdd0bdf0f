"""Shared fixtures of the geometry tests: rendered single-crater stereo scenes (cached)."""

from __future__ import annotations

import functools

import pytest

from tests.geometry.geometry_scene import Scene, render_crater_scene


@functools.cache
def _scene(diameter: float, near_rim: float, azimuth: float) -> Scene:
    return render_crater_scene(diameter, near_rim, size=(640, 480), pitch_deg=10.0,
                               sun_zenith_deg=60.0, sun_azimuth_deg=azimuth, seed=3)


@pytest.fixture(scope="session")
def crater_scene() -> Scene:
    """A 5 m crater with its near rim 8 m away, sun from the front-left at zenith 60 deg."""
    return _scene(5.0, 8.0, 30.0)


@pytest.fixture(scope="session")
def crater_scene_side_sun() -> Scene:
    """A 10 m crater with its near rim 10 m away, sun from the side (protocol azimuth 90)."""
    return _scene(10.0, 10.0, 90.0)

"""Shared analytic scenes: one fresh bowl crater on flat ground, seen by the paper's sensors."""

import numpy as np
import pytest

from lunarnav_ml.baselines.analytic import (
    AnalyticScene,
    CraterSpec,
    render_disparity,
    simulate_lidar,
)
from lunarnav_ml.baselines.crater_model import CraterProfile

CRATER_D = 10.0
CRATER_XY = (16.0, 3.0)  # rover frame, m; near rim ~11.3 m away
PROFILE = CraterProfile(CRATER_D, 0.2 * CRATER_D)  # floor 2 m down, rim 0.4 m up
CAMERA = {"fx": 256.0, "fy": 256.0, "cx": 255.5, "cy": 255.5, "baseline_m": 0.3,
          "height_m": 1.5, "pitch_deg": 20.0}


@pytest.fixture(scope="session")
def crater_scene() -> AnalyticScene:
    return AnalyticScene([CraterSpec(CRATER_XY, PROFILE)])


@pytest.fixture(scope="session")
def crater_scan(crater_scene) -> np.ndarray:
    return simulate_lidar(crater_scene, range_noise_m=0.01, rng=3)


@pytest.fixture(scope="session")
def flat_scan() -> np.ndarray:
    return simulate_lidar(AnalyticScene(), range_noise_m=0.01, rng=4)


def disparity_of(scene: AnalyticScene, noise_px: float = 0.15, seed: int = 5) -> np.ndarray:
    """512 x 512 left disparity of ``scene`` with CAMERA (90 deg field of view)."""
    return render_disparity(scene, width=512, height=512, fx=CAMERA["fx"], cx=CAMERA["cx"],
                            cy=CAMERA["cy"], baseline_m=CAMERA["baseline_m"],
                            camera_height_m=CAMERA["height_m"], pitch_deg=CAMERA["pitch_deg"],
                            noise_px=noise_px, rng=seed)


@pytest.fixture(scope="session")
def crater_disparity(crater_scene) -> np.ndarray:
    return disparity_of(crater_scene)

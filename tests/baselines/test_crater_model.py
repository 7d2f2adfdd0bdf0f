"""Known-answer tests of the parametric crater model and its occlusion test."""

import numpy as np
import pytest

from lunarnav_ml.baselines.crater_model import CraterProfile, occluded
from lunarnav_ml.errors import InputError


def test_profile_known_heights():
    p = CraterProfile(10.0, 2.0, 0.4)
    assert p.height(np.array(0.0)) == pytest.approx(-2.0)
    assert p.height(np.array(5.0)) == pytest.approx(0.4)  # rim crest
    assert p.height(np.array(2.5)) == pytest.approx(-2.0 + 2.4 * (0.4 * 0.25 + 0.6 * 0.125))
    assert p.height(np.array(5.0 * 3.0)) == pytest.approx(0.0, abs=1e-12)  # flank ends
    assert p.height(np.array(20.0)) == 0.0
    # continuous at the rim
    assert p.height(np.array(5.0 - 1e-6)) == pytest.approx(p.height(np.array(5.0 + 1e-6)), abs=1e-4)


def test_default_rim_and_bad_arguments():
    assert CraterProfile(20.0, 3.0).rim_height_m == pytest.approx(0.8)
    with pytest.raises(InputError, match="diameter_m"):
        CraterProfile(float("nan"), 1.0)
    with pytest.raises(InputError, match="depth_m"):
        CraterProfile(5.0, -1.0)


def test_sample_is_uniform_disk():
    pts, rho = CraterProfile(10.0, 2.0).sample(0.5, extent=1.0)
    assert pts.shape[1] == 3 and rho.max() <= 1.0 + 1e-9
    assert len(pts) == pytest.approx(np.pi * 25 / 0.25, rel=0.05)


def test_occlusion_hides_near_interior_only():
    p = CraterProfile(10.0, 2.0)
    pts = np.array([[-4.0, 0.0, float(p.height(np.array(4.0)))],   # just inside the near rim
                    [4.75, 0.0, float(p.height(np.array(4.75)))],  # upper far wall
                    [-16.0, 0.0, 0.0]])                             # ground before the crater
    hidden = occluded(p, pts, sensor_xy=np.array([-25.0, 0.0]), sensor_z=1.5)
    assert hidden.tolist() == [True, False, False]

import numpy as np
import pytest

from lunarnav_ml.errors import InputError
from lunarnav_ml.geometry.ellipse import Ellipse, fit_crater_ellipse
from lunarnav_ml.geometry.lifter import LifterConfig, lift_crater
from lunarnav_ml.geometry.stereo import SGBMStereo


def _true_disparity(sc) -> np.ndarray:
    return sc.rig.focal_px * sc.rig.baseline_m / sc.depth


@pytest.fixture(scope="module")
def sgbm_disparity(crater_scene):
    return SGBMStereo(num_disparities=96)(crater_scene.left, crater_scene.right).disparity


@pytest.mark.parametrize("method", ["tangent", "plane"])
def test_exact_inputs_recover_center_and_diameter(crater_scene, method):
    sc = crater_scene
    res = lift_crater(sc.ellipse, _true_disparity(sc), sc.rig, LifterConfig(method=method))
    assert res.ok, res.reason
    np.testing.assert_allclose(res.center_m, sc.center_rover, atol=0.05)
    assert res.diameter_m == pytest.approx(sc.crater.diameter, abs=0.05)


def test_rendered_crater_end_to_end(crater_scene, sgbm_disparity):
    """Fitted ellipse + SGBM disparity on a rendered 5 m crater, near rim 8 m away."""
    sc = crater_scene
    fit = fit_crater_ellipse(sc.left, sc.box)
    assert fit.ok, fit.reason
    res = lift_crater(fit.ellipse, sgbm_disparity, sc.rig)
    assert res.ok, res.reason
    assert np.hypot(*(res.center_m[:2] - sc.center_rover[:2])) < 0.3
    assert res.diameter_m == pytest.approx(sc.crater.diameter, abs=0.35)
    assert res.rim_points_m.shape[1] == 3 and res.n_rim >= 8


def test_side_lit_10m_crater(crater_scene_side_sun):
    sc = crater_scene_side_sun
    disp = SGBMStereo(num_disparities=96)(sc.left, sc.right).disparity
    res = lift_crater(fit_crater_ellipse(sc.left, sc.box).ellipse, disp, sc.rig)
    assert res.ok, res.reason
    assert np.hypot(*(res.center_m[:2] - sc.center_rover[:2])) < 0.4
    assert res.diameter_m == pytest.approx(sc.crater.diameter, abs=0.4)


def test_covariance_is_a_covariance(crater_scene, sgbm_disparity):
    res = lift_crater(crater_scene.ellipse, sgbm_disparity, crater_scene.rig)
    cov = res.covariance
    assert cov.shape == (4, 4)
    np.testing.assert_allclose(cov, cov.T, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(cov) >= -1e-12)
    assert 0.0 < res.horizontal_sigma_m < 1.0
    # along-range uncertainty dominates at grazing view
    assert cov[0, 0] > cov[1, 1]


def test_farther_crater_has_larger_uncertainty(crater_scene):
    sc = crater_scene
    disp = _true_disparity(sc)
    near = lift_crater(sc.ellipse, disp + np.random.default_rng(0).normal(0, 0.1, disp.shape), sc.rig)
    # the same crater's disparities scaled as if 1.5x farther: larger range sigma
    far_rig = type(sc.rig)(sc.rig.focal_px, sc.rig.baseline_m / 1.5, sc.rig.cx, sc.rig.cy,
                           sc.rig.height_m, sc.rig.pitch_deg)
    far = lift_crater(sc.ellipse, disp / 1.5 + np.random.default_rng(0).normal(0, 0.1, disp.shape),
                      far_rig)
    assert near.ok and far.ok
    assert far.covariance[0, 0] > near.covariance[0, 0]


@pytest.mark.parametrize("method", ["tangent", "plane"])
def test_all_invalid_disparity_gives_a_reason(crater_scene, method):
    sc = crater_scene
    res = lift_crater(sc.ellipse, np.full(sc.depth.shape, np.nan), sc.rig, LifterConfig(method=method))
    assert not res.ok
    assert res.reason in {"insufficient_rim_disparity", "insufficient_ground_disparity"}
    assert np.isnan(res.center_m).all() and np.isnan(res.diameter_m)


def test_inconsistent_disparity_is_rejected(crater_scene):
    sc = crater_scene
    noisy = np.random.default_rng(1).uniform(1, 40, sc.depth.shape)  # matcher garbage
    res = lift_crater(sc.ellipse, noisy, sc.rig)
    assert not res.ok and res.reason == "stereo_inconsistent"


def test_degenerate_ellipses(crater_scene, sgbm_disparity):
    sc = crater_scene
    bad = Ellipse(np.nan, 10.0, 5.0, 3.0, 0.0)
    assert lift_crater(bad, sgbm_disparity, sc.rig).reason == "invalid_ellipse"
    sky = Ellipse(sc.ellipse.cx, 5.0, 40.0, 3.0, 0.0)  # above the horizon
    res = lift_crater(sky, sgbm_disparity, sc.rig)
    assert not res.ok
    res = lift_crater(sky, sgbm_disparity, sc.rig, LifterConfig(method="plane"))
    assert not res.ok


def test_lifter_bad_inputs(crater_scene):
    with pytest.raises(InputError, match="disparity"):
        lift_crater(crater_scene.ellipse, np.zeros(10), crater_scene.rig)
    with pytest.raises(InputError, match="method"):
        lift_crater(crater_scene.ellipse, np.ones((5, 5)), crater_scene.rig, LifterConfig(method="x"))

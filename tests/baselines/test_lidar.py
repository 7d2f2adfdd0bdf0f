"""The lidar detector stage by stage on one analytic crater with a known answer, plus the
inputs that must give no detection (empty, NaN, flat) and those that must raise."""

import numpy as np
import pytest

from lunarnav_ml.baselines import lidar as L
from lunarnav_ml.baselines.analytic import AnalyticScene, CraterSpec, simulate_lidar
from lunarnav_ml.baselines.crater_model import CraterProfile
from lunarnav_ml.errors import InputError
from tests.baselines.conftest import CRATER_D, CRATER_XY, PROFILE

SENSOR = np.array([0.0, 0.0, 1.5])
CENTER = np.array(CRATER_XY)
DEPTH = PROFILE.depth_m + PROFILE.rim_height_m  # crest to floor, as in the dataset


@pytest.fixture(scope="module")
def scene(crater_scan):
    return L.prepare_scene(crater_scan, SENSOR, L.LidarConfig())


def test_stage1_ground_plane_and_back_wall(scene):
    assert scene.sensor_h == pytest.approx(1.5, abs=0.02)
    walls = L.find_back_walls(scene, L.LidarConfig())
    # the back wall: beyond the center, inside the rim
    back = [w for w in walls if np.hypot(*w.centroid[:2]) > np.hypot(*CENTER)]
    assert len(back) == 1
    assert np.hypot(*(back[0].centroid[:2] - CENTER)) < CRATER_D / 2
    assert np.all(back[0].normals[:, 2] > 0)


def test_stage2_front_rim_back_rim_diameter(scene):
    cfg = L.LidarConfig()
    ests = [e for w in L.find_back_walls(scene, cfg) if (e := L.estimate_crater(scene, w, cfg))]
    assert len(ests) == 1
    est = ests[0]
    u = CENTER / np.hypot(*CENTER)
    assert est.front_rim[:2] @ u == pytest.approx(np.hypot(*CENTER) - 5.0, abs=0.4)
    assert est.back_rim[:2] @ u == pytest.approx(np.hypot(*CENTER) + 5.0, abs=0.4)
    assert est.diameter_m == pytest.approx(CRATER_D, rel=0.06)
    assert np.hypot(*(est.center[:2] - CENTER)) < 0.4


def test_stage3_model_matching_refines_the_center(crater_scan):
    prior = L.MapCrater((CENTER[0] + 1.0, CENTER[1] - 1.0), CRATER_D, DEPTH, PROFILE.rim_height_m)
    # wrong diameter: never a candidate; inside the real crater, so its prior search is dropped
    decoy = L.MapCrater((CENTER[0], CENTER[1]), 3.0, 0.6)
    dets = L.detect_craters_lidar(crater_scan, map_craters=[decoy, prior])
    assert len(dets) == 1 and dets[0].map_index == 1
    assert np.hypot(*(dets[0].center_m[:2] - CENTER)) < 0.2
    assert dets[0].center_m[2] == pytest.approx(PROFILE.rim_height_m, abs=0.1)
    assert dets[0].diameter_m == CRATER_D and -0.1 < dets[0].score <= 0.0


def test_model_score_peaks_at_the_truth(scene):
    cfg = L.LidarConfig()
    model = L.ModelPoints.build(PROFILE, 0.2, CENTER, scene.sensor_h)
    offsets = np.array([[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0]]) + CENTER
    scores = L.score_placements(scene, model, offsets, np.zeros(3), cfg)
    assert np.argmax(scores) == 0 and scores[0] > scores[1:].max() + 0.01


def test_prior_search_finds_the_crater_stage1_misses(crater_scan):
    prior = L.MapCrater((CENTER[0] + 1.0, CENTER[1] - 1.0), CRATER_D, DEPTH, PROFILE.rim_height_m)
    # Stage 1 finds no back wall at all
    blind = L.LidarConfig(min_cluster_points=10**6, prior_search_m=0.0)
    assert L.detect_craters_lidar(crater_scan, map_craters=[prior], config=blind) == []
    cfg = L.LidarConfig(min_cluster_points=10**6)  # the default prior search
    dets = L.detect_craters_lidar(crater_scan, map_craters=[prior], config=cfg)
    assert len(dets) == 1 and np.hypot(*(dets[0].center_m[:2] - CENTER)) < 0.3
    assert np.isnan(dets[0].stage2_diameter_m)


def test_prior_search_replaces_the_placement_of_a_wrong_estimate(scene):
    """A neighbour's Stage-2 estimate 6 m to the side claims the map crater: without the prior
    search the crater is placed there or not at all; with it, at the truth."""
    prior = L.MapCrater((CENTER[0] + 1.0, CENTER[1] - 1.0), CRATER_D, DEPTH, PROFILE.rim_height_m)
    beside = np.array([CENTER[0], CENTER[1] + 6.0, 0.0])
    wall = L.BackWall(beside[None], np.array([[0.0, 0.0, 1.0]]), beside)
    wrong = L.CraterEstimate(wall, beside, beside, beside, CRATER_D)
    loose = L.LidarConfig(prior_search_m=0.0, max_prior_offset_m=None)
    off = L.match_to_map(scene, [wrong], [prior], loose)
    assert len(off) == 1 and np.hypot(*(off[0].center_m[:2] - CENTER)) > 2.0
    # the placement lands over 4 m from the prior: dropped
    assert L.match_to_map(scene, [wrong], [prior], L.LidarConfig(prior_search_m=0.0)) == []
    dets = L.match_to_map(scene, [wrong], [prior], L.LidarConfig())
    assert len(dets) == 1 and np.hypot(*(dets[0].center_m[:2] - CENTER)) < 0.3
    assert np.isnan(dets[0].stage2_diameter_m)


def test_prior_search_rejects_open_ground(flat_scan, crater_scan):
    """On a flat scan the best placement still finds a fair score between the rings; the
    shadow contrast (its shadow is no emptier than the same ranges beside it) rejects it."""
    cfg = L.LidarConfig()
    mc = L.MapCrater(tuple(CENTER), CRATER_D, DEPTH)
    scene = L.prepare_scene(flat_scan, SENSOR, cfg)
    center, score = L.fit_model(scene, CENTER, mc, cfg, half_width_m=2.5)
    assert score >= cfg.min_score  # the score alone would accept it
    model = L.ModelPoints.build(L.map_profile(mc), 0.2, center[:2], scene.sensor_h)
    contrast, expected = L.shadow_contrast(scene, model, center[:2], CRATER_D)
    assert expected >= cfg.min_shadow_expected and contrast < cfg.min_shadow_contrast
    assert L.detect_craters_lidar(flat_scan, map_craters=[mc], config=cfg) == []
    crater = L.prepare_scene(crater_scan, SENSOR, cfg)
    model = L.ModelPoints.build(L.map_profile(mc), 0.2, CENTER, crater.sensor_h)
    assert L.shadow_contrast(crater, model, CENTER, CRATER_D)[0] > 0.9


def _crater_on_a_slope(x_m: float) -> tuple:
    """A 5 m crater at (x_m, 0) on the inner wall of a wide shallow crater around the sensor,
    where the ground rises away from it (~0.12 m/m): the scene, the truth (ground frame) and
    the map crater."""
    wide = CraterProfile(40.0, 1.0, 0.3)
    small = CraterProfile(5.0, 0.8, 0.2)
    slope = AnalyticScene([CraterSpec((-2.0, 0.0), wide), CraterSpec((x_m, 0.0), small)])
    scene = L.prepare_scene(simulate_lidar(slope, range_noise_m=0.01, rng=3), SENSOR,
                            L.LidarConfig())
    truth = scene.frame.to_ground(np.array([[x_m, 0.0, 0.0]]))[0][:2]
    return scene, truth, L.MapCrater((x_m, 0.0), 5.0, 1.0, 0.2)


def test_tilted_local_ground_on_a_slope():
    """A 5 m crater on the inner wall of a wide shallow crater, where the ground rises away
    from the sensor by 0.116 m/m: the fitted plane recovers the slope, and the model placed
    on it lands nearer the truth (and scores better) than on a level ground."""
    scene, truth, mc = _crater_on_a_slope(14.0)
    ground = L.local_ground(scene, L.map_profile(mc), truth, tilt=True)
    assert ground[1] == pytest.approx(0.116, abs=0.01) and abs(ground[2]) < 0.01
    assert np.all(L.local_ground(scene, L.map_profile(mc), truth)[1:] == 0.0)
    start = truth + np.array([0.8, -0.6])
    fits = {tilt: L.fit_model(scene, start, mc, L.LidarConfig(tilted_ground=tilt),
                              half_width_m=2.5) for tilt in (False, True)}
    err = {tilt: np.hypot(*(c[:2] - truth)) for tilt, (c, _) in fits.items()}
    assert err[True] < 0.25 and err[False] > 0.35
    assert fits[True][1] > fits[False][1] + 0.05


def test_sight_height_over_the_local_plane_on_a_slope():
    """Where the ground rises away from the sensor, the sight lines meet the crater's plane
    more steeply than they meet the scan's ground plane: the model's line-of-sight classes
    use the sensor's height over the local plane where it passes under the sensor, and the
    placement lands nearer the truth and scores better than with the height over the scan's
    ground plane."""
    scene, truth, mc = _crater_on_a_slope(16.0)
    ground = L.local_ground(scene, L.map_profile(mc), truth, tilt=True)
    on, off = L.LidarConfig(), L.LidarConfig(plane_sight=False)
    assert L.sight_height(scene, ground, off) == scene.sensor_h
    # the plane rises ~0.13 m/m away from the sensor: it passes ~0.97 m under the sensor's foot
    assert L.sight_height(scene, ground, on) == pytest.approx(scene.sensor_h - ground[0])
    assert L.sight_height(scene, ground, on) > scene.sensor_h + 0.8
    start = truth + np.array([0.8, -0.6])
    fits = {c.plane_sight: L.fit_model(scene, start, mc, c, half_width_m=2.5) for c in (on, off)}
    err = {k: np.hypot(*(c[:2] - truth)) for k, (c, _) in fits.items()}
    assert err[True] < 0.2 and err[False] > 0.25
    assert fits[True][1] > fits[False][1] + 0.02
    # a plane above the sensor (a wall ahead) leaves the sight height at its floor, not <= 0
    wall = np.array([scene.sensor_h + 5.0, -0.3, 0.0])
    assert L.sight_height(scene, wall, on) == L.MIN_SIGHT_HEIGHT
    # a level local ground (no slope fitted) says nothing of the slope: the scan's ground plane
    assert L.sight_height(scene, np.array([-0.5, 0.0, 0.0]), on) == scene.sensor_h


def test_map_crater_far_from_prior_is_not_tried(crater_scan):
    far = L.MapCrater((CENTER[0] + 20.0, CENTER[1]), CRATER_D, DEPTH)
    assert L.detect_craters_lidar(crater_scan, map_craters=[far]) == []


def test_gravity_alignment_on_a_tilted_scan(crater_scan):
    """The same scan seen from a rover pitched 6 deg: same crater in the tilted frame."""
    a = np.radians(6.0)
    rot = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])
    tilted = (crater_scan - SENSOR) @ rot.T + SENSOR
    dets = L.detect_craters_lidar(tilted, sensor_origin=SENSOR)
    truth = (np.array([*CENTER, PROFILE.rim_height_m]) - SENSOR) @ rot.T + SENSOR
    assert len(dets) == 1 and np.hypot(*(dets[0].center_m[:2] - truth[:2])) < 0.4


def test_flat_empty_and_nan_give_no_detection(flat_scan, crater_scan):
    prior = [L.MapCrater(tuple(CENTER), CRATER_D, DEPTH)]
    assert L.detect_craters_lidar(flat_scan, map_craters=prior) == []
    assert L.detect_craters_lidar(flat_scan) == []
    assert L.detect_craters_lidar(np.zeros((0, 3)), map_craters=prior) == []
    assert L.detect_craters_lidar(np.full((500, 3), np.nan)) == []
    with_nans = crater_scan.copy()
    with_nans[::7] = np.nan
    assert len(L.detect_craters_lidar(with_nans, map_craters=prior)) == 1


def test_bad_input_raises():
    with pytest.raises(InputError, match="points"):
        L.detect_craters_lidar(np.zeros((10, 2)))
    with pytest.raises(InputError, match="sensor_origin"):
        L.detect_craters_lidar(np.zeros((10, 3)), sensor_origin=(0.0, np.nan, 1.5))


def test_model_width_sizes_the_model_to_a_narrower_bowl():
    """A crater whose bowl is 0.9 of the map's diameter: the full-width model slides toward the
    sensor, a model of 0.9 the width lands on it, and the map's diameter is reported."""
    center = np.array((14.0, 2.0))
    scan = simulate_lidar(AnalyticScene([CraterSpec(tuple(center), CraterProfile(4.5, 1.0, 0.2))]),
                          range_noise_m=0.01, rng=3)
    prior = L.MapCrater((center[0] + 0.5, center[1] - 0.5), 5.0, 1.2, 0.2)
    err = {}
    for w in (1.0, 0.9):
        (det,) = L.detect_craters_lidar(scan, map_craters=[prior],
                                        config=L.LidarConfig(model_width=w))
        err[w] = float(np.hypot(*(det.center_m[:2] - center)))
        assert det.diameter_m == 5.0
    assert err[0.9] < 0.12 and err[1.0] > 0.2
    with pytest.raises(InputError, match="model_width"):
        L.LidarConfig(model_width=float("nan"))

import json

import numpy as np
import pytest

from lunarnav_ml.errors import InputError
from lunarnav_ml.geometry.ellipse import Ellipse, fit_crater_ellipse
from lunarnav_ml.geometry.lifter import (
    LifterConfig,
    LiftResult,
    _crest_row,
    _lowest_step,
    _match_crest,
    _mean_lift,
    _rim_disparities,
    _rules_agree,
    _tries,
    lift_crater,
    rows_needed,
)
from lunarnav_ml.geometry.stereo import SGBMStereo

from .test_stereo import _texture, _warp

# the helper's rims are sharp crests: the occluding edge is the crest itself
SHARP = {"rim_offset": 0.0, "rim_offset_m": 0.0, "rim_offset_view": 0.0}


def _true_disparity(sc) -> np.ndarray:
    return sc.rig.focal_px * sc.rig.baseline_m / sc.depth


@pytest.fixture(scope="module")
def sgbm_disparity(crater_scene):
    return SGBMStereo(num_disparities=96)(crater_scene.left, crater_scene.right).disparity


@pytest.mark.parametrize("method", ["tangent", "plane"])
def test_exact_inputs_recover_center_and_diameter(crater_scene, method):
    sc = crater_scene
    # the helper's rim is a sharp crest: its occluding edge is the crest itself
    res = lift_crater(sc.ellipse, _true_disparity(sc), sc.rig,
                      LifterConfig(method=method, **SHARP))
    assert res.ok, res.reason
    np.testing.assert_allclose(res.center_m, sc.center_rover, atol=0.05)
    assert res.diameter_m == pytest.approx(sc.crater.diameter, abs=0.05)


def test_rendered_crater_end_to_end(crater_scene, sgbm_disparity):
    """Fitted ellipse + SGBM disparity on a rendered 5 m crater, near rim 8 m away."""
    sc = crater_scene
    fit = fit_crater_ellipse(sc.left, sc.box)
    assert fit.ok, fit.reason
    # the helper's sharp crest, as in test_side_lit_10m_crater: the default edge offsets are
    # calibrated on the protocol renders' smoothed rims (0.31 m too near here, 0.14 sharp)
    res = lift_crater(fit.ellipse, sgbm_disparity, sc.rig, LifterConfig(**SHARP))
    assert res.ok, res.reason
    assert np.hypot(*(res.center_m[:2] - sc.center_rover[:2])) < 0.25
    assert res.diameter_m == pytest.approx(sc.crater.diameter, abs=0.35)
    assert res.rim_points_m.shape[1] == 3 and res.n_rim >= 8


def test_side_lit_10m_crater(crater_scene_side_sun):
    sc = crater_scene_side_sun
    disp = SGBMStereo(num_disparities=96)(sc.left, sc.right).disparity
    # the helper's sharp crest: the default edge offsets, calibrated on the protocol renders'
    # rounded rims, would put it 0.37 m too far for this radius
    res = lift_crater(fit_crater_ellipse(sc.left, sc.box).ellipse, disp, sc.rig,
                      LifterConfig(**SHARP))
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
    gray = np.zeros((5, 5), np.uint8)
    with pytest.raises(InputError, match="pair: right image: expected the disparity's shape"):
        lift_crater(crater_scene.ellipse, np.ones((5, 5)), crater_scene.rig, None,
                    (gray, np.zeros((6, 5, 3), np.uint8)))
    with pytest.raises(InputError, match="pair: left image: expected shape"):
        lift_crater(crater_scene.ellipse, np.ones((5, 5)), crater_scene.rig, None,
                    (np.zeros((5, 5, 2)), gray))
    with pytest.raises(InputError, match="pair: expected"):
        lift_crater(crater_scene.ellipse, np.ones((5, 5)), crater_scene.rig, None, (gray,))


def test_crest_row_snaps_to_the_occluding_edge():
    """Far wall (5 px) above row 50, the crest and outer flank (9 px, growing) below it."""
    rows = np.arange(100, dtype=float)
    column = np.where(rows < 50, 5.0, 9.0 + 0.1 * (rows - 50))
    assert _crest_row(column, 53.2, snap_px=6, min_jump=0.08) == pytest.approx(49.5)
    assert _crest_row(column, 46.0, snap_px=6, min_jump=0.08) == pytest.approx(49.5)
    # out of reach, or no jump at all (plain ground): the row stays
    assert _crest_row(column, 60.0, snap_px=6, min_jump=0.08) == 60.0
    assert _crest_row(9.0 + 0.1 * rows, 53.2, snap_px=6, min_jump=0.08) == 53.2
    # invalid rows between the two surfaces do not hide the jump
    column[49:51] = np.nan
    assert _crest_row(column, 53.0, snap_px=6, min_jump=0.08) == pytest.approx(50.5)


def test_with_no_jump_an_invalid_run_above_marks_the_crest():
    """Sky or an unreadable shadow (NaN) above row 50, the crest and flank below."""
    rows = np.arange(100, dtype=float)
    column = np.where(rows < 50, np.nan, 9.0 + 0.1 * (rows - 50))
    assert _crest_row(column, 53.2, snap_px=6, min_jump=0.08) == 53.2
    assert _crest_row(column, 53.2, 6, 0.08, invalid_edge=True) == pytest.approx(49.5)
    assert _lowest_step(column, 53.0, top=40.0, snap_px=4, min_jump=0.08) == 53.0
    assert _lowest_step(column, 53.0, 40.0, 4, 0.08, invalid_edge=True) == pytest.approx(49.5)
    # a jump still wins; one invalid row is not a run; an invalid run out of reach is not seen
    jump = np.where(rows < 48, np.nan, np.where(rows < 50, 5.0, 9.0 + 0.1 * (rows - 50)))
    assert _crest_row(jump, 51.0, 6, 0.08, invalid_edge=True) == pytest.approx(49.5)
    one = column.copy()
    one[:49] = 9.0
    assert _crest_row(one, 53.2, 6, 0.08, invalid_edge=True) == 53.2
    assert _crest_row(column, 60.0, 6, 0.08, invalid_edge=True) == 60.0


def test_a_crest_under_an_unreadable_far_wall_is_found(crater_scene):
    """The far wall's disparity removed above the crest (as in a deep shadow): the lift still
    reads the crest, and without the rule most samples keep their ellipse rows."""
    sc = crater_scene
    disp = _true_disparity(sc)
    exact = lift_crater(sc.ellipse, disp, sc.rig, LifterConfig(**SHARP))
    _, y, _, h = sc.ellipse.bbox()
    shadow = disp.copy()
    near = [(u, v) for u, v in sc.ellipse.points(72) if v > y + 0.6 * h]
    for u, v in near:  # every row of the crater above the crest, in each sample's column
        edge = _crest_row(disp[:, round(u)], v, 6, 0.08)
        assert edge != v  # a crest edge was there to hide
        shadow[int(y) - 2:int(np.ceil(edge)), round(u)] = np.nan
    seen = lift_crater(sc.ellipse, shadow, sc.rig, LifterConfig(**SHARP))
    blind = lift_crater(sc.ellipse, shadow, sc.rig, LifterConfig(**SHARP, crest_at_invalid=False))
    assert exact.ok and seen.ok and len(near) > 10
    assert seen.crest_fraction > 0.8 and blind.crest_fraction < 0.5
    truth = np.hypot(*exact.center_m[:2])
    assert abs(np.hypot(*seen.center_m[:2]) - truth) < 0.05


def test_snapped_rim_disparities_read_the_crest_not_the_flank():
    h = 120
    rows = np.arange(h, dtype=float)[:, None]
    disp = np.where(rows < 50, 5.0, 9.0 + 0.1 * (rows - 50)) * np.ones((h, 40))
    pts = np.array([[20.0, 55.0], [21.0, 55.0]])
    d0, r0 = _rim_disparities(disp, pts)
    d6, r6 = _rim_disparities(disp, pts, snap_px=6)
    np.testing.assert_allclose(d0, 9.5, atol=1e-9)  # the flank at row 55
    np.testing.assert_allclose(r6, 49.5)
    np.testing.assert_allclose(d6, 8.95, atol=1e-9)  # the flank line carried to the edge
    np.testing.assert_allclose(r0, 55.0)


def _flank_cut_by_a_nearer_rise(h: int, w: int) -> np.ndarray:
    """Far wall (5 px) above row 50, the crest's flank (9 px + 0.1 a row) on rows 50-53, then
    a nearer rise that hides the rest of the flank (10.3 px + 0.1 a row) from row 54."""
    rows = np.arange(h, dtype=float)[:, None]
    d = np.where(rows < 50, 5.0, np.where(rows < 54, 9.0 + 0.1 * (rows - 50),
                                          10.3 + 0.1 * (rows - 54)))
    return d * np.ones((1, w))


def test_the_crest_line_can_stop_at_a_nearer_edge_below_it():
    disp = _flank_cut_by_a_nearer_rise(120, 40)
    pts = np.array([[20.0, 52.0], [21.0, 52.0]])
    d, rows = _rim_disparities(disp, pts, snap_px=6, stop_jump=0.08)
    np.testing.assert_allclose(rows, 49.5)
    np.testing.assert_allclose(d, 8.95, atol=1e-9)  # the flank alone, carried to the crest
    mixed, _ = _rim_disparities(disp, pts, snap_px=6)  # the rise's rows in the line too
    assert np.all(np.abs(mixed - 8.95) > 0.3)  # 8.60


def test_the_crest_match_can_stop_at_a_nearer_edge_below_it():
    left = _texture(120, 400, seed=5)
    truth = _flank_cut_by_a_nearer_rise(120, 400)
    right = _warp(left, truth)
    us = np.arange(80.0, 320.0, 12.0)
    crest = np.full(len(us), 49.5)
    d = np.full(len(us), 8.3)
    flat = np.tile([1.0, 0.0], (len(us), 1))
    pair = (left.astype(np.uint8), right)
    stop = LifterConfig(flank_stop_jump=0.08)
    got = _match_crest(pair, us, crest, d, flat, stop, truth)
    assert np.median(got) == pytest.approx(8.95, abs=0.05)
    # a matcher smears the rise over rows, so its own map may show no step: the one-row
    # matches do, and are cut there
    own = _match_crest(pair, us, crest, d, flat, stop)
    assert np.median(own) == pytest.approx(8.95, abs=0.05)
    mixed = _match_crest(pair, us, crest, d, flat, LifterConfig(), truth)  # off by default
    assert abs(np.median(mixed) - 8.95) > 0.2  # 8.64


def test_rim_offset_moves_the_center_away_by_about_the_offset(crater_scene):
    """The occluding edge in front of the crest by k R: the center moves ~k R / (1 - R / rho)."""
    sc = crater_scene
    disp = _true_disparity(sc)
    sharp = lift_crater(sc.ellipse, disp, sc.rig, LifterConfig(**SHARP))
    rounded = lift_crater(sc.ellipse, disp, sc.rig, LifterConfig(**{**SHARP, "rim_offset": 0.06}))
    assert sharp.ok and rounded.ok
    rho = np.hypot(*sharp.center_m[:2])
    expected = 0.06 * sc.crater.radius / (1 - sc.crater.radius / rho)
    assert np.hypot(*rounded.center_m[:2]) - rho == pytest.approx(expected, rel=0.3)


def test_metric_rim_offset_moves_the_center_away_by_about_the_offset(crater_scene):
    """An edge 0.3 m in front of the crest: the center moves ~0.3 / (1 - R / rho) away."""
    sc = crater_scene
    disp = _true_disparity(sc)
    sharp = lift_crater(sc.ellipse, disp, sc.rig, LifterConfig(**SHARP))
    metric = lift_crater(sc.ellipse, disp, sc.rig, LifterConfig(**{**SHARP, "rim_offset_m": 0.3}))
    behind = lift_crater(sc.ellipse, disp, sc.rig, LifterConfig(**{**SHARP, "rim_offset_m": -0.3}))
    assert sharp.ok and metric.ok and behind.ok
    rho = np.hypot(*sharp.center_m[:2])
    expected = 0.3 / (1 - sc.crater.radius / rho)
    assert np.hypot(*metric.center_m[:2]) - rho == pytest.approx(expected, rel=0.3)
    assert rho - np.hypot(*behind.center_m[:2]) == pytest.approx(expected, rel=0.3)
    # the bearings do not change: the diameter scales with the range
    assert metric.diameter_m / sharp.diameter_m == pytest.approx(
        np.hypot(*metric.center_m[:2]) / rho, rel=1e-6)


def test_view_term_of_the_rim_offset_follows_the_depression_of_the_sight_line(crater_scene):
    """rim_offset_view c: an edge c r H / R in front of the crest (R the edge's range), the
    same shift as the metric offset of that size."""
    sc = crater_scene
    disp = _true_disparity(sc)
    sharp = lift_crater(sc.ellipse, disp, sc.rig, LifterConfig(**SHARP))
    view = lift_crater(sc.ellipse, disp, sc.rig, LifterConfig(**{**SHARP, "rim_offset_view": -0.2}))
    assert sharp.ok and view.ok
    rho = np.hypot(*sharp.center_m[:2])
    near = rho - sc.crater.radius
    offset = -0.2 * sc.crater.radius * sc.rig.height_m / near
    metric = lift_crater(sc.ellipse, disp, sc.rig, LifterConfig(**{**SHARP, "rim_offset_m": offset}))
    expected = offset / (1 - sc.crater.radius / rho)
    assert np.hypot(*view.center_m[:2]) - rho == pytest.approx(expected, rel=0.3)
    # the samples off the line of sight lie farther than the near rim: a smaller view term
    assert abs(np.hypot(*view.center_m[:2]) - rho) < abs(np.hypot(*metric.center_m[:2]) - rho)
    assert abs(np.hypot(*view.center_m[:2]) - rho) > 0.5 * abs(expected)


def test_rim_disparity_crest_fraction_and_the_relative_gate(crater_scene):
    sc = crater_scene
    disp = _true_disparity(sc)
    exact = lift_crater(sc.ellipse, disp, sc.rig, LifterConfig(**SHARP))
    assert exact.ok
    # the median of the true disparity at the labelled near-rim samples (a sharp crest)
    pts = sc.ellipse.points(72)
    near = pts[pts[:, 1] > sc.ellipse.cy + 0.2 * (pts[:, 1].max() - sc.ellipse.cy)]
    rim = np.median(disp[np.round(near[:, 1]).astype(int), np.round(near[:, 0]).astype(int)])
    assert exact.rim_disparity_px == pytest.approx(rim, rel=0.05)
    assert 0.5 <= exact.crest_fraction <= 1.0  # a sharp crest: most samples find its edge
    # a matcher error of ~2 px per column: over the absolute 1.5 px gate, within 20 % of the
    # disparity
    noisy = disp + np.random.default_rng(3).normal(0.0, 2.0, (1, disp.shape[1]))
    strict = lift_crater(sc.ellipse, noisy, sc.rig, LifterConfig(max_rim_residual_rel=0.0))
    assert not strict.ok and strict.reason == "stereo_inconsistent"
    assert 1.5 < strict.rim_residual_px < 0.2 * strict.rim_disparity_px
    relative = lift_crater(sc.ellipse, noisy, sc.rig, LifterConfig(max_rim_residual_rel=0.2))
    assert relative.ok
    assert relative.rim_residual_px == strict.rim_residual_px


def test_crest_match_reads_the_crest_where_the_matcher_smeared_it():
    """Far wall (5 px) above row 50, the crest and a slanted flank (9 px + 0.1 a row) below;
    the matcher's crest value is 8.3 px, pulled toward the far wall as a block matcher's is at
    an occluding edge. One-row windows matched in the images read the flank's own rows, and
    the line through them meets the crest's row at the true 8.95 px."""
    left = _texture(120, 400, seed=5)
    rows = np.arange(120, dtype=float)[:, None]
    truth = np.where(rows < 50, 5.0, 9.0 + 0.1 * (rows - 50)) * np.ones((1, 400))
    right = _warp(left, truth)
    us = np.arange(80.0, 320.0, 12.0)
    crest = np.full(len(us), 49.5)
    d = np.full(len(us), 8.3)  # the matcher's crest value, too low
    flat = np.tile([1.0, 0.0], (len(us), 1))  # the rim runs along the rows here
    cfg = LifterConfig(crest_match=True)
    got = _match_crest((left.astype(np.uint8), right), us, crest, d, flat, cfg)
    np.testing.assert_allclose(got, 8.95, atol=0.15)  # per sample; the matcher's: 8.3
    assert np.median(got) == pytest.approx(8.95, abs=0.03)
    # where the rim is steep in the image the windows would cross it: the matcher's value stays
    steep = np.tile([1.0, 3.0], (len(us), 1))
    kept = _match_crest((left.astype(np.uint8), right), us, crest, d, steep, cfg)
    np.testing.assert_array_equal(kept, d)


def test_crest_match_on_a_rendered_crater(crater_scene, sgbm_disparity):
    sc = crater_scene
    fit = fit_crater_ellipse(sc.left, sc.box)
    pair = (sc.left, sc.right)
    res = lift_crater(fit.ellipse, sgbm_disparity, sc.rig, LifterConfig(crest_match=True), pair)
    assert res.ok, res.reason
    assert np.hypot(*(res.center_m[:2] - sc.center_rover[:2])) < 0.3
    assert res.diameter_m == pytest.approx(sc.crater.diameter, abs=0.35)
    off = lift_crater(fit.ellipse, sgbm_disparity, sc.rig, LifterConfig(crest_match=False), pair)
    assert res.center_m[0] != off.center_m[0]  # the images were used


def test_a_failed_lift_is_retried_with_a_wider_crest_search(crater_scene_side_sun):
    """The ellipse 7 rows below the true crest: the 6-row search reads the flank below it
    (a spread over this tight gate), the 12-row retry finds the crest and passes."""
    sc = crater_scene_side_sun
    e = sc.ellipse
    low = Ellipse(e.cx, e.cy + 7.0, e.a, e.b, e.angle_deg)
    gate = {"max_rim_residual_px": 0.1, "max_rim_residual_rel": 0.0, **SHARP}
    disp = _true_disparity(sc)
    first = lift_crater(low, disp, sc.rig, LifterConfig(retry_snap_px=0, reach_far_arc=False, **gate))
    assert not first.ok and first.reason == "stereo_inconsistent"
    res = lift_crater(low, disp, sc.rig, LifterConfig(reach_far_arc=False, **gate))
    assert res.ok and res.crest_search_px == 12
    np.testing.assert_allclose(res.center_m[:2], sc.center_rover[:2], atol=0.1)
    # a retry that fails too leaves the first lift's reason
    lower = Ellipse(e.cx, e.cy + 8.0, e.a, e.b, e.angle_deg)  # beyond half the ellipse's height
    two = LifterConfig(reach_far_arc=False, **gate)
    assert lift_crater(lower, disp, sc.rig, two).reason == "stereo_inconsistent"
    assert lift_crater(e, disp, sc.rig, LifterConfig(**gate)).crest_search_px == 6


def test_the_lowest_step_rule_finds_a_crest_beyond_the_searches_cap(crater_scene_side_sun):
    """The ellipse 8 rows below the crest, beyond the searches' cap (half its height), and a
    tight gate: the largest-step lifts fail it; the lowest-step rule of the first search finds
    the crest as the lowest disparity step between the far arc and the cap."""
    sc = crater_scene_side_sun
    e = sc.ellipse
    low = Ellipse(e.cx, e.cy + 8.0, e.a, e.b, e.angle_deg)
    gate = {"max_rim_residual_px": 0.1, "max_rim_residual_rel": 0.0, **SHARP}
    disp = _true_disparity(sc)
    assert not lift_crater(low, disp, sc.rig, LifterConfig(reach_far_arc=False, **gate)).ok
    res = lift_crater(low, disp, sc.rig, LifterConfig(**gate))
    assert res.ok and res.crest_step == "lowest" and res.crest_search_px == 6
    np.testing.assert_allclose(res.center_m[:2], sc.center_rover[:2], atol=0.1)
    # on the crest both rules find it: their mean, or with the mean off the first rule's lift
    assert lift_crater(e, disp, sc.rig, LifterConfig(**gate)).crest_step == "both"
    first = LifterConfig(mean_rules_within=None, **gate)
    assert lift_crater(e, disp, sc.rig, first).crest_step == "largest"


def test_the_lowest_step_is_taken_not_the_largest():
    """A column with a far crest step (rows 40/41, 30 %) above the near crest's (rows 50/51,
    10 %): the lowest step of at least 8 % is the near crest, the largest the far one."""
    column = np.full(100, 5.0)
    column[41:] = 7.0
    column[51:] = 7.8
    assert _lowest_step(column, 53.0, top=38.0, snap_px=4, min_jump=0.08) == pytest.approx(50.5)
    assert _crest_row(column, 46.0, snap_px=6, min_jump=0.08) == pytest.approx(40.5)
    # no step of 8 % in reach: the point's own row
    assert _lowest_step(column, 53.0, top=52.0, snap_px=4, min_jump=0.08) == 53.0


def test_the_range_sigma_carries_the_rim_models_own_error(crater_scene):
    """Exact disparities leave the samples no spread; the range sigma is then the rim model's
    term, ``rim_model_sigma`` of the radius, along the line of sight."""
    sc = crater_scene
    disp = _true_disparity(sc)
    bare = lift_crater(sc.ellipse, disp, sc.rig, LifterConfig(rim_model_sigma=0.0, **SHARP))
    res = lift_crater(sc.ellipse, disp, sc.rig, LifterConfig(**SHARP))
    assert bare.ok and res.ok
    np.testing.assert_array_equal(res.center_m, bare.center_m)
    radius = sc.crater.diameter / 2
    model = LifterConfig().rim_model_sigma
    assert bare.horizontal_sigma_m < 0.3 * model * radius
    assert res.horizontal_sigma_m == pytest.approx(model * radius, rel=0.1)


def test_the_tries_widen_the_search_each_with_both_crest_rules():
    got = [[(c.snap_px, lowest) for c, lowest in s] for s in _tries(LifterConfig())]
    assert got == [[(6, False), (6, True)], [(12, False), (12, True)]]
    assert [[(c.snap_px, lw) for c, lw in s] for s in _tries(LifterConfig(reach_far_arc=False))] == [
        [(6, False)], [(12, False)]]
    assert [[(c.snap_px, lw) for c, lw in s] for s in _tries(LifterConfig(retry_snap_px=0))] == [
        [(6, False), (6, True)]]


def test_a_near_rim_hidden_behind_a_brow_is_rejected(crater_scene):
    """Level ground in front of the near rim, a little above its crest (a crater on a
    downslope, seen over a brow): the visible edge is the brow, not the crest."""
    sc = crater_scene
    disp = _true_disparity(sc)
    rim = lift_crater(sc.ellipse, disp, sc.rig, LifterConfig(**SHARP))
    assert rim.ok and rim.flank_rise_m > 0.05  # the outer flank lies below a visible crest
    brow = disp.copy()
    pts = sc.ellipse.points(720)
    near = pts[pts[:, 1] > sc.ellipse.cy]
    plateau = rim.rim_height_m + 0.05
    for u, v in near:
        rows = np.arange(int(np.ceil(v)), int(np.ceil(v)) + 25)
        uv = np.column_stack([np.full(len(rows), round(u)), rows]).astype(float)
        down = -(sc.rig.rays(uv) @ sc.rig.rotation.T)[:, 2]  # rover-frame drop per unit depth
        brow[rows, round(u)] = sc.rig.focal_px * sc.rig.baseline_m * down / (
            sc.rig.height_m - plateau)
    hidden = lift_crater(sc.ellipse, brow, sc.rig, LifterConfig(min_flank_rise_px=None, **SHARP))
    assert not hidden.ok and hidden.reason == "near_rim_hidden"  # the 0 m bound alone
    assert abs(hidden.flank_rise_m) < 0.03
    # unchecked, the lift reads the brow: the crater comes out too near
    read = lift_crater(sc.ellipse, brow, sc.rig,
                       LifterConfig(min_flank_rise_m=None, min_flank_rise_px=None, **SHARP))
    assert read.ok
    assert np.hypot(*read.center_m[:2]) < np.hypot(*sc.center_rover[:2]) - 0.1


def test_the_hidden_rim_test_read_as_disparity(crater_scene):
    """``min_flank_rise_px``: the rise as the disparity it moves a point at the crest by
    (rise x d / H): a threshold just over that rejects the lift, just under keeps it as is."""
    sc = crater_scene
    disp = _true_disparity(sc)
    rim = lift_crater(sc.ellipse, disp, sc.rig, LifterConfig(**SHARP))
    assert rim.ok and rim.flank_rise_m > 0.05
    px = rim.flank_rise_m * rim.rim_disparity_px / sc.rig.height_m
    over = lift_crater(sc.ellipse, disp, sc.rig, LifterConfig(min_flank_rise_px=1.01 * px, **SHARP))
    assert not over.ok and over.reason == "near_rim_hidden"
    under = lift_crater(sc.ellipse, disp, sc.rig,
                        LifterConfig(min_flank_rise_px=0.99 * px, **SHARP))
    assert under.ok
    np.testing.assert_array_equal(under.center_m, rim.center_m)


def test_of_two_passing_crest_rules_the_farther_lift_is_kept(crater_scene_side_sun):
    """The ellipse 8 rows below the crest with a loose gate: the largest-step lift passes but
    reads the flank below the crest, too near; the lowest-step lift finds the crest."""
    sc = crater_scene_side_sun
    e = sc.ellipse
    low = Ellipse(e.cx, e.cy + 8.0, e.a, e.b, e.angle_deg)
    disp = _true_disparity(sc)
    truth = np.hypot(*sc.center_rover[:2])
    flank = lift_crater(low, disp, sc.rig, LifterConfig(reach_far_arc=False, **SHARP))
    assert flank.ok and flank.crest_step == "largest"
    assert np.hypot(*flank.center_m[:2]) < truth - 0.3
    res = lift_crater(low, disp, sc.rig, LifterConfig(**SHARP))
    assert res.ok and res.crest_step == "lowest" and res.crest_search_px == 6
    np.testing.assert_allclose(res.center_m[:2], sc.center_rover[:2], atol=0.1)


def test_two_crest_rules_that_agree_give_their_mean(crater_scene_side_sun):
    """The same two lifts as above: 0.3 m or more apart, so a 1 % tolerance keeps the farther;
    a tolerance wide enough to take both gives their mean."""
    sc = crater_scene_side_sun
    e = sc.ellipse
    low = Ellipse(e.cx, e.cy + 8.0, e.a, e.b, e.angle_deg)
    disp = _true_disparity(sc)
    flank = lift_crater(low, disp, sc.rig, LifterConfig(reach_far_arc=False, **SHARP))
    crest = lift_crater(low, disp, sc.rig, LifterConfig(**SHARP))
    tight = lift_crater(low, disp, sc.rig, LifterConfig(mean_rules_within=0.01, **SHARP))
    assert tight.crest_step == "lowest"
    np.testing.assert_array_equal(tight.center_m, crest.center_m)
    wide = lift_crater(low, disp, sc.rig, LifterConfig(mean_rules_within=0.5, **SHARP))
    assert wide.ok and wide.crest_step == "both" and wide.crest_search_px == 6
    np.testing.assert_allclose(wide.center_m, 0.5 * (flank.center_m + crest.center_m))
    np.testing.assert_allclose(wide.diameter_m, 0.5 * (flank.diameter_m + crest.diameter_m))


def test_the_mean_of_two_lifts_and_when_they_agree():
    def lift(x, d, step):
        return LiftResult(True, "ok", np.array([x, 0.0, 0.5]), d, np.eye(4) * x,
                          crest_step=step, rim_disparity_px=x)
    near, far = lift(10.0, 5.0, "largest"), lift(10.15, 5.2, "lowest")
    assert _rules_agree(near, far, 0.02) and _rules_agree(far, near, 0.02)
    assert not _rules_agree(near, far, 0.01) and not _rules_agree(near, far, None)
    m = _mean_lift(near, far)
    np.testing.assert_allclose(m.center_m, [10.075, 0.0, 0.5])
    assert m.diameter_m == pytest.approx(5.1) and m.crest_step == "both"
    np.testing.assert_allclose(m.covariance, np.eye(4) * 10.075)
    assert m.rim_disparity_px == 10.15  # the farther lift's diagnostics


def test_rows_needed_leave_room_above_a_box_for_a_fitted_ellipse():
    first, last = rows_needed(np.array([[100.0, 200.0, 300.0, 80.0]]), 1024)
    assert first <= 200 - 0.25 * 80 - 4 and last == 200 + 80 * 5.5 + 50
    assert rows_needed(np.array([[0.0, 300.0, 50.0, 8.0]]), 1024)[0] == 290  # small: 10 rows
    assert rows_needed(np.array([[0.0, 5.0, 50.0, 8.0]]), 1024)[0] == 0


def test_load_edge_offsets_reads_a_calibration_and_names_bad_fields(tmp_path):
    from lunarnav_ml.geometry.lifter import load_edge_offsets

    path = tmp_path / "rim_offset.json"
    box = {"box_rim_offset": 0.1, "box_rim_offset_m": -0.2, "box_rim_offset_view": 0.3,
           "n_lifted": 5}
    path.write_text(json.dumps({"fitted_ellipses": None, "box_ellipses": box}))
    cfg = load_edge_offsets(path)
    default = LifterConfig()
    assert (cfg.box_rim_offset, cfg.box_rim_offset_m, cfg.box_rim_offset_view) == (0.1, -0.2, 0.3)
    assert cfg.rim_offset == default.rim_offset and cfg.snap_px == default.snap_px
    path.write_text(json.dumps({"box_ellipses": {**box, "box_rim_offset_m": "x"}}))
    with pytest.raises(InputError, match=r"box_ellipses\.box_rim_offset_m"):
        load_edge_offsets(path)
    path.write_text(json.dumps({"fitted_ellipses": None}))
    with pytest.raises(InputError, match="no edge offsets"):
        load_edge_offsets(path)
    with pytest.raises(InputError, match="not found"):
        load_edge_offsets(tmp_path / "none.json")


def test_the_shipped_legacy_offsets_load():
    from pathlib import Path

    from lunarnav_ml.geometry.lifter import load_edge_offsets

    path = Path(__file__).resolve().parents[2] / "configs/geometry/legacy_crest_edge_offsets.json"
    cfg = load_edge_offsets(path)
    assert (cfg.rim_offset, cfg.box_rim_offset_view) == (0.0726, -0.1880)
